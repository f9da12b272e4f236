"""Mouth / inner-lip regions and the inner-lip loop (Dinev et al. 2018 §4, Fig. 2)."""

import numpy as np
import pytest

from facelab_addon.core.errors import RegionError
from facelab_addon.core.geometry import geodesic
from facelab_addon.core.geometry.mesh import vertex_adjacency
from facelab_addon.core.lips import lip_loop, regions


def grid(n=7, m=None):
    from facelab_addon.testing.meshes import grid_mesh

    return grid_mesh(np.arange(n, dtype=float), np.arange(n if m is None else m, dtype=float))


def tube(n_around=12, n_up=4):
    t = np.linspace(0, 2 * np.pi, n_around, endpoint=False)
    V = np.array([[np.cos(a), np.sin(a), h] for h in range(n_up) for a in t])
    F = []
    for h in range(n_up - 1):
        for i in range(n_around):
            a, b = h * n_around + i, h * n_around + (i + 1) % n_around
            F += [[a, b, b + n_around], [a, b + n_around, a + n_around]]
    return V, np.array(F)


def tetra(offset):
    V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]) + offset
    F = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    return V, F


# ---------------------------------------------------------------- triangle sets


def test_faces_in_region_needs_all_three_vertices():
    V, F = grid(4)  # 16 vertices, vertex (i, j) = 4 i + j
    mask = np.zeros(16, bool)
    mask[[0, 1, 4, 5, 2]] = True  # the first quad plus one extra vertex
    got = regions.faces_in_region(F, mask)
    np.testing.assert_array_equal(got, [0, 1])  # the two triangles of quad (0,0)
    # vertex indices work like a mask
    np.testing.assert_array_equal(regions.faces_in_region(F, [0, 1, 4, 5, 2]), [0, 1])


def test_region_border_is_shared_with_outside_triangles():
    V, F = grid(7)
    rows = (V[:, 0] >= 2) & (V[:, 0] <= 4)  # a strip of rows 2..4
    lf = regions.faces_in_region(F, rows)
    assert len(lf) == 2 * 6 * 2
    border = regions.region_border(F, lf, len(V))
    # rows 2 and 4 touch outside triangles; row 3 (open mesh ends included) does not
    expected = np.flatnonzero((V[:, 0] == 2) | (V[:, 0] == 4))
    np.testing.assert_array_equal(border, expected)


def test_validate_regions_errors():
    V, F = grid(7)
    lips = regions.faces_in_region(F, (V[:, 0] >= 2) & (V[:, 0] <= 4))
    mouth = regions.faces_in_region(F, (V[:, 0] <= 2) | (V[:, 0] >= 4))
    mf, lf = regions.validate_regions(F, mouth, lips, len(V))
    assert len(np.intersect1d(mf, lf)) == 0
    with pytest.raises(RegionError, match="inner-lip region is empty.*Auto Regions"):
        regions.validate_regions(F, mouth, [], len(V))
    with pytest.raises(RegionError, match="mouth region is empty"):
        regions.validate_regions(F, np.array([], int), lips, len(V))
    with pytest.raises(RegionError, match="overlap in 2 triangles"):
        regions.validate_regions(F, np.r_[mouth, lips[:2]], lips, len(V))
    with pytest.raises(RegionError, match="refers to triangle"):
        regions.validate_regions(F, mouth, [len(F)], len(V))
    # a lip region that is a whole closed piece has no border
    Vt, Ft = tetra(10.0)
    V2, F2 = np.r_[V, Vt], np.r_[F, Ft + len(V)]
    tet = np.arange(len(F), len(F2))
    with pytest.raises(RegionError, match="no border"):
        regions.validate_regions(F2, mouth, tet, len(V2))
    with pytest.raises(RegionError, match="1 piece.*no border vertex"):
        regions.validate_regions(F2, mouth, np.r_[lips, tet], len(V2))


def test_order_edge_loop():
    V, F = tube()
    ring = np.arange(12, 24)  # the second ring of the tube
    rng = np.random.default_rng(0)
    got = lip_loop.order_edge_loop(F, rng.permutation(ring))
    A = vertex_adjacency(F, len(V))
    assert set(got.tolist()) == set(ring.tolist())
    assert all(A[got[i], got[(i + 1) % 12]] for i in range(12))
    np.testing.assert_array_equal(lip_loop.order_edge_loop(F, ring), ring)  # an ordered loop is kept
    with pytest.raises(RegionError, match="not a single closed edge loop"):
        lip_loop.order_edge_loop(F, ring[:-1])
    with pytest.raises(RegionError, match="more than one closed loop"):
        lip_loop.order_edge_loop(F, np.r_[ring, ring + 24])


