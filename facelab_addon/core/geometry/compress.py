"""Compress per-frame lip corrections into a small shape-key basis.

The propagated corrections of Dinev et al. 2018 (§4) are one offset per
vertex and frame. To keep them editable in Blender they are stored as a few
corrective shape keys (the basis) and per-frame key values (the weights):
a truncated SVD of the corrections restricted to the vertices that move. The
rank is the smallest one whose reconstruction keeps every vertex of every
frame within ``tol`` of the input (max-norm, not RMS), 0.01 mm by default.

Memory: only the affected vertices are copied, one block at a time, and the
SVD goes through the ``T × T`` Gram matrix, so 1000 frames of a 26,719-vertex
face need a few tens of MB beyond the input array.
"""

from __future__ import annotations

import numpy as np

from ..errors import FaceLabError, MeshError

__all__ = ["compress", "reconstruct", "DEFAULT_TOL_M"]

#: Default tolerance, 0.01 mm, in metres.
DEFAULT_TOL_M = 1e-5

_BLOCK = 1024  # vertices per block


def _check(C):
    C = np.asarray(C)
    if C.ndim != 3 or C.shape[-1] != 3 or C.shape[0] == 0:
        raise MeshError(f"Corrections must be a (T,V,3) array with T >= 1, got shape {C.shape}.")
    if C.dtype != np.float64 and C.dtype != np.float32:
        C = C.astype(np.float64)
    return C


def compress(corrections, tol=None, *, metres_per_unit: float = 1.0, max_rank: int | None = None):
    """Truncated-SVD basis of per-frame corrections with a per-vertex error bound.

    Parameters
    ----------
    corrections : (T,V,3) array_like
        Per-frame vertex offsets (corrected minus captured), scene units.
        Vertices that never move (all zeros) are left out of the work.
    tol : float, optional
        Largest allowed reconstruction error of any vertex in any frame,
        Euclidean, scene units. Default: 0.01 mm, i.e.
        ``DEFAULT_TOL_M / metres_per_unit``.
    metres_per_unit : float
        Size of one scene unit in metres (Blender's unit scale), used only
        for the default ``tol``: 1.0 for metres, 0.01 for centimetres.
    max_rank : int, optional
        Cap on the rank; if the tolerance needs more, a FaceLabError says so.

    Returns
    -------
    basis : (r,V,3) float64 ndarray
        Corrective shapes, scene units, zero on vertices that never move;
        each scaled so its weight peaks at magnitude 1 over the frames.
    weights : (T,r) float64 ndarray
        Per-frame weights (shape-key values) in [-1, 1]; ``r`` may be 0 when
        every correction is below ``tol``.

    Raises
    ------
    MeshError
        On a wrong shape or NaN/infinite corrections.
    FaceLabError
        If ``tol`` is not positive, or ``max_rank`` is too small for ``tol``.
    """
    C = _check(corrections)
    T, V, _ = C.shape
    if not (np.isscalar(metres_per_unit) and np.isfinite(metres_per_unit) and float(metres_per_unit) > 0):
        raise FaceLabError(f"metres_per_unit must be a positive number, got {metres_per_unit!r}; set the scene's "
                           "Unit Scale (1 for metres).")
    tol = DEFAULT_TOL_M / float(metres_per_unit) if tol is None else float(tol)
    if not (tol > 0 and np.isfinite(tol)):
        raise FaceLabError(f"The compression tolerance must be a positive distance in scene units, got {tol}.")

    # affected vertices, and a NaN check, block by block (no full-size temporaries)
    moving = np.zeros(V, dtype=bool)
    for s in range(0, V, _BLOCK):
        blk = C[:, s : s + _BLOCK]
        if not np.isfinite(blk).all():
            bad = np.flatnonzero(~np.isfinite(blk).all(axis=(0, 2)))[:5] + s
            raise MeshError(
                f"The corrections have NaN or infinite values at vertices {bad.tolist()}; fix those frames."
            )
        moving[s : s + _BLOCK] = (blk != 0).any(axis=(0, 2))
    idx = np.flatnonzero(moving)
    blocks = [idx[s : s + _BLOCK] for s in range(0, len(idx), _BLOCK)]

    def block(b):
        return np.asarray(C[:, b, :], dtype=np.float64).reshape(T, -1)

    if len(idx) == 0:
        return np.zeros((0, V, 3)), np.zeros((T, 0))
    # Gram matrix A Aᵀ (T,T), accumulated over vertex blocks
    G = np.zeros((T, T))
    for b in blocks:
        A = block(b)
        G += A @ A.T
    w, U = np.linalg.eigh(G)
    w, U = w[::-1], np.ascontiguousarray(U[:, ::-1])
    w = np.clip(w, 0.0, None)
    rmax = int(np.sum(w > (1e-13 * w[0] if w[0] > 0 else 0.0)))
    tail = np.r_[np.cumsum(w[::-1])[::-1], 0.0]  # tail[r] = sum_{i>=r} w_i (energy left at rank r)

    def max_err(r):
        Ur = U[:, :r]
        e = 0.0
        for b in blocks:
            A = block(b)
            R = A - Ur @ (Ur.T @ A) if r else A
            e = max(e, float(np.sqrt(np.max(np.sum(R.reshape(T, -1, 3) ** 2, axis=2)))))
        return e

    # bounds: the Frobenius tail bounds the max error from above; the mean error from below
    n_entries = T * len(idx)
    hi = next((r for r in range(rmax + 1) if tail[r] <= tol * tol), rmax)
    lo = next((r for r in range(hi + 1) if tail[r] <= n_entries * tol * tol), hi)
    if max_err(lo) <= tol:
        hi = lo
    else:
        if max_err(hi) > tol:  # numerical floor of the Gram route: take the exact SVD
            return _compress_exact(C, idx, tol, max_rank)
        while hi - lo > 1:
            mid = (lo + hi) // 2
            if max_err(mid) <= tol:
                hi = mid
            else:
                lo = mid
    r = hi
    if max_rank is not None and r > int(max_rank):
        raise FaceLabError(
            f"Keeping every vertex within {tol:.3g} scene units needs {r} corrective shapes, more than "
            f"max_rank={int(max_rank)}; raise max_rank or the tolerance."
        )
    Ur = U[:, :r]
    basis = np.zeros((r, V, 3))
    for b in blocks:
        basis[:, b, :] = (Ur.T @ block(b)).reshape(r, len(b), 3)
    return _normalise(basis, Ur.copy())


