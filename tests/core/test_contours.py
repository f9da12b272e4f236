"""Occluding contours and curve correspondence (Bhat et al. 2013, §4.2) and eyelids on the eyeball (§4.1).

The analytic "mouth" is a band of a torus around the z axis: the tube's
cross-section circles are the lip roll, its latitude circles the concentric
edge loops. Seen from a camera on the axis at distance D, the point at tube
angle phi (position ((R + r cos phi) cos theta, (R + r cos phi) sin theta,
r sin phi), outward normal (cos phi cos theta, cos phi sin theta, sin phi)) is
on the silhouette when n . (c - p) = D sin phi - R cos phi - r = 0, so the
inner silhouette (the one bounding the mouth opening) is at

    phi* = pi + atan2(R, D) - asin(r / sqrt(D^2 + R^2)).

The loops are placed so that loop ``k_sil`` lies exactly at phi*.
"""

import time

import numpy as np
import pytest

from facelab_addon.core.capture.camera import Camera
from facelab_addon.core.errors import FaceLabError, MeshError
from facelab_addon.core.geometry.polyline import (
    point_to_polyline_distance,
    resample_polyline,
)
from facelab_addon.core.geometry.silhouette import silhouette_edges
from facelab_addon.core.geometry.sphere import fit_sphere, project_to_sphere, ray_sphere
from facelab_addon.core.solve.contour_loops import TrackedCurve, contour_loops
from facelab_addon.core.solve.matching import (
    CurveCorrespondence,
    MatchParams,
    half_points,
    contour_residuals,
    match_contours,
)
from facelab_addon.core.solve.occlusion import (
    envelope_counts,
    half_silhouette_counts,
    select_occluding_loop,
    silhouette_edge_counts,
)
from facelab_addon.testing.contour_truth import (
    ict_contour_loops,
    synthetic_tracked_curves,
)

R_TORUS, R_TUBE, DIST = 2.0, 0.5, 12.0
PHI_SIL = np.pi + np.arctan2(R_TORUS, DIST) - np.arcsin(R_TUBE / np.hypot(DIST, R_TORUS))
STEP = np.pi / 14


def torus_band(k_sil=3, n_rings=9, n_around=50, roll=0.0, phi_sil=PHI_SIL):
    """Band of the torus with latitude loops phi_k = PHI_SIL + (k_sil - k) STEP - roll, k = 0..n_rings-1.

    Ring 0 (deepest inside the mouth) is the band's inner border; ring k_sil is the silhouette from the
    axis camera when roll = 0. ``roll`` rotates every cross-section (a lip roll moving the silhouette).
    Returns V (n_rings*n_around, 3), F, ring vertex ids (list).
    """
    phis = phi_sil + (k_sil - np.arange(n_rings)) * STEP - roll
    th = np.linspace(0, 2 * np.pi, n_around, endpoint=False)
    P, T = np.meshgrid(phis, th, indexing="ij")
    rho = R_TORUS + R_TUBE * np.cos(P)
    V = np.stack([rho * np.cos(T), rho * np.sin(T), R_TUBE * np.sin(P)], -1).reshape(-1, 3)
    F = []
    for k in range(n_rings - 1):
        for i in range(n_around):
            a, b = k * n_around + i, k * n_around + (i + 1) % n_around
            c, d = b + n_around, a + n_around
            F += [[a, b, c], [a, c, d]]
    F = np.array(F)
    # outward normals (away from the tube's centre circle)
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    cen = V[F].mean(1)
    rad = cen.copy()
    rad[:, 2] = 0
    core = rad / np.linalg.norm(rad, axis=1, keepdims=True) * R_TORUS
    if (np.einsum("ij,ij->i", n, cen - core) < 0).mean() > 0.5:
        F = F[:, ::-1]
    rings = [np.arange(k * n_around, (k + 1) * n_around) for k in range(n_rings)]
    return V, F, rings


def axis_camera(dist=DIST):
    return Camera.look_at([0, 0, dist], [0, 0, 0], [0, 1, 0], 50, 36, 1920, 1080)


@pytest.fixture(scope="module")
def band():
    V, F, rings = torus_band()
    loops = contour_loops(V, F, mouth_loop=rings[0], n_mouth_loops=len(rings))
    return V, F, rings, loops


