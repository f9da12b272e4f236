"""Deformation transfer (Sumner & Popović 2004; Bhat et al. 2013 §5.1) against analytic deformations."""

import numpy as np
import pytest

from facelab_addon.core.errors import FaceLabError
from facelab_addon.core.solve.deformation_transfer import (
    DeformationTransfer,
    deformation_transfer,
    triangle_correspondence_from_markers,
)


def grid(n=15, m=None, size=1.0, bump=0.15):
    """Bumpy height-field patch on [0,size]^2 with n x m vertices (one piece)."""
    from facelab_addon.testing.meshes import grid_mesh

    m = n if m is None else m
    return grid_mesh(np.linspace(0, size, n), np.linspace(0, size, m),
                     lambda X, Y: bump * np.sin(2.0 * X) * np.cos(1.5 * Y) + 0.05 * X * Y)


def two_pieces():
    """Two disjoint patches (like a face and an eyeball): 2 connected components."""
    V1, F1 = grid(9)
    V2, F2 = grid(6, size=0.4)
    V2 = V2 + [1.5, 0.2, 0.3]
    return np.r_[V1, V2], np.r_[F1, F2 + len(V1)]


def rotation(ax, ang):
    ax = np.asarray(ax, float) / np.linalg.norm(ax)
    K = np.array([[0, -ax[2], ax[1]], [ax[2], 0, -ax[0]], [-ax[1], ax[0], 0]])
    return np.eye(3) + np.sin(ang) * K + (1 - np.cos(ang)) * K @ K


def warp(V):
    """A smooth non-affine creature warp (changes the rest shape, keeps topology)."""
    return V + np.c_[0.3 * V[:, 0] ** 2, 0.1 * np.sin(3 * V[:, 1]), 0.2 * V[:, 0] * V[:, 1]]


def bend(V, k=0.8):
    """A smooth non-linear deformation: bend around the y axis."""
    x, y, z = V.T
    th = k * x
    r = 1.0 / k - z
    return np.c_[np.sin(th) * r, y, 1.0 / k - np.cos(th) * r]


def test_identity_deformation_leaves_the_creature_unchanged():
    V, F = two_pieces()
    C = warp(V)
    out = deformation_transfer(V, F, V, C, F)
    np.testing.assert_allclose(out, C, atol=1e-12)
    dt = DeformationTransfer(V, F, C, F)
    np.testing.assert_allclose(dt.transfer_deltas(np.zeros((3,) + V.shape)), 0.0, atol=1e-12)


def test_similarity_transfers_exactly_on_every_piece():
    V, F = two_pieces()
    R, s, t = rotation([1, 2, 0.5], 0.7), 1.3, np.array([0.2, -0.1, 0.4])
    # a target where the source is: the same similarity (about the world origin)
    np.testing.assert_allclose(deformation_transfer(V, F, s * V @ R.T + t, V, F), s * V @ R.T + t, atol=1e-10)
    # a warped creature: the similarity seen from the creature's placement P (best fit of the actor onto it),
    # P M P^-1, exact including each piece's placement (the first-order hint is exact for similarities)
    C = warp(V)
    dt = DeformationTransfer(V, F, C, F)
    sp_, Rp, tp = dt.placement
    assert abs(sp_ - 1.0) > 1e-3 and np.abs(tp).max() > 1e-2  # a real placement, not the identity
    local = (C - tp) @ Rp / sp_  # P^-1(C)
    exp = sp_ * (s * local @ R.T + t) @ Rp.T + tp
    np.testing.assert_allclose(dt.transfer(s * V @ R.T + t), exp, atol=1e-10)


@pytest.mark.parametrize("offset", [[0.0, 50.0, 0.0], [3e3, -2e3, 1e3]])
def test_translated_identical_creature_gets_the_source_deltas(offset):
    """Where the creature was modelled does not matter: a translated copy receives the source deltas."""
    V, F = two_pieces()
    rng = np.random.default_rng(3)
    d = np.stack([bend(V) - V, 0.02 * rng.standard_normal(V.shape), V * [0, 0.5, -0.3]])
    dt = DeformationTransfer(V, F, V + offset, F)
    s_, R_, t_ = dt.placement
    assert abs(s_ - 1.0) < 1e-12 and np.abs(R_ - np.eye(3)).max() < 1e-12
    np.testing.assert_allclose(t_, offset, atol=1e-12 * np.abs(offset).max())
    out = dt.transfer_deltas(d)
    for k in range(len(d)):
        assert np.abs(out[k] - d[k]).max() <= 1e-9 * np.abs(d[k]).max()


