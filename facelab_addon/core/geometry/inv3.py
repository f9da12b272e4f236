"""Closed-form inverses of many 3x3 matrices (adjugate over determinant).

One vectorised formula instead of a LAPACK call per matrix: equal to ``np.linalg.inv`` to
round-off on well-conditioned matrices and far cheaper on large stacks of small ones (triangle
shape matrices, tetrahedron edge matrices, per-corner frames).
"""

from __future__ import annotations

import numpy as np

__all__ = ["inv3"]


def inv3(A, *, return_det: bool = False):
    """Inverses of (...,3,3) matrices in closed form.

    Parameters
    ----------
    A : (...,3,3) array_like of float
        The matrices (any units u; the inverse has units 1/u).
    return_det : bool
        Also return the determinants.

    Returns
    -------
    inv : (...,3,3) float64 ndarray
        ``inv[k] @ A[k] = I``; inf/NaN entries for a singular matrix (no warning is raised).
    det : (...,) float64 ndarray
        The determinants (only with ``return_det``).
    """
    A = np.asarray(A, dtype=np.float64)
    r0, r1, r2 = A[..., 0, :], A[..., 1, :], A[..., 2, :]
    cols = np.stack([np.cross(r1, r2), np.cross(r2, r0), np.cross(r0, r1)], axis=-1)  # adjugate
    c0 = cols[..., :, 0]
    det = r0[..., 0] * c0[..., 0] + r0[..., 1] * c0[..., 1] + r0[..., 2] * c0[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = cols / det[..., None, None]
    return (inv, det) if return_det else inv