def test_geodesic_distance_on_a_plane_is_euclidean():
    V, F = grid(9)
    V = V * [1.0, 0.7, 0.0]
    d = geodesic.geodesic_distance(V, F, [40], limit=3.0)
    e = np.linalg.norm(V - V[40], axis=1)
    inside = e <= 2.5
    np.testing.assert_allclose(d[inside], e[inside], atol=1e-9)
    assert np.isinf(d[e > 4.5]).all()
    de = geodesic.geodesic_distance(V, F, [40], limit=3.0, exact=False)
    assert (de[inside] >= e[inside] - 1e-12).all() and de[inside].max() > e[inside].max()


def test_no_mouth_raises():
    V, F = grid(9)
    with pytest.raises(RegionError, match="select the inner-lip edge loop"):
        lip_loop.inner_lip_loop(V, F)


# ---------------------------------------------------------------- ICT-FaceKit


@pytest.fixture(scope="module")
def ict_regions(ict):
    """The ICT model and its Auto Regions: (model, inner-lip loop, mouth vertex mask, lip vertex mask)."""
    mouth, lip, dist, loop = regions.auto_regions(ict.neutral, ict.faces, return_distance=True)
    return ict, loop, mouth, lip


def halves(V, loop):
    a, b = sorted((int(np.argmin(V[loop, 0])), int(np.argmax(V[loop, 0]))))
    return loop[a : b + 1], np.r_[loop[b:], loop[: a + 1]]


def test_ict_inner_lip_loop_is_the_contact_line(ict_regions):
    m, loop, _, _ = ict_regions
    V, F = m.neutral, m.faces
    A = vertex_adjacency(F, len(V))
    assert len(np.unique(loop)) == len(loop) > 40
    assert all(A[loop[i], loop[(i + 1) % len(loop)]] for i in range(len(loop)))  # closed edge loop
    P = V[loop]
    # on the lips (ICT: cm, x = mouth width, y up), spanning corner to corner
    assert np.abs(P[:, 0]).max() < 2.7 and P[:, 0].max() - P[:, 0].min() > 4.0
    assert (P[:, 1] > -3.8).all() and (P[:, 1] < -3.0).all()
    assert m.part_vertex_mask("M_Face")[loop].all()
    # the two halves are the upper and lower lip, nearly touching (neutral gap ~1 mm)
    h1, h2 = halves(V, loop)
    d = np.linalg.norm(V[h1][:, None] - V[h2][None], axis=2).min(axis=1)
    assert np.median(d) < 0.15 and d.max() < 0.3
    assert abs(V[h1, 1].mean() - V[h2, 1].mean()) < 0.2


def test_ict_loop_is_invariant_to_units_rotation_and_vertex_order(ict_regions):
    m, loop, _, _ = ict_regions
    rng = np.random.default_rng(3)
    perm = rng.permutation(len(m.neutral))  # new vertex i is old vertex perm[i]
    inv = np.argsort(perm)
    Q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    X = (m.neutral @ Q.T * 0.01)[perm]  # metres, rotated, shuffled
    got = lip_loop.inner_lip_loop(X, inv[m.faces])
    assert set(perm[got].tolist()) == set(loop.tolist())


def test_ict_auto_regions(ict_regions):
    m, loop, mouth, lip = ict_regions
    V, F = m.neutral, m.faces
    assert lip[loop].all() and not (mouth & ~lip)[loop].any()
    mf, lf = regions.faces_in_region(F, mouth), regions.faces_in_region(F, lip)
    regions.validate_regions(F, mf, lf, len(V))  # no overlap, lip border exists
    # the mouth region is skin around the mouth, not the mouth bag (ICT part M_BackHead)
    assert not (mouth & ~lip & m.part_vertex_mask("M_BackHead")).any()
    assert not (mouth | lip)[m.part_vertex_mask("M_Teeth", "M_GumsTongue")].any()
    # widths are relative to the mouth: about 5 mm of lip and 2 cm of mouth on ICT (cm)
    d = geodesic.geodesic_distance(V, F, loop, limit=5.0)
    W = lip_loop.loop_width(V, loop)  # mouth corner to corner: ICT's mouth is about 4.4 cm wide
    assert 4.0 < W < 5.0
    assert d[lip].max() <= regions.DEFAULT_LIP_WIDTH * W * 1.01
    assert 0.8 * regions.DEFAULT_LIP_WIDTH * W < d[lip].max()
    assert (regions.DEFAULT_LIP_WIDTH + regions.DEFAULT_MOUTH_WIDTH) * W * 0.9 < d[mouth].max()
    assert 600 < lip.sum() < 1500 and 500 < (mouth & ~lip).sum() < 2000
    # on the face side the border ring is shared: a border vertex next to the mouth band is in both
    border = regions.region_border(F, lf, len(V))
    A = vertex_adjacency(F, len(V))
    next_to_band = (A @ (mouth & ~lip).astype(float))[border] > 0
    # (0.85: which border vertices a doubly assigned triangle gives up depends on geodesic ties at the band edge;
    # on the same loop this share moves between 0.91 and 0.98 when the band widths change by 2 %)
    assert next_to_band.sum() > 50 and mouth[border[next_to_band]].mean() > 0.85
    # so lip and mouth triangles are adjacent: no gap of ignored triangles between them
    touching = mouth[F[lf]].sum(axis=1) == 2
    assert touching.sum() > 50
    # an explicit (shuffled) loop gives the same regions; so does a metre scene
    m2, l2 = regions.auto_regions(V, F, loop=np.random.default_rng(0).permutation(loop))
    np.testing.assert_array_equal(m2, mouth)
    np.testing.assert_array_equal(l2, lip)
    m3, l3 = regions.auto_regions(V * 0.01, F, loop=loop)
    np.testing.assert_array_equal(l3, lip)
    assert (m3 != mouth).sum() <= 2  # geodesic ties at the band edge may flip
    np.testing.assert_array_equal(regions.inner_lip_vertices(V, F, loop=loop), lip)
    with pytest.raises(RegionError, match="positive"):
        regions.auto_regions(V, F, loop=loop, lip_width=-1.0)