# ----------------------------------------------------------------- candidates


def test_rings_grown_from_the_border_are_the_latitude_loops(band):
    V, F, rings, loops = band
    assert len(loops.mouth) == len(rings)
    for got, want in zip(loops.mouth, rings):
        assert sorted(got.tolist()) == want.tolist()
        # ordered: consecutive vertices are mesh neighbours one step apart around the axis
        ang = np.arctan2(V[got, 1], V[got, 0])
        step = np.abs(np.angle(np.exp(1j * (np.roll(ang, -1) - ang))))
        np.testing.assert_allclose(step, 2 * np.pi / 50, atol=1e-9)
    assert loops.eyes == {} and loops.curve_names() == ["mouth_upper", "mouth_lower"]


def test_split_points_are_the_corners_and_the_lip_middle(band):
    V, F, rings, loops = band
    for k, lp in enumerate(loops.mouth):
        rho = np.hypot(V[lp[0], 0], V[lp[0], 1])
        z = V[lp[0], 2]
        # corners: the extreme vertices along lateral = up x forward = +x
        np.testing.assert_allclose(V[loops.mouth_corners[k]], [[-rho, 0, z], [rho, 0, z]], atol=1e-12)
        for name, sign in (("mouth_upper", 1), ("mouth_lower", -1)):
            h = loops.halves[name][k]
            X = h.bary[:, :1] * V[h.vertices[:, 0]] + h.bary[:, 1:] * V[h.vertices[:, 1]]
            S = X[h.splits]
            assert len(h.splits) == 3
            np.testing.assert_allclose(S[0], [-rho, 0, z], atol=1e-12)
            np.testing.assert_allclose(S[2], [rho, 0, z], atol=1e-12)
            # middle: on the chord crossing x = 0 (50 vertices: theta = pi/2 is between two vertices)
            assert abs(S[1, 0]) < 1e-12 and np.sign(S[1, 1]) == sign
            np.testing.assert_allclose(abs(S[1, 1]), rho * np.cos(np.pi / 50), rtol=1e-12)
            # the half runs over its own side only
            assert (sign * X[1:-1, 1] > 0).all()


# ------------------------------------------------------------------ selection


@pytest.mark.parametrize("k_sil", [2, 3, 5])
def test_selection_picks_the_analytic_silhouette_loop(k_sil):
    V, F, rings = torus_band(k_sil=k_sil)
    cam = axis_camera()
    counts = silhouette_edge_counts(V, F, cam, rings)
    assert counts[k_sil] == 50 and counts.sum() == 50  # every edge of that loop, no other
    assert select_occluding_loop(V, F, cam, rings) == k_sil
    # the brute-force silhouette of the whole mesh agrees
    E = {tuple(e) for e in silhouette_edges(V, F, cam)}
    lp = rings[k_sil]
    assert {tuple(sorted(e)) for e in zip(lp, np.roll(lp, -1))} <= E
    # per-half selection inside match_contours picks it too
    loops = contour_loops(V, F, mouth_loop=rings[0], n_mouth_loops=len(rings))
    curves = synthetic_tracked_curves(V, F, [cam], loops)
    corr = match_contours(V, F, [cam], curves, loops)
    assert [c.loop for c in corr] == [k_sil, k_sil]


def test_only_silhouettes_bounding_the_opening_count():
    """The torus's outer equator is a silhouette too, but there the surface lies on the opening's side of it."""
    cam = axis_camera()
    phi_out = np.arctan2(R_TORUS, DIST) + np.arcsin(R_TUBE / np.hypot(DIST, R_TORUS))  # D sin - R cos = r, near 0
    V, F, rings = torus_band(k_sil=3, phi_sil=phi_out)
    assert silhouette_edge_counts(V, F, cam, rings)[3] == 50
    loops = contour_loops(V, F, mouth_loop=rings[0], n_mouth_loops=len(rings))
    assert half_silhouette_counts(V, cam, loops, inner=False).max() == 25  # each half of ring 3
    assert half_silhouette_counts(V, cam, loops).max() == 0  # an outer outline, not an inner-lip line
    # the inner silhouette of the same torus counts fully
    V, F, rings = torus_band(k_sil=3)
    loops = contour_loops(V, F, mouth_loop=rings[0], n_mouth_loops=len(rings))
    np.testing.assert_array_equal(half_silhouette_counts(V, cam, loops), half_silhouette_counts(V, cam, loops, inner=False))
    assert half_silhouette_counts(V, cam, loops)[[3, 3 + len(rings)]].tolist() == [25, 25]


