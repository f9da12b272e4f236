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

:func:`compress_streamed` answers a different question for shots that do not fit in memory:
*does* the correction fit in at most ``max_rank`` shapes within ``tol``? It reads the frames
chunk by chunk (from a spool file, or from a low-rank product) and keeps only ``O(k·n)``
numbers: a randomized range finder of the row space (one pass), a projection (second pass)
and a per-frame, per-vertex error check of the ranks up to ``max_rank`` (third and fourth passes).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np

from ..errors import FaceLabError, MeshError

__all__ = ["compress", "reconstruct", "compress_streamed", "low_rank_reader", "StreamedBasis", "DEFAULT_TOL_M",
           "StorageOutcome"]

#: Default tolerance, 0.01 mm, in metres.
DEFAULT_TOL_M = 1e-5

_BLOCK = 1024  # vertices per block
_BLOCK_VALUES = 4_000_000  # float64 values per streamed block (32 MB)


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


# --------------------------------------------------------------------------- streamed, bounded memory
@dataclass
class StreamedBasis:
    """What :func:`compress_streamed` found.

    Attributes
    ----------
    fits : bool
        Whether at most ``max_rank`` shapes keep every vertex of every frame within ``tol``.
    basis : (r,n,3) float64 ndarray
        Corrective shapes (scene units), scaled so each weight peaks at magnitude 1; ``r`` is the
        smallest rank within ``tol`` when ``fits``, else ``max_rank`` (the best it could do).
    weights : (T,r) float64 ndarray
        Per-frame weights in [-1, 1].
    frame_error : (T,) float64 ndarray
        Largest vertex error of each frame at rank ``r``, scene units (NaN for frames not measured
        when the correction does not fit: the energy beyond ``max_rank`` alone exceeds ``tol``, or a
        chunk of frames needs more shapes).
    max_error : float
        ``max(frame_error)``.
    """

    fits: bool
    basis: np.ndarray
    weights: np.ndarray
    frame_error: np.ndarray
    max_error: float


def low_rank_reader(basis, weights):
    """A chunk reader ``read(i, j) -> (j-i,n,3)`` of ``weights[i:j] @ basis`` for :func:`compress_streamed`.

    Parameters
    ----------
    basis : (r,n,3) array_like
        Shapes, scene units.
    weights : (T,r) array_like
    """
    B = np.asarray(basis, dtype=np.float64)
    W = np.asarray(weights, dtype=np.float64)
    if B.ndim != 3 or B.shape[-1] != 3 or W.ndim != 2 or W.shape[1] != B.shape[0]:
        raise MeshError(f"A low-rank correction needs basis (r,n,3) and weights (T,r); got {B.shape} and {W.shape}.")
    Bf = B.reshape(len(B), B.shape[1] * 3)  # explicit: a rank-0 basis (no correction) reads zeros

    def read(i, j):
        return (W[i:j] @ Bf).reshape(j - i, B.shape[1], 3)

    return read


def _chunks(T, chunk):
    for i in range(0, T, chunk):
        yield i, min(T, i + chunk)