def test_ict_wider_lip_band_pushes_the_mouth_band_outward(ict_regions):
    """A wider FL_lips (0.2 mouth widths) keeps FL_mouth a full-width band right outside it (issue 11).

    So the trusted input of Propagate is as wide as with the default band; the few-frame Propagate
    difference between the two widths (benchmarks/lip_band.py) comes from the lip band itself.
    """
    m, loop, mouth0, _ = ict_regions
    V, F = m.neutral, m.faces
    W = lip_loop.loop_width(V, loop)
    lw, mw = 0.2 * W, regions.DEFAULT_MOUTH_WIDTH * W
    mouth, lip, d, _ = regions.auto_regions(V, F, loop=loop, lip_width=lw, mouth_width=mw, return_distance=True)
    band = mouth & ~lip
    assert d[lip].max() <= lw and 0.9 * lw < d[lip].max()
    assert (d[band] > lw).all() and (d[band] <= lw + mw).all() and d[band].max() > 0.9 * (lw + mw)
    assert d[band].min() < lw + 0.1 * W  # starts at the lip border, no gap of ignored skin
    assert band.sum() > 0.8 * (mouth0 & ~regions.auto_regions(V, F, loop=loop)[1]).sum()
    regions.validate_regions(F, regions.faces_in_region(F, mouth), regions.faces_in_region(F, lip), len(V))


def test_lip_faces_duplicated_in_place_are_named_as_duplicates():
    """Lip faces duplicated in place (Shift+D, move cancelled: new vertices on the old ones, in the same groups)
    make a borderless piece of the inner-lip region. The message named the new vertices only; it now says they
    are duplicates lying on other vertices and how to remove them (Propagate's regressor says the same)."""
    from facelab_addon.core.errors import RegionError
    from facelab_addon.core.lips.regressor import LipRegressor
    from facelab_addon.testing.meshes import grid_mesh

    V, F = grid_mesh(np.arange(12, dtype=float), np.arange(10, dtype=float), lambda x, y: 0.3 * np.sin(0.5 * x))
    y = V[:, 1]
    mouth, lips = regions.faces_in_region(F, (y <= 3) | (y >= 6)), regions.faces_in_region(F, (y >= 3) & (y <= 6))
    dup_faces = lips[:6]
    used = np.unique(F[dup_faces])
    new = len(V) + np.arange(len(used))
    V2 = np.vstack([V, V[used]])  # the copies, exactly on the originals
    remap = np.arange(len(V))
    remap[used] = new
    F2 = np.vstack([F, remap[F[dup_faces]]])
    lips2 = np.r_[lips, len(F) + np.arange(len(dup_faces))]
    with pytest.raises(RegionError, match=r"no border vertex \(first vertices \["):  # without positions, as before
        regions.validate_regions(F2, mouth, lips2, len(V2))
    msg = (rf"their {len(used)} vertices \(first \[{new[0]}, .*are duplicates lying exactly on other vertices "
           rf"\(first \[{used[0]}, .*Merge by Distance")
    with pytest.raises(RegionError, match=msg):
        regions.validate_regions(F2, mouth, lips2, len(V2), V2)
    with pytest.raises(RegionError, match=msg):
        LipRegressor(V2, F2, mouth, lips2)