def _normalise(basis, weights):
    peak = np.max(np.abs(weights), axis=0) if weights.size else np.zeros(0)
    peak = np.where(peak > 0, peak, 1.0)
    return basis * peak[:, None, None], weights / peak


def _compress_exact(C, idx, tol, max_rank):
    T, V, _ = C.shape
    A = np.asarray(C[:, idx, :], dtype=np.float64).reshape(T, -1)
    U, s, Vt = np.linalg.svd(A, full_matrices=False)
    r = len(s)
    for k in range(len(s) + 1):
        R = A - (U[:, :k] * s[:k]) @ Vt[:k]
        if np.sqrt(np.max(np.sum(R.reshape(T, -1, 3) ** 2, axis=2))) <= tol:
            r = k
            break
    if max_rank is not None and r > int(max_rank):
        raise FaceLabError(
            f"Keeping every vertex within {tol:.3g} scene units needs {r} corrective shapes, more than "
            f"max_rank={int(max_rank)}; raise max_rank or the tolerance."
        )
    basis = np.zeros((r, V, 3))
    basis[:, idx, :] = (s[:r, None] * Vt[:r]).reshape(r, len(idx), 3)
    return _normalise(basis, U[:, :r].copy())


def reconstruct(basis, weights, frames=None) -> np.ndarray:
    """Corrections from a basis and weights (the inverse of :func:`compress`).

    Parameters
    ----------
    basis : (r,V,3) array_like
        Corrective shapes, scene units.
    weights : (T,r) array_like
        Per-frame weights.
    frames : array_like of int, optional
        Only these frames (default: all ``T``).

    Returns
    -------
    (T',V,3) float64 ndarray
        ``sum_i weights[t,i] * basis[i]``, scene units.
    """
    B = np.asarray(basis, dtype=np.float64)
    W = np.asarray(weights, dtype=np.float64)
    if B.ndim != 3 or B.shape[-1] != 3 or W.ndim != 2 or W.shape[1] != B.shape[0]:
        raise FaceLabError(
            f"basis (r,V,3) and weights (T,r) do not match: got {B.shape} and {W.shape}; pass the pair from compress()."
        )
    if frames is not None:
        W = W[np.asarray(frames, dtype=np.int64)]
    return (W @ B.reshape(B.shape[0], B.shape[1] * 3)).reshape(len(W), B.shape[1], 3)