def compress_streamed(read, T: int, n: int, tol: float, max_rank: int, *, oversample: int = 10, chunk: int = 64,
                      seed: int = 0, low_rank=None) -> StreamedBasis:
    """At most ``max_rank`` shapes within ``tol``, reading the corrections chunk by chunk.

    Parameters
    ----------
    read : callable(i, j) -> (j-i,n,3) array_like
        Frames ``i`` to ``j`` of the corrections, scene units (a memory-mapped spool slice,
        or :func:`low_rank_reader`). Called a few times per chunk; never asked for all frames.
    T, n : int
        Frames and vertices.
    tol : float
        Largest allowed error of any vertex in any frame, Euclidean, scene units.
    max_rank : int
        The key budget.
    oversample : int
        Extra random directions of the range finder (Halko et al. 2011).
    chunk : int
        Frames per read.
    seed : int
        Seed of the random test matrix (results are reproducible).
    low_rank : tuple of (basis (r,n,3), weights (T,r)), optional
        The corrections are exactly this product: its row space is used instead of a random
        sketch (no sampling error), and ``read`` should be ``low_rank_reader(*low_rank)``.

    Returns
    -------
    StreamedBasis

    Raises
    ------
    FaceLabError
        ``tol`` not positive, ``max_rank`` < 1, or NaN / infinite corrections.

    Notes
    -----
    Pass 1 sketches the row space, ``Z = Ωᵀ A`` with a Gaussian ``Ω`` (T,k), ``k = max_rank +
    oversample``; its orthonormal basis ``Q`` (3n,k) gives pass 2, ``W = A Q`` (T,k), whose small
    SVD orders the directions. Pass 3 finds, chunk by chunk, the first rank whose largest vertex error
    is within ``tol`` on every frame of the chunk (rank-1 updates of the residual, starting where the
    energy bound allows); pass 4 checks every frame at the largest such rank. When the energy left beyond
    ``max_rank`` already exceeds ``T·n·tol²`` (so the RMS error, a lower bound of the max error,
    is above ``tol``) pass 3 is skipped. Memory: ``O(k·n + chunk·n)`` floats.
    """
    tol = float(tol)
    if not (tol > 0 and np.isfinite(tol)):
        raise FaceLabError(f"The compression tolerance must be a positive distance in scene units, got {tol}.")
    if int(max_rank) < 1:
        raise FaceLabError(f"The key budget must be at least 1 shape, got {max_rank}.")
    T, n, max_rank = int(T), int(n), int(max_rank)
    m = 3 * n
    chunk = max(1, min(int(chunk), _BLOCK_VALUES // max(m, 1)))  # a block of about 32 MB at any mesh size
    if T == 0 or n == 0:
        return StreamedBasis(True, np.zeros((0, n, 3)), np.zeros((T, 0)), np.zeros(T), 0.0)

    def block(i, j):
        a = np.asarray(read(i, j), dtype=np.float64).reshape(j - i, m)
        if not np.isfinite(a).all():
            t = i + int(np.flatnonzero(~np.isfinite(a).all(axis=1))[0])
            raise MeshError(f"The correction of frame #{t} has NaN or infinite values; fix that frame's solve.")
        return a

    if low_rank is not None:  # the row space is known exactly
        B0 = np.asarray(low_rank[0], dtype=np.float64).reshape(len(low_rank[0]), m)
        Q = np.linalg.qr(B0.T)[0] if len(B0) else np.zeros((m, 0))
    else:  # pass 1: randomized sketch of the row space
        k = min(max_rank + int(oversample), T, m)
        rng = np.random.default_rng(seed)
        Z = np.zeros((k, m))
        for i, j in _chunks(T, chunk):
            Z += rng.standard_normal((j - i, k)).T @ block(i, j)
        Q = np.linalg.qr(Z.T)[0]
        del Z
    k = Q.shape[1]
    if low_rank is not None:  # pass 2: projections (of the small factors when the product is known)
        W = np.asarray(low_rank[1], dtype=np.float64) @ (B0 @ Q)
    else:
        W = np.empty((T, k))
        for i, j in _chunks(T, chunk):
            W[i:j] = block(i, j) @ Q
    U, s, Vt = np.linalg.svd(W, full_matrices=False)
    weights = U * s  # (T,k)
    basis = Vt @ Q.T  # (k,m) orthonormal rows, ordered by energy
    del Q
    r_cap = min(max_rank, k)
    # energy beyond the budget (the sketch's own, a lower bound of the true tail when sampled)
    total = 0.0
    if low_rank is None:
        for i, j in _chunks(T, chunk):
            total += float(np.sum(block(i, j) ** 2))
    else:
        total = float(np.sum(s**2))
    tail = max(total - float(np.sum(s[:r_cap] ** 2)), 0.0)
    if tail > T * n * tol * tol:
        return StreamedBasis(False, *_normalise(basis[:r_cap].reshape(r_cap, n, 3), weights[:, :r_cap].copy()),
                             np.full(T, np.nan), float(np.sqrt(tail / (T * n))))
    # pass 3: per chunk, the first rank from r_lo on that keeps its frames within tol (below r_lo the RMS
    # error alone, energy left / entries, exceeds tol); ranks are added as rank-1 updates of the residual
    left = total - np.r_[0.0, np.cumsum(s[:r_cap] ** 2)]
    r_lo = int(np.flatnonzero(left <= T * n * tol * tol)[0])
    r_need = r_lo
    for i, j in _chunks(T, chunk):
        R = block(i, j) - weights[i:j, :r_lo] @ basis[:r_lo]  # a new array: the caller's frames stay unchanged
        r = max(r_lo, r_need)
        if r > r_lo:
            R -= weights[i:j, r_lo:r] @ basis[r_lo:r]
        while True:
            e = _frame_errors(R, n)
            if e.max() <= tol:
                break
            if r == r_cap:  # this chunk needs more than the budget: it does not fit
                b, w = _normalise(basis[:r_cap].reshape(r_cap, n, 3), weights[:, :r_cap].copy())
                fe = np.full(T, np.nan)
                fe[i:j] = e
                return StreamedBasis(False, b, w, fe, float(e.max()))
            R -= np.multiply.outer(weights[i:j, r], basis[r])
            r += 1
        r_need = r
    # pass 4: every frame at the rank found (a rank that fits one chunk may not fit an earlier one exactly)
    r = r_need
    while True:
        fe = np.empty(T)
        for i, j in _chunks(T, chunk):
            fe[i:j] = _frame_errors(block(i, j) - weights[i:j, :r] @ basis[:r], n)
        if fe.max() <= tol or r == r_cap:
            break
        r += 1
    b, w = _normalise(basis[:r].reshape(r, n, 3), weights[:, :r].copy())
    return StreamedBasis(bool(fe.max() <= tol), b, w, fe, float(fe.max()))


def _frame_errors(R, n):
    """Largest vertex norm of each row of ``R`` (c, 3n)."""
    sq = np.square(R)
    v = sq[:, 0::3] + sq[:, 1::3]
    v += sq[:, 2::3]
    return np.sqrt(v.max(axis=1))


class StorageOutcome(enum.Enum):
    """How a per-frame correction was (or is to be) stored.

    ``NONE``: every frame is within the tolerance of zero, nothing stored; ``KEYS``: a few corrective keys,
    at most the key budget; ``KEYS_OVER_BUDGET``: more keys than the budget, because a point cache had no
    place (an unsaved .blend without a cache folder); ``CACHE``: a point cache of the whole mesh played by a
    Mesh Cache modifier; ``PATCH_CACHE``: a point cache of the corrected vertices only, added after the capture.
    """

    NONE = "none"
    KEYS = "keys"
    KEYS_OVER_BUDGET = "keys over budget"
    CACHE = "cache"
    PATCH_CACHE = "patch cache"

    @property
    def mode(self) -> str:
        """``"none"``, ``"keys"`` or ``"cache"``: what the scene holds."""
        return {"keys over budget": "keys", "patch cache": "cache"}.get(self.value, self.value)

    @property
    def reported(self) -> bool:
        """Whether a report says where the correction went: anything but a few keys within the budget (or nothing)."""
        return self not in (StorageOutcome.NONE, StorageOutcome.KEYS)