def test_rotated_scaled_creature_gets_the_placed_source_deltas():
    """A copy turned 90 degrees and scaled 2x about an arbitrary point receives s R d (any shape)."""
    V, F = two_pieces()
    R, s, c = rotation([0.3, -1.0, 0.6], np.pi / 2), 2.0, np.array([4.0, -7.0, 2.5])
    C = s * (V - c) @ R.T + c
    rng = np.random.default_rng(4)
    d = np.stack([bend(V) - V, 0.02 * rng.standard_normal(V.shape)])
    dt = DeformationTransfer(V, F, C, F)
    np.testing.assert_allclose(dt.placement[0], s, rtol=1e-12)
    np.testing.assert_allclose(dt.placement[1], R, atol=1e-12)
    out = dt.transfer_deltas(d)
    for k in range(len(d)):
        exp = s * d[k] @ R.T
        assert np.abs(out[k] - exp).max() <= 1e-9 * np.abs(exp).max()


def test_mirrored_creature_gets_the_mirrored_source_deltas():
    """A mirror image of the actor (x -> -x, same vertex order) receives the mirrored deltas."""
    V, F = two_pieces()
    M = np.diag([-1.0, 1.0, 1.0])
    d = bend(V) - V
    dt = DeformationTransfer(V, F, V @ M + [5.0, 1.0, -2.0], F)
    assert np.linalg.det(dt.placement[1]) < 0
    out = dt.transfer_deltas(d)
    assert np.abs(out - d @ M).max() <= 1e-9 * np.abs(d).max()


def test_placement_of_a_warped_creature_does_not_change_its_transfer():
    """A different creature moved, turned and scaled receives the same deltas, turned and scaled."""
    V, F = grid(12)
    C = warp(V)
    R, s, c = rotation([1.0, 0.2, -0.4], 2.1), 0.5, np.array([-30.0, 12.0, 8.0])
    d = bend(V) - V
    ref = DeformationTransfer(V, F, C, F).transfer_deltas(d)
    out = DeformationTransfer(V, F, s * (C - c) @ R.T + c, F).transfer_deltas(d)
    np.testing.assert_allclose(out, s * ref @ R.T, atol=1e-9 * np.abs(ref).max())


def test_general_affine_transfers_exactly_when_the_triangles_stay_parallel():
    """A general affine map A (with out-of-plane shear) of a flat actor patch gives A on a flat creature.

    The phantom vertex makes the source gradient equal A on the triangle's plane only (its normal
    column follows the deformed triangle), so exactness needs target triangles parallel to the
    source ones: an in-plane warp of a planar patch.
    """
    V, F = grid(12, bump=0.0)
    V[:, 2] = 0.0
    C = V + np.c_[0.3 * V[:, 0] ** 2, 0.1 * np.sin(3 * V[:, 1]), np.zeros(len(V))]  # in-plane warp
    A = np.array([[1.2, 0.3, -0.1], [0.05, 0.8, 0.2], [0.4, -0.2, 1.1]])
    out = deformation_transfer(V, F, V @ A.T, C, F)
    exp = C @ A.T
    np.testing.assert_allclose(out - out.mean(0), exp - exp.mean(0), atol=1e-10)
    # the same map on a curved creature is only reproduced approximately (this is why it is not exact)
    out2 = deformation_transfer(V, F, V @ A.T, warp(V), F)
    assert np.abs((out2 - out2.mean(0)) - (warp(V) @ A.T - (warp(V) @ A.T).mean(0))).max() > 1e-4


def test_identical_creature_reproduces_any_actor_shape():
    V, F = two_pieces()
    rng = np.random.default_rng(0)
    shapes = np.stack([bend(V), V + 0.02 * rng.standard_normal(V.shape), V * [1, 1.5, 0.7]])
    out = deformation_transfer(V, F, shapes, V, F)
    np.testing.assert_allclose(out, shapes, atol=1e-10)


def test_many_shapes_at_once_equal_one_at_a_time_and_correctives():
    V, F = grid(10)
    C = warp(V)
    dt = DeformationTransfer(V, F, C, F)
    rng = np.random.default_rng(1)
    d = 0.03 * rng.standard_normal((20, len(V), 3))  # more than one block of 16
    all_at_once = dt.transfer_deltas(d)
    np.testing.assert_allclose(all_at_once[17], dt.transfer_deltas(d[17]), atol=1e-12)
    base = bend(V) - V
    corr = dt.transfer_correctives(d[:3], base=np.broadcast_to(base, d[:3].shape))
    np.testing.assert_allclose(corr[1], dt.transfer(V + base + d[1]) - dt.transfer(V + base), atol=1e-12)
    # on the rest pose the two corrective modes agree to first order
    small = 1e-4 * d[:2]
    np.testing.assert_allclose(dt.transfer_correctives(small), dt.transfer_correctives(small, base=0 * small),
                               atol=1e-9)


