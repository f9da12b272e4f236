"""The fixed operators of the lip regressor (core/lips/regressor/operators.py) on a hexagonal fan.

Lip region: the 6 triangles around vertex 0 (one interior vertex, the ring 1..6 its border); mouth
region: the ring of 12 triangles out to radius 2. Gradient-domain Poisson with the border held is exact
for affine maps: given the gradients ``A`` of ``x -> A x + t`` and the mapped border, vertex 0 lands at
``A·0 + t = t``."""

import numpy as np
import pytest

from facelab_addon.core.errors import FaceLabError
from facelab_addon.core.lips.regressor.operators import lip_operators


def fan():
    ang = np.arange(6) * np.pi / 3
    ring = lambda r: np.stack([r * np.cos(ang), r * np.sin(ang), np.zeros(6)], 1)  # noqa: E731
    V = np.vstack([[0.0, 0.0, 0.0], ring(1.0), ring(2.0)])
    lips = [[0, 1 + i, 1 + (i + 1) % 6] for i in range(6)]
    mouth = []
    for i in range(6):
        a, b, A, B = 1 + i, 1 + (i + 1) % 6, 7 + i, 7 + (i + 1) % 6
        mouth += [[a, A, B], [a, B, b]]
    F = np.array(lips + mouth)
    return V, F, np.arange(6, 18), np.arange(6)


def test_regions_border_and_indexing():
    V, F, mouth, lips = fan()
    ops = lip_operators(V, F, mouth, lips, center="rest", patches=1, input_radius=None, backend="splu")
    np.testing.assert_array_equal(ops.interior_vertices, [0])
    np.testing.assert_array_equal(ops.border_vertices, np.arange(1, 7))
    np.testing.assert_array_equal(ops.lip_verts, np.arange(7))
    np.testing.assert_array_equal(ops.mouth_verts, np.arange(1, 13))
    np.testing.assert_array_equal(ops.used, np.arange(13))
    np.testing.assert_array_equal(ops.used[ops.mouth_u], ops.mouth_verts)
    np.testing.assert_array_equal(ops.used[ops.iv_u], [0])
    np.testing.assert_array_equal(ops.mouth_verts[ops.mouth_local], F[mouth])
    np.testing.assert_array_equal(ops.lip_verts[ops.lip_local], F[lips])
    assert ops.mouth_size == pytest.approx(4.0)  # x spans -2..2
    assert ops.n_vertices == 13
    # one patch: the whole mouth feeds the whole lip region with weight 1, and its divergence is D_I
    (ms, ls, w), = ops.patches
    np.testing.assert_array_equal(ms, np.arange(12))
    np.testing.assert_array_equal(ls, np.arange(6))
    np.testing.assert_array_equal(w, np.ones(6))
    assert ops.patch_spacing == np.inf
    assert abs(ops.D_patch[0] - ops.D_I).max() == 0
    # P = D_r⁻¹ D_r⁻ᵀ: <DᵀD, P> is the squared gradient norm, 3 for the rest pose itself
    D = np.stack([np.c_[V[f[1]] - V[f[0]], V[f[2]] - V[f[0]], [0, 0, 0]] for f in F[mouth]])
    D[:, :, 2] = np.cross(D[:, :, 0], D[:, :, 1]) / np.sqrt(np.linalg.norm(np.cross(D[:, :, 0], D[:, :, 1]), axis=1))[:, None]
    np.testing.assert_allclose(np.einsum("fij,fij->f", np.matmul(D.transpose(0, 2, 1), D), ops.mouth_P), 3.0)


@pytest.mark.parametrize("backend", ["splu", "auto"])
def test_poisson_solve_reproduces_an_affine_map(backend):
    V, F, mouth, lips = fan()
    ops = lip_operators(V, F, mouth, lips, center="rest", patches=1, input_radius=None, backend=backend)
    A = np.array([[1.2, 0.3, 0.0], [-0.1, 0.9, 0.2], [0.05, 0.0, 1.1]])
    t = np.array([0.5, -0.25, 2.0])
    Fg = np.broadcast_to(A, (6, 3, 3))
    xb = V[ops.border_vertices] @ A.T + t
    rhs = ops.D_I @ Fg.transpose(0, 2, 1).reshape(-1, 3) - ops.L_IB @ xb
    np.testing.assert_allclose(ops.factor.solve(rhs), [t], atol=1e-12)
    # the identity gradients' divergence: the rest border gives the rest interior
    np.testing.assert_allclose(ops.factor.solve(ops.b_ident - ops.L_IB @ V[ops.border_vertices]), [[0, 0, 0]],
                               atol=1e-12)


def test_a_lip_region_without_interior_is_refused():
    V, F, mouth, lips = fan()
    with pytest.raises(FaceLabError, match="border"):
        lip_operators(V, F, mouth, lips[:3], center="rest", patches=1, input_radius=None, backend="splu")
