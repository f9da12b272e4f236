"""The rigid motion that best maps one point set onto another (Kabsch), optionally trimmed.

Used to tell a head's turn from its expression: the rotation from the face at rest to a captured
frame, fitted on the vertices that moved least non-rigidly (:func:`rigid_fit` with ``keep`` < 1).
"""

from __future__ import annotations

import numpy as np

from ..errors import FaceLabError

__all__ = ["rigid_fit"]


def rigid_fit(source, target, *, keep: float = 1.0, iterations: int = 3):
    """Rotation ``R`` and translation ``t`` minimising ``sum_i ||R s_i + t - q_i||^2`` (no scale, no reflection).

    Parameters
    ----------
    source, target : (N,3) float
        Corresponding points, any units (the same for both).
    keep : float
        In (0, 1]: after a fit on all points, refit ``iterations - 1`` times on the fraction ``keep``
        of them with the smallest residuals (a trimmed fit: the points that moved rigidly decide, an
        expression or an opened jaw does not). 1: one least-squares fit on all points.
    iterations : int
        Fits when ``keep < 1``.

    Returns
    -------
    R : (3,3) float ndarray
        A proper rotation (``det R = 1``).
    t : (3,) float ndarray
        Same units as the points.

    Raises
    ------
    FaceLabError
        Fewer than 3 points, shapes that differ, or non-finite values.
    """
    A = np.asarray(source, dtype=np.float64)
    B = np.asarray(target, dtype=np.float64)
    if A.shape != B.shape or A.ndim != 2 or A.shape[1] != 3:
        raise FaceLabError(f"rigid_fit needs two (N,3) point sets of the same shape, got {A.shape} and {B.shape}.")
    if len(A) < 3:
        raise FaceLabError(f"rigid_fit needs at least 3 points, got {len(A)}.")
    if not (np.isfinite(A).all() and np.isfinite(B).all()):
        raise FaceLabError("rigid_fit got NaN or infinite positions; check the mesh.")
    if not 0 < keep <= 1:
        raise FaceLabError(f"keep must be in (0, 1], got {keep!r}.")
    R, t = _kabsch(A, B)
    if keep < 1:
        n = max(3, int(np.ceil(keep * len(A))))
        for _ in range(max(int(iterations), 1) - 1):
            use = np.argpartition(np.linalg.norm(A @ R.T + t - B, axis=1), n - 1)[:n]  # the most rigid
            R, t = _kabsch(A[use], B[use])
    return R, t


def _kabsch(A, B):
    """``(R, t)`` of the least-squares rigid fit ``R a + t ~ b`` of (N,3) points."""
    ca, cb = A.mean(axis=0), B.mean(axis=0)
    U, _, Vt = np.linalg.svd((B - cb).T @ (A - ca))
    R = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt)) or 1.0]) @ Vt
    return R, cb - R @ ca