def test_bend_transfers_to_a_stretched_creature_as_the_corresponding_bend():
    """Gradients travel by correspondence: a creature stretched 1.3x along x bends by the same angles,
    i.e. with curvature k / 1.3 in its own coordinates."""
    V, F = grid(21, bump=0.0)
    V[:, 2] = 0.0
    C = V * [1.3, 0.9, 1.0]
    k = 0.8
    out = deformation_transfer(V, F, bend(V, k), C, F)
    exp = bend(C, k / 1.3)
    err = np.linalg.norm((out - out.mean(0)) - (exp - exp.mean(0)), axis=1)
    motion = np.linalg.norm(exp - C, axis=1).max()
    assert err.max() < 0.01 * motion
    # and it is not the same bend in creature coordinates
    wrong = bend(C, k)
    assert np.linalg.norm((out - out.mean(0)) - (wrong - wrong.mean(0)), axis=1).max() > 0.1 * motion


def test_creature_without_correspondence_is_refused():
    V, F = grid(8)
    V2, F2 = grid(9)
    with pytest.raises(FaceLabError, match="correspondence"):
        DeformationTransfer(V, F, V2, F2)
    with pytest.raises(FaceLabError, match="triangles"):
        DeformationTransfer(V, F, V2, F2, correspondence=np.zeros(5, int))
    with pytest.raises(FaceLabError, match="pairs no creature triangle"):
        DeformationTransfer(V, F, V2, F2, correspondence=-np.ones(len(F2), int))


def test_marker_correspondence_between_different_topologies():
    Vs, Fs = grid(11)
    Vt, Ft = grid(16, 13)  # another resolution: different topology
    Vt = Vt * [1.2, 1.1, 1.0] + [0.3, -0.2, 0.1]  # and another size and place
    # markers: corners and centre of both patches (source vertex ids -> target vertex ids)
    def ids(n, m):
        return np.array([0, m - 1, (n - 1) * m, n * m - 1, (n // 2) * m + m // 2, (n // 4) * m + m // 4])

    corr, fitted = triangle_correspondence_from_markers(Vs, Fs, Vt, Ft, ids(11, 11), ids(16, 13),
                                                        return_fitted=True)
    assert corr.shape == (len(Ft),) and corr.min() >= 0
    # the fitted source lies on the target and every target triangle maps to a source triangle nearby
    uv_t = (Vt[Ft].mean(1)[:, :2] - [0.3, -0.2]) / [1.2, 1.1]
    uv_s = Vs[Fs].mean(1)[:, :2]
    h = 1.0 / 10
    assert np.linalg.norm(uv_t - uv_s[corr], axis=1).max() < 1.0 * h
    # transfer through the correspondence: the creature (1.2x wider) bends by the same angles, i.e. with
    # curvature k / 1.2 in its own coordinates (a random correspondence is 0.24 off here)
    dt = DeformationTransfer(Vs, Fs, Vt, Ft, corr)
    k = 0.8
    out = dt.transfer(bend(Vs, k))
    exp = bend(Vt - [0.3, -0.2, 0.1], k / 1.2)
    mot = np.linalg.norm(bend(Vs, k) - Vs, axis=1).max()
    e = (out - out.mean(0)) - (exp - exp.mean(0))
    assert np.linalg.norm(e, axis=1).max() < 0.06 * mot
    with pytest.raises(FaceLabError, match="at least 4"):
        triangle_correspondence_from_markers(Vs, Fs, Vt, Ft, [0, 1], [0, 1])


def test_part_labels_keep_layered_parts_apart():
    """Two close parallel layers (like lips in front of teeth): labels keep each layer's pairing inside it."""
    Va, Fa = grid(11)
    Vt, Ft = grid(14, 12)
    Vs = np.r_[Va, Va - [0, 0, 0.03]]
    Fs = np.r_[Fa, Fa + len(Va)]
    Vc = np.r_[Vt, Vt - [0, 0, 0.03]] * [1.1, 1.0, 1.0]
    Fc = np.r_[Ft, Ft + len(Vt)]
    sg = np.r_[np.zeros(len(Fa), int), np.ones(len(Fa), int)]
    tg = np.r_[np.zeros(len(Ft), int), np.ones(len(Ft), int)]
    mk_s = np.array([0, 10, 110, 120, 60])
    mk_t = np.array([0, 11, 13 * 12, 14 * 12 - 1, 7 * 12 + 6])
    corr = triangle_correspondence_from_markers(Vs, Fs, Vc, Fc, mk_s, mk_t, source_groups=sg, target_groups=tg)
    np.testing.assert_array_equal(sg[corr], tg)
    with pytest.raises(FaceLabError, match="both meshes"):
        triangle_correspondence_from_markers(Vs, Fs, Vc, Fc, mk_s, mk_t, source_groups=sg)