def test_fast_counts_match_brute_force_silhouettes_on_ict(ict, ict_loops):
    V = ict.pose({"jawOpen": 0.4, "mouthFunnel": 0.6})
    cam = Camera.look_at(V[6632:6706].mean(0) + [3, -5, 30], V[6632:6706].mean(0), [0, 1, 0], 35, 36, 1920, 1080)
    E = {tuple(e) for e in silhouette_edges(V, ict.faces, cam)}
    fast = half_silhouette_counts(V, cam, ict_loops, inner=False)
    for name in ict_loops.curve_names():
        lo, hi = ict_loops._pack[4][name]
        brute = [sum(tuple(sorted(e)) in E for e in zip(h.chain[:-1], h.chain[1:])) for h in ict_loops.halves[name]]
        np.testing.assert_array_equal(fast[lo:hi], brute)


# ------------------------------------------------------------------- matching


def _circle_curve(cam, radius, z, upper=True, n=4001):
    """Finely sampled projected semicircle (the tracked curve), left to right."""
    th = np.linspace(np.pi, 0, n) if upper else np.linspace(np.pi, 2 * np.pi, n)
    X = np.stack([radius * np.cos(th), radius * np.sin(th), np.full(n, z)], 1)
    return cam.project(X)


def test_arc_length_matching_on_a_circle_gives_the_analytic_parameters(band):
    """Axis camera: the ring projects to a regular polygon, the curve to a circle of another radius.

    Corners go to the curve's ends, the lip middle to its top, and a loop vertex at angle theta to the
    curve point at the same angle (equal chords: arc-length fraction = angle fraction).
    """
    V, F, rings, loops = band
    cam = axis_camera()
    k = 3
    rho, z = np.hypot(*V[rings[k][0], :2]), V[rings[k][0], 2]
    r_curve = 0.9 * rho
    for reverse in (False, True):
        C = _circle_curve(cam, r_curve, z)
        C = C[::-1] if reverse else C
        corr = match_contours(V, F, [cam], [TrackedCurve("mouth_upper", 0, C)], loops)[0]
        assert corr.loop == k and corr.camera == 0 and corr.targets is None
        X = corr.evaluate(V)
        theta = np.arctan2(X[:, 1], X[:, 0])
        # expected target: the curve's point at theta; a polygon's chords: arc fraction of a vertex is exact,
        # the middle point (on a chord) sits at the curve's top
        want = cam.project(np.stack([r_curve * np.cos(theta), r_curve * np.sin(theta), np.full(len(X), z)], 1))
        mid = corr.vertices[:, 0] != corr.vertices[:, 1]
        mid &= (corr.bary[:, 1] > 0)
        want[mid] = cam.project([[0, r_curve, z]])
        np.testing.assert_allclose(corr.pixels, want, atol=2e-3)
        np.testing.assert_allclose(corr.curve_t[[0, -1]], [0, 1], atol=1e-12)
        assert np.all(np.diff(corr.curve_t) > 0)


def test_corner_beyond_the_curve_end_snaps_to_the_end_and_interior_is_arc_length(band):
    """A straight tracked line shorter than the contour: hand-computed targets."""
    V, F, rings, loops = band
    cam = axis_camera()
    corr0 = match_contours(V, F, [cam], [TrackedCurve("mouth_lower", 0, _circle_curve(cam, 1.5, 0.0, False))],
                              loops)[0]
    k = corr0.loop
    h = loops.halves["mouth_lower"][k]
    P = cam.project(corr0.evaluate(V))
    a, b, y = 700.0, 1220.0, 700.0  # line from (a, y) to (b, y); corners project outside [a, b]
    assert P[0, 0] < a and P[-1, 0] > b
    line = np.array([[a, y], [0.5 * (a + b) + 13.0, y], [b, y]])  # an extra, off-centre vertex
    corr = match_contours(V, F, [cam], [TrackedCurve("mouth_lower", 0, line)], loops)[0]
    u = np.r_[0, np.cumsum(np.linalg.norm(np.diff(P, axis=0), axis=1))]
    i0, im, i1 = h.splits
    xm = P[im, 0]  # the middle projects straight down onto the line
    want = np.empty(len(P))
    want[: im + 1] = a + (u[: im + 1] - u[0]) / (u[im] - u[0]) * (xm - a)
    want[im:] = xm + (u[im:] - u[im]) / (u[i1] - u[im]) * (b - xm)
    np.testing.assert_allclose(corr.pixels[:, 0], want, atol=1e-9)
    np.testing.assert_allclose(corr.pixels[:, 1], y)
    np.testing.assert_allclose(corr.curve_t, (want - a) / (b - a), atol=1e-12)


