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


# --------------------------------------------------------------------------- streamed, bounded memory
def test_streamed_finds_a_low_rank_correction_within_the_budget(tmp_path):
    from facelab_addon.core.geometry.compress import compress_streamed

    C, idx = corrections(T=300, V=2000, moving=300, rank=5)
    spool = np.memmap(tmp_path / "spool.f32", dtype="<f4", mode="w+", shape=C.shape)
    spool[:] = C
    before = np.array(spool)
    r = compress_streamed(lambda i, j: spool[i:j], len(C), C.shape[1], 1e-5, max_rank=24, chunk=37)
    assert r.fits and r.basis.shape == (5, C.shape[1], 3) and r.weights.shape == (300, 5)
    got = reconstruct(r.basis, r.weights)
    assert np.sqrt(np.sum((got - before) ** 2, axis=2)).max() <= 1e-5  # float32 spool, every vertex, every frame
    assert r.frame_error.shape == (300,) and r.max_error == r.frame_error.max() <= 1e-5
    np.testing.assert_array_equal(np.array(spool), before)  # the spool is read, never written


def test_streamed_refuses_a_full_rank_correction_and_says_how_far_off():
    from facelab_addon.core.geometry.compress import compress_streamed

    rng = np.random.default_rng(3)
    C = rng.normal(0, 1e-3, (80, 500, 3))  # noise: every frame its own shape
    r = compress_streamed(lambda i, j: C[i:j], 80, 500, 1e-5, max_rank=16)
    assert not r.fits and r.basis.shape[0] == 16 and r.max_error > 1e-4  # RMS left beyond 16 shapes


def test_streamed_rank_is_the_smallest_within_tolerance_per_frame():
    """A decaying spectrum: the rank found keeps every frame within tol, one less does not."""
    from facelab_addon.core.geometry.compress import compress_streamed

    rng = np.random.default_rng(4)
    T, n, k = 120, 400, 12
    B = np.linalg.qr(rng.standard_normal((3 * n, k)))[0].T.reshape(k, n, 3)
    W = rng.standard_normal((T, k)) * (1e-3 * 0.5 ** np.arange(k))
    C = np.einsum("tr,rvc->tvc", W, B)
    for tol in (1e-4, 1e-5, 1e-6):
        r = compress_streamed(lambda i, j: C[i:j], T, n, tol, max_rank=k)
        e = np.sqrt(np.sum((reconstruct(r.basis, r.weights) - C) ** 2, axis=2)).max(axis=1)
        assert r.fits and e.max() <= tol and np.allclose(e, r.frame_error, atol=1e-12)
        q = r.basis.shape[0]
        b, w = compress(C, tol=tol)
        assert q <= b.shape[0] + 1  # the randomized basis is as good as the exact SVD, give or take one


def test_streamed_takes_a_low_rank_product_without_forming_it():
    from facelab_addon.core.geometry.compress import compress_streamed, low_rank_reader

    rng = np.random.default_rng(5)
    B, W = rng.normal(0, 1e-3, (4, 300, 3)), rng.normal(0, 1, (50, 4))
    B[3] = B[0] + B[1]  # rank 3 in a basis of 4
    r = compress_streamed(low_rank_reader(B, W), 50, 300, 1e-9, max_rank=8, low_rank=(B, W))
    assert r.fits and r.basis.shape[0] == 3
    np.testing.assert_allclose(reconstruct(r.basis, r.weights), np.einsum("tr,rvc->tvc", W, B), atol=1e-9)
    with pytest.raises(FaceLabError, match="key budget"):
        compress_streamed(low_rank_reader(B, W), 50, 300, 1e-9, max_rank=0)
    with pytest.raises(MeshError, match="NaN"):
        bad = np.einsum("tr,rvc->tvc", W, B)
        bad[7, 3, 1] = np.nan
        compress_streamed(lambda i, j: bad[i:j], 50, 300, 1e-6, max_rank=8)
