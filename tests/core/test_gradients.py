"""Deformation gradients with a phantom vertex (Sumner & Popović 2004; Dinev et al. 2018 §4)."""

import numpy as np
import pytest

from facelab_addon.core.errors import MeshError
from facelab_addon.core.geometry.gradients import deformation_gradients, rest_inverse, shape_matrices


def bumpy_grid(n=6, seed=0):
    """A non-planar triangulated grid: (V,3), (F,3)."""
    from facelab_addon.testing.meshes import grid_mesh

    rng = np.random.default_rng(seed)
    return grid_mesh(np.linspace(0, 1, n), np.linspace(0, 1, n),
                     lambda x, y: 0.2 * np.sin(3 * x) * np.cos(2 * y) + 0.02 * rng.standard_normal(x.shape))


def rotation(axis, angle):
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def test_hand_computed_single_triangle():
    rest = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    deformed = rest * [2.0, 1.0, 1.0]  # stretch x by 2
    # rest phantom offset (0,0,1)/sqrt(1); deformed cross = (0,0,2) -> (0,0,2)/sqrt(2)
    F = deformation_gradients(rest, deformed, [[0, 1, 2]])
    np.testing.assert_allclose(F[0], np.diag([2.0, 1.0, np.sqrt(2.0)]), atol=1e-15)


def test_rest_pose_gives_identity():
    V, F = bumpy_grid()
    G = deformation_gradients(V, V, F)
    assert G.shape == (len(F), 3, 3)
    np.testing.assert_allclose(G, np.broadcast_to(np.eye(3), G.shape), atol=1e-12)


def test_rigid_motion_gives_rotation_on_every_triangle():
    V, F = bumpy_grid()
    R = rotation([1.0, -2.0, 0.5], 0.8)
    G = deformation_gradients(V, V @ R.T + [3.0, -1.0, 2.0], F)
    np.testing.assert_allclose(G, np.broadcast_to(R, G.shape), atol=1e-12)


def test_similarity_gives_sR():
    V, F = bumpy_grid()
    A = 1.7 * rotation([0.3, 1.0, -1.0], -1.1)
    G = deformation_gradients(V, V @ A.T, F)
    np.testing.assert_allclose(G, np.broadcast_to(A, G.shape), atol=1e-12)


def test_general_affine_map_is_exact_on_the_triangle_plane():
    V, F = bumpy_grid()
    A = np.array([[1.3, 0.4, -0.2], [0.1, 0.8, 0.5], [-0.3, 0.2, 1.1]])
    D = V @ A.T + [0.5, 0.0, -1.0]
    G = deformation_gradients(V, D, F)
    Dr = shape_matrices(V, F)
    # edges map exactly: F e = A e for both edges of every triangle
    for c in (0, 1):
        np.testing.assert_allclose(np.einsum("fij,fj->fi", G, Dr[:, :, c]), Dr[:, :, c] @ A.T, atol=1e-12)
    # so F equals A on the tangent plane: F P = A P with P the projection onto the plane
    n = np.cross(Dr[:, :, 0], Dr[:, :, 1])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    P = np.eye(3) - n[:, :, None] * n[:, None, :]
    np.testing.assert_allclose(G @ P, A @ P, atol=1e-12)
    # and the phantom column follows Sumner's formula on the deformed triangle
    c = np.cross(Dr[:, :, 0] @ A.T, Dr[:, :, 1] @ A.T)
    np.testing.assert_allclose(
        np.einsum("fij,fj->fi", G, Dr[:, :, 2]), c / np.sqrt(np.linalg.norm(c, axis=1, keepdims=True)), atol=1e-12
    )
    # a general A is NOT reproduced off the plane (guards against a wrong phantom formula passing silently)
    assert np.abs(G - A).max() > 1e-3


def test_vectorised_over_frames_and_scale_invariant():
    V, F = bumpy_grid()
    rng = np.random.default_rng(1)
    frames = V + 0.05 * rng.standard_normal((4,) + V.shape)
    G = deformation_gradients(V, frames, F)
    assert G.shape == (4, len(F), 3, 3)
    for t in range(4):
        np.testing.assert_allclose(G[t], deformation_gradients(V, frames[t], F), atol=1e-13)
    # centimetres vs metres: same gradients
    np.testing.assert_allclose(deformation_gradients(V * 0.01, frames * 0.01, F), G, atol=1e-10)
    # precomputed rest inverse gives the same
    np.testing.assert_allclose(deformation_gradients(V, frames, F, rest_inv=rest_inverse(V, F)), G, atol=1e-13)


def test_errors_name_problem_and_fix():
    V, F = bumpy_grid()
    with pytest.raises(MeshError, match="topology differs"):
        deformation_gradients(V, V[:-1], F)
    bad = V.copy()
    bad[3, 1] = np.nan
    with pytest.raises(MeshError, match="NaN"):
        deformation_gradients(V, bad[None].repeat(2, 0), F)
    degen = V.copy()
    degen[F[0, 1]] = degen[F[0, 0]]
    with pytest.raises(MeshError, match="degenerate.*Degenerate Dissolve"):
        deformation_gradients(degen, degen, F)