def test_sliding_follows_the_roll_and_fixed_keeps_the_previous_assignment():
    cam = axis_camera()
    V0, F, rings = torus_band(k_sil=3)
    loops = contour_loops(V0, F, mouth_loop=rings[0], n_mouth_loops=len(rings))
    c0 = synthetic_tracked_curves(V0, F, [cam], loops)
    prev = match_contours(V0, F, [cam], c0, loops)
    assert [p.loop for p in prev] == [3, 3]
    # roll every cross-section by two loop steps: the silhouette moves to loop 1
    V1, _, _ = torus_band(k_sil=3, roll=2 * STEP)
    c1 = synthetic_tracked_curves(V1, F, [cam], loops)
    slide = match_contours(V1, F, [cam], c1, loops, previous=prev)
    assert [s.loop for s in slide] == [1, 1]
    for r in contour_residuals(V1, [cam], slide):
        assert r.max() < 0.05
    fixed = match_contours(V1, F, [cam], c1, loops, previous=prev, sliding=False)
    for f, p, cv in zip(fixed, prev, c1):
        assert f.loop == p.loop == 3
        np.testing.assert_array_equal(f.vertices, p.vertices)
        np.testing.assert_array_equal(f.bary, p.bary)
        np.testing.assert_array_equal(f.curve_t, p.curve_t)
        # targets: the new curve at the old normalised arc length
        C = cv.pixels
        s = np.r_[0, np.cumsum(np.linalg.norm(np.diff(C, axis=0), axis=1))]
        want = np.stack([np.interp(p.curve_t * s[-1], s, C[:, 0]), np.interp(p.curve_t * s[-1], s, C[:, 1])], 1)
        np.testing.assert_allclose(f.pixels, want, atol=1e-9)
    # the fixed contour (loop 3) no longer lies on the new silhouette: large residual, sliding does not
    assert max(r.max() for r in contour_residuals(V1, [cam], fixed)) > 5.0
    # without previous, sliding=False matches normally (the first frame of a fixed run)
    first = match_contours(V1, F, [cam], c1, loops, sliding=False)
    assert [f.loop for f in first] == [1, 1]


def test_previous_loop_wins_ties():
    cam = axis_camera()
    V, F, rings = torus_band(k_sil=3)
    loops = contour_loops(V, F, mouth_loop=rings[0], n_mouth_loops=len(rings))
    # flatten the band into a planar annulus: no loop has a silhouette edge, all tie at zero
    ang = np.arctan2(V[:, 1], V[:, 0])
    rad = 1.0 + 0.1 * np.repeat(np.arange(len(rings)), 50)
    Vf = np.stack([rad * np.cos(ang), rad * np.sin(ang), np.zeros(len(V))], 1)
    C = synthetic_tracked_curves(V, F, [cam], loops)
    prev = [CurveCorrespondence("mouth_upper", 0, np.zeros((1, 2), int), np.ones((1, 2)) / 2, loop=6,
                                   curve_t=np.zeros(1), source_camera=0)]
    out = match_contours(Vf, F, [cam], C[:1], loops, previous=prev)
    assert half_silhouette_counts(Vf, cam, loops).max() == 0
    assert out[0].loop == 6
    # without previous: the loop closest to the curve
    out = match_contours(Vf, F, [cam], C[:1], loops)
    P = [cam.project(Vf[h.chain]) for h in loops.halves["mouth_upper"]]
    d = [np.mean(point_to_polyline_distance(p, C[0].pixels)) for p in P]
    assert out[0].loop == int(np.argmin(d))


