"""Midpoint subdivision of a triangle mesh, for production-scale tests and benchmarks.

Every triangle is split into four at its edge midpoints (no smoothing: the surface and any
linear per-vertex attribute, such as blendshape deltas, stay exactly what they were). The
ICT-FaceKit face (26,719 vertices, 52,220 triangles) becomes a 105k-vertex face whose
expressions are the subdivided expressions, so the shapes, regions and captures the
benchmarks build on the original face exist at four times the resolution.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

__all__ = ["subdivide_midpoint"]


def subdivide_midpoint(vertices, faces):
    """Split every triangle into four at its edge midpoints.

    Parameters
    ----------
    vertices : (V,3) array_like
        Positions, any units.
    faces : (F,3) int array_like
        Triangles.

    Returns
    -------
    vertices : (V+E,3) float64 ndarray
        The original vertices followed by one midpoint per edge (``E`` unique edges).
    faces : (4F,3) int64 ndarray
        Corner triangles ``(a, ab, ca)``, ``(ab, b, bc)``, ``(ca, bc, c)`` and the middle
        ``(ab, bc, ca)`` of each input triangle, in input order; same orientation.
    S : (V+E, V) scipy.sparse.csr_matrix
        The linear map of per-vertex attributes: ``S @ x`` subdivides any (V,) or (V,k)
        attribute (positions, deltas) the same way.
    """
    V = np.asarray(vertices, dtype=np.float64)
    F = np.asarray(faces, dtype=np.int64)
    n = len(V)
    e = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])  # (3F, 2): ab, bc, ca
    key = np.sort(e, axis=1)
    uniq, inv = np.unique(key, axis=0, return_inverse=True)
    inv = inv.ravel()
    mid = n + inv.reshape(3, len(F)).T  # (F, 3): ab, bc, ca
    a, b, c = F.T
    ab, bc, ca = mid.T
    out_f = np.stack([np.stack([a, ab, ca], 1), np.stack([ab, b, bc], 1), np.stack([ca, bc, c], 1),
                      np.stack([ab, bc, ca], 1)], 1).reshape(-1, 3)
    E = len(uniq)
    rows = np.r_[np.arange(n), np.repeat(n + np.arange(E), 2)]
    cols = np.r_[np.arange(n), uniq.ravel()]
    vals = np.r_[np.ones(n), np.full(2 * E, 0.5)]
    S = sp.csr_matrix((vals, (rows, cols)), shape=(n + E, n))
    return S @ V, out_f, S
