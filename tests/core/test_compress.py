"""Corrective shape-key basis with a per-vertex error bound."""

import numpy as np
import pytest

from facelab_addon.core.errors import FaceLabError, MeshError
from facelab_addon.core.geometry.compress import DEFAULT_TOL_M, compress, reconstruct


def corrections(T=60, V=3000, moving=400, rank=4, noise=0.0, seed=0):
    """(T,V,3) corrections of known rank on a subset of vertices, plus the subset."""
    rng = np.random.default_rng(seed)
    idx = np.sort(rng.choice(V, moving, replace=False))
    B = rng.standard_normal((rank, moving, 3)) * 0.1
    W = np.cumsum(rng.standard_normal((T, rank)), axis=0) * 0.2
    C = np.zeros((T, V, 3))
    C[:, idx] = np.einsum("tr,rvc->tvc", W, B) + noise * rng.standard_normal((T, moving, 3))
    return C, idx


def max_vertex_error(C, basis, weights):
    return float(np.sqrt(np.max(np.sum((reconstruct(basis, weights) - C) ** 2, axis=2))))


def test_exact_low_rank_is_found_with_its_rank():
    C, idx = corrections(rank=4)
    basis, weights = compress(C, tol=1e-9)
    assert basis.shape == (4, C.shape[1], 3) and weights.shape == (C.shape[0], 4)
    assert max_vertex_error(C, basis, weights) <= 1e-9
    # vertices that never move stay zero in the basis; weights are shape-key values in [-1, 1]
    still = np.setdiff1d(np.arange(C.shape[1]), idx)
    assert not basis[:, still].any()
    np.testing.assert_allclose(np.abs(weights).max(axis=0), 1.0)


@pytest.mark.parametrize("tol", [3e-2, 1e-2, 3e-3, 1e-3])
def test_tolerance_is_honoured_with_the_smallest_rank(tol):
    C, _ = corrections(rank=8, noise=2e-3, seed=1)
    basis, weights = compress(C, tol=tol)
    r = basis.shape[0]
    assert max_vertex_error(C, basis, weights) <= tol
    # one shape fewer breaks the bound (the rank is not needlessly high)
    if r > 0:
        A = C.reshape(len(C), -1)
        U, s, Vt = np.linalg.svd(A, full_matrices=False)
        R = A - (U[:, : r - 1] * s[: r - 1]) @ Vt[: r - 1]
        assert np.sqrt(np.max(np.sum(R.reshape(C.shape) ** 2, axis=2))) > tol


def test_default_tolerance_is_a_hundredth_of_a_millimetre_in_scene_units():
    C, _ = corrections(rank=3, noise=4e-6, seed=2)  # cm-sized offsets with 0.04 µm..0.1 mm noise
    b_m, w_m = compress(C)  # metres: tol = 1e-5
    assert max_vertex_error(C, b_m, w_m) <= DEFAULT_TOL_M
    b_cm, w_cm = compress(C, metres_per_unit=0.01)  # centimetres: tol = 1e-3
    assert max_vertex_error(C, b_cm, w_cm) <= 1e-3
    assert b_cm.shape[0] <= 3 < b_m.shape[0]


def test_small_corrections_and_subsets():
    C = np.zeros((5, 10, 3))
    b, w = compress(C, tol=1e-3)
    assert b.shape == (0, 10, 3) and w.shape == (5, 0)
    assert reconstruct(b, w).shape == (5, 10, 3) and not reconstruct(b, w).any()
    C, _ = corrections(T=10, V=50, moving=20, rank=2)
    b, w = compress(C, tol=1e-9)
    np.testing.assert_allclose(reconstruct(b, w, frames=[3, 7]), C[[3, 7]], atol=1e-9)


def test_errors():
    C, _ = corrections(T=5, V=20, moving=5)
    with pytest.raises(FaceLabError, match="positive distance"):
        compress(C, tol=0)
    bad = C.copy()
    bad[2, 4, 1] = np.nan
    with pytest.raises(MeshError, match="NaN.*vertices \\[4\\]"):
        compress(bad, tol=1e-3)
    with pytest.raises(MeshError, match="\\(T,V,3\\)"):
        compress(C[0], tol=1e-3)
    with pytest.raises(FaceLabError, match="needs 4 corrective shapes.*max_rank=1"):
        compress(C, tol=1e-12, max_rank=1)
    with pytest.raises(FaceLabError, match="do not match"):
        reconstruct(np.zeros((2, 20, 3)), np.zeros((5, 3)))