def test_correspondence_matrix_and_evaluate_agree(band):
    V, F, rings, loops = band
    cam = axis_camera()
    corr = match_contours(V, F, [cam], synthetic_tracked_curves(V, F, [cam], loops), loops)
    for c in corr:
        A = c.matrix(len(V))
        np.testing.assert_allclose(A @ V, c.evaluate(V), atol=1e-14)
        np.testing.assert_allclose(c.evaluate(np.stack([V, 2 * V]))[1], 2 * c.evaluate(V))
        np.testing.assert_allclose(c.bary.sum(1), 1.0)


# ---------------------------------------------------------------- eyes / cornea


def test_fit_sphere_recovers_a_known_sphere():
    rng = np.random.default_rng(1)
    d = rng.normal(size=(200, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d = d[d[:, 2] > 0.2]  # a cap only, as an eyeball's visible part
    c, r = fit_sphere(np.array([1.0, -2.0, 3.0]) + 0.7 * d)
    np.testing.assert_allclose(c, [1, -2, 3], atol=1e-10)
    assert abs(r - 0.7) < 1e-10
    with pytest.raises(FaceLabError, match="coplanar"):
        fit_sphere(np.c_[rng.normal(size=(10, 2)), np.zeros(10)])


def test_cornea_projection_equals_the_analytic_ray_sphere_intersection():
    cam = Camera.look_at([0.5, -1.0, 10.0], [0, 0, 0], [0, 1, 0], 50, 36, 1920, 1080)
    c, r = np.array([0.3, 0.2, 0.1]), 1.2
    # points on the front of the sphere: the projection must give them back
    th = np.linspace(0, 2 * np.pi, 17)
    X = c + r * np.stack([0.6 * np.cos(th), 0.6 * np.sin(th), np.full_like(th, 0.8)], 1)
    Y, hit = project_to_sphere(cam, cam.project(X), c, r)
    assert hit.all()
    np.testing.assert_allclose(Y, X, atol=1e-9)
    # the ray through the centre hits at distance |C - c| - r from the camera
    Y, hit = project_to_sphere(cam, cam.project(c[None]), c, r)
    assert hit[0]
    np.testing.assert_allclose(np.linalg.norm(Y[0] - cam.center), np.linalg.norm(c - cam.center) - r, atol=1e-9)
    # a ray that misses: flagged, point on the sphere at the closest approach
    O, D = np.array([[0.0, 0, 10]]), np.array([[0.0, 1, -1]])
    Y, hit = ray_sphere(O, D, [0, 0, 0], 1.0)
    assert not hit[0]
    np.testing.assert_allclose(np.linalg.norm(Y[0]), 1.0)
    np.testing.assert_allclose(Y[0], [0, 1 / np.sqrt(2), 1 / np.sqrt(2)], atol=1e-12)
    # per-ray radii (concentric spheres)
    Y, _ = ray_sphere(np.zeros((2, 3)) + [0, 0, 5], [[0, 0, -1], [0, 0, -1]], [0, 0, 0], [1.0, 2.0])
    np.testing.assert_allclose(Y[:, 2], [1.0, 2.0])


# ------------------------------------------------------------------------- ICT


@pytest.fixture(scope="module")
def ict_loops(ict):
    return ict_contour_loops(ict)


def helmet(V):
    tgt = V[6632:6706].mean(0) + [0, 2.0, 0]
    return [Camera.look_at(tgt + [dx, -6.0, 30.0], tgt, [0, 1, 0], 35, 36, 1920, 1080) for dx in (-5.0, 5.0)]


def test_ict_loops(ict, ict_loops):
    L = ict_loops
    assert [len(r) for r in L.mouth] == [74] * 14
    assert L.mouth[0].tolist() and set(L.mouth[0]) == set(range(6632, 6706))
    assert set(L.eyes) == {"left", "right"} and all(len(L.eyes[s]) == 4 for s in L.eyes)
    # left eye loops around the +x eyeball, inside the face part
    face = ict.part_vertex_mask("M_Face")
    for side, sgn in (("left", 1), ("right", -1)):
        c, r = L.eye_spheres[side]
        assert np.sign(c[0]) == sgn and 1.0 < r < 2.0  # centimetres
        for lp in L.eyes[side]:
            assert face[lp].all() and np.linalg.norm(ict.neutral[lp].mean(0)[:2] - c[:2]) < r
    # corners of the lip-contact ring are the mouth corners: far apart laterally, at the same height
    cl, cr = ict.neutral[L.mouth_corners[7]]
    assert 4.0 < cr[0] - cl[0] < 5.5 and abs(cl[0] + cr[0]) < 1e-6 and abs(cl[1] - cr[1]) < 1e-6
    # every ring is split at the same anatomical corner: consecutive rings' corners are joined by a mesh edge
    from facelab_addon.core.geometry.mesh import vertex_adjacency

    A = vertex_adjacency(ict.faces, len(ict.neutral))
    for cor in (L.mouth_corners, L.eye_corners["left"], L.eye_corners["right"]):
        for k in range(len(cor) - 1):
            assert A[cor[k, 0], cor[k + 1, 0]] and A[cor[k, 1], cor[k + 1, 1]]
    lat = ict.neutral[L.mouth_corners, 0]
    assert np.ptp(lat[:, 0]) < 0.5 and np.ptp(lat[:, 1]) < 0.5  # within 5 mm across the lip roll
    need = L.needed_vertices()
    assert len(need) < 4000 and np.isin(np.concatenate(L.mouth), need).all()


@pytest.mark.parametrize("expr", ["neutral", "jawOpen", "mouthRollUpper", "mouthFunnel", "eyeBlink_L"])
def test_truth_curves_matched_to_the_truth_have_near_zero_residual(ict, ict_loops, expr):
    V = ict.neutral if expr == "neutral" else ict.expressions[expr]
    cams = helmet(V)
    curves = synthetic_tracked_curves(V, ict.faces, cams, ict_loops)
    assert len(curves) == 12
    corr = match_contours(V, ict.faces, cams, curves, ict_loops, MatchParams(eyelids="both"))
    assert len(corr) == 4 + 16
    res = contour_residuals(V, cams, corr)
    for c, r in zip(corr, res):
        if c.camera >= 0:
            # pixels; what remains is the curve's 0.25 px resampling, which shortens the arc length a little
            # where the projected loop zigzags
            assert r.max() < 0.3, (c.name, c.camera, r.max())
        else:
            # 3D eyelid on the eyeball, lifted with the lid's current height over the sphere: unbiased, only
            # the curve's resampling remains
            assert r.max() < 0.01, (c.name, r.max())  # cm
            assert c.source_camera in (0, 1)
    # the rest-height lift (old default) is off wherever the expression changes the lid's height (blink)
    rest = match_contours(V, ict.faces, cams, curves, ict_loops, MatchParams(eyelid_height="rest"))
    r3 = np.concatenate([r for c, r in zip(rest, contour_residuals(V, cams, rest)) if c.camera < 0])
    if expr == "eyeBlink_L":
        assert r3.max() > 0.05  # cm
    # eyelids come as a 2D correspondence followed by its 3D lift; the targets reproject onto each other
    pairs = [(a, b) for a, b in zip(corr[:-1], corr[1:]) if b.camera == -1]
    assert len(pairs) == 8
    for c2, c3 in pairs:
        assert c2.name == c3.name and c2.camera == c3.source_camera and c2.loop == c3.loop
        # the 3D points are the 2D ones minus those lifted at a grazing angle
        row = {(a, b, t): i for i, ((a, b), t) in enumerate(zip(c2.vertices.tolist(), c2.curve_t.tolist()))}
        idx = [row[(a, b, t)] for (a, b), t in zip(c3.vertices.tolist(), c3.curve_t.tolist())]
        assert len(idx) >= 0.5 * len(c2)
        np.testing.assert_allclose(cams[c2.camera].project(c3.targets), c2.pixels[idx], atol=1e-6)
        ctr, _ = ict_loops.eye_spheres[c2.name.split("_")[1]]
        ray = c3.targets - cams[c2.camera].center
        nrm = c3.targets - ctr
        cos = -(ray * nrm).sum(1) / np.linalg.norm(ray, axis=1) / np.linalg.norm(nrm, axis=1)
        assert cos.min() >= 0.25


def test_ict_selection_moves_with_the_lip_roll(ict, ict_loops):
    cams = helmet(ict.neutral)
    got = {}
    for expr in ("neutral", "mouthRollUpper"):
        V = ict.neutral if expr == "neutral" else ict.expressions[expr]
        curves = synthetic_tracked_curves(V, ict.faces, cams, ict_loops, names=["mouth_upper", "mouth_lower"])
        got[expr] = {c.name: c.loop for c in match_contours(V, ict.faces, cams, curves, ict_loops)[:2]}
    # rolling the upper lip in moves its silhouette outward (higher ring); the lower lip stays put
    assert got["mouthRollUpper"]["mouth_upper"] >= got["neutral"]["mouth_upper"] + 2
    assert abs(got["mouthRollUpper"]["mouth_lower"] - got["neutral"]["mouth_lower"]) <= 1


def test_match_contours_is_fast_on_ict(ict, ict_loops):
    V = ict.expressions["jawOpen"]
    cams = helmet(V)
    curves = synthetic_tracked_curves(V, ict.faces, cams, ict_loops, spacing_px=1.0)
    match_contours(V, ict.faces, cams, curves, ict_loops)
    t0 = time.process_time()
    for _ in range(10):
        match_contours(V, ict.faces, cams, curves, ict_loops)
    ms = (time.process_time() - t0) * 100
    assert ms < 40.0, ms  # a few ms on an idle core; generous for a loaded shared machine


# ---------------------------------------------------------------------- errors


def test_bad_input_messages(band, ict, ict_loops):
    V, F, rings, loops = band
    cam = axis_camera()
    good = synthetic_tracked_curves(V, F, [cam], loops)[0]
    with pytest.raises(FaceLabError, match="Unknown tracked curve 'lips'"):
        match_contours(V, F, [cam], [TrackedCurve("lips", 0, good.pixels)], loops)
    with pytest.raises(FaceLabError, match="camera 2, but 1 camera"):
        match_contours(V, F, [cam], [TrackedCurve("mouth_upper", 2, good.pixels)], loops)
    with pytest.raises(FaceLabError, match="has no eyes"):
        match_contours(V, F, [cam], [TrackedCurve("eyelid_left_upper", 0, good.pixels)], loops)
    with pytest.raises(FaceLabError, match="at least 2 points"):
        match_contours(V, F, [cam], [TrackedCurve("mouth_upper", 0, good.pixels[:1])], loops)
    with pytest.raises(FaceLabError, match="NaN"):
        bad = good.pixels.copy()
        bad[3] = np.nan
        match_contours(V, F, [cam], [TrackedCurve("mouth_upper", 0, bad)], loops)
    with pytest.raises(MeshError, match="rebuild the loops"):
        match_contours(V[:-1], F, [cam], [good], loops)
    with pytest.raises(FaceLabError, match="eyelid_height must be"):
        MatchParams(eyelid_height="x")
    with pytest.raises(FaceLabError, match="eyelids must be"):
        MatchParams(eyelids="3D")
    with pytest.raises(FaceLabError, match="pass MatchParams"):
        match_contours(V, F, [cam], [good], loops, "3d")
    behind = Camera.look_at([0, 0, -DIST], [0, 0, -2 * DIST], [0, 1, 0], 50, 36, 1920, 1080)
    with pytest.raises(FaceLabError, match="behind the camera"):
        match_contours(V, F, [behind], [good], loops)
    with pytest.raises(MeshError, match="not a closed border"):
        contour_loops(V, F, mouth_loop=rings[3])
    with pytest.raises(FaceLabError, match="eyeball needs at least 4"):
        contour_loops(V, F, mouth_loop=rings[0], eyeballs={"left": [1, 2]})


def test_default_mouth_loop_is_found_and_loops_do_not_depend_on_scale(ict, ict_loops):
    L = contour_loops(ict.neutral * 0.01, ict.faces, fixed=~ict.part_vertex_mask("M_Face"))  # metres
    assert [set(a.tolist()) for a in L.mouth] == [set(a.tolist()) for a in ict_loops.mouth]
    np.testing.assert_array_equal(L.mouth_corners, ict_loops.mouth_corners)
    assert L.eyes == {}  # no eyeballs given: no eyelid contours


def test_synthetic_curves_noise_and_off_screen(band):
    V, F, rings, loops = band
    cam = axis_camera()
    clean = synthetic_tracked_curves(V, F, [cam], loops)
    noisy = synthetic_tracked_curves(V, F, [cam], loops, noise_px=0.5, seed=3)
    d = np.concatenate([n.pixels - c.pixels for n, c in zip(noisy, clean)])
    assert abs(d.std() - 0.5) < 0.05
    # spacing: consecutive samples 0.25 px apart along the polyline (ends kept)
    step = np.linalg.norm(np.diff(clean[0].pixels, axis=0), axis=1)
    assert step.max() <= 0.25 + 1e-9 and step.mean() > 0.2
    # a camera that sees the mouth only partly (narrow image) delivers no curve
    narrow = Camera(cam.K, cam.R, cam.t, 1000, 1080)
    assert synthetic_tracked_curves(V, F, [narrow], loops) == []


def test_silhouettes_far_from_the_tracked_curve_do_not_count(ict, ict_loops):
    """Open funnelled mouth seen from the helmet cameras (below): the lower lip has inner-lip silhouettes on
    ring 5 and an outline on the lip front (ring 13). A curve traced along either is matched to that ring."""
    w = {"jawOpen": 0.53, "mouthFunnel": 0.47, "mouthLowerDown_L": 0.21, "mouthLowerDown_R": 0.24,
         "mouthSmile_L": 0.55, "mouthSmile_R": 0.24, "mouthUpperUp_R": 0.18}
    from facelab_addon.testing.capture_sim import helmet_cameras

    X = ict.pose(w)
    cams = helmet_cameras()  # 3 cm below the mouth, 19 cm away, 6 cm either side
    lo, hi = ict_loops._pack.offsets["mouth_lower"]
    for cam in cams:
        c = half_silhouette_counts(X, cam, ict_loops)[lo:hi]
        assert c[5] == c.max() and c[13] >= 0.5 * c[5]  # both are real silhouettes; the count alone says 5
    for k in (5, 13):
        for ci, cam in enumerate(cams):
            P = resample_polyline(cam.project(half_points(X, ict_loops.halves["mouth_lower"][k])), 0.25)
            corr = match_contours(X, ict.faces, cams, [TrackedCurve("mouth_lower", ci, P)], ict_loops)[0]
            assert corr.loop == k
            assert contour_residuals(X, cams, [corr])[0].max() < 0.1


def test_synthetic_tracker_follows_the_opening_not_the_lip_front_outline(ict, ict_loops):
    """A pose where the lower lip's front outline (ring 13) has about as many inner silhouette edges as the
    inner-lip line (ring 6): only the edges nearest the opening make the synthetic tracker's curve."""
    from facelab_addon.testing.capture_sim import helmet_cameras

    w = {"browInnerUp_L": 0.496, "eyeBlink_L": 0.272, "eyeBlink_R": 0.596, "jawLeft": -0.049, "jawOpen": 0.526,
         "mouthFunnel": 0.473, "mouthLowerDown_L": 0.209, "mouthLowerDown_R": 0.243, "mouthPucker": 0.066,
         "mouthRollLower": 0.072, "mouthSmile_L": 0.548, "mouthSmile_R": 0.244, "mouthUpperUp_L": 0.085,
         "mouthUpperUp_R": 0.18}
    X = ict.pose(w)
    cams = helmet_cameras()
    lo, hi = ict_loops._pack.offsets["mouth_lower"]
    curves = synthetic_tracked_curves(X, ict.faces, cams, ict_loops, names=["mouth_lower"])
    for cam, cv in zip(cams, curves):
        inner = half_silhouette_counts(X, cam, ict_loops)[lo:hi]
        env = envelope_counts(X, cam, ict_loops)[lo:hi]
        assert (env <= inner).all()
        assert inner[13] >= 0.75 * inner.max() and env[13] <= 0.5 * inner[13]
        # ring 13 lies below the chosen ring in the image, away from the opening
        k = int(np.argmax(env))
        assert k in (5, 6)
        y = [cam.project(half_points(X, ict_loops.halves["mouth_lower"][j]))[:, 1].mean() for j in (k, 13)]
        assert y[1] > y[0]
        ends = cam.project(X[ict_loops.halves["mouth_lower"][k].chain[[0, -1]]])
        np.testing.assert_allclose(cv.pixels[[0, -1]], ends, atol=1e-9)
