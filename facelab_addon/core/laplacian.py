"""Discrete mesh Laplacians.

* ``uniform_laplacian``: the umbrella operator of Laplacian surface editing
  (Sorkine et al. 2004, [SCOL*04] in Dinev et al. 2018 §5):
  ``delta_i = v_i - mean(v_j for neighbours j)``. It depends on topology only,
  so a solver built on it can be factored once per mesh topology.
* ``cotangent_laplacian``: the cotangent operator (used by Bhat et al. 2013
  §4.3 for the out-of-subspace corrective).

Both return sparse ``(V,V)`` matrices ``L`` with ``L @ ones = 0``; the
Laplacian coordinates of positions ``X (V,3)`` are ``L @ X`` (scene units).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from .mesh import vertex_adjacency

__all__ = ["uniform_laplacian", "cotangent_laplacian", "laplacian"]


def uniform_laplacian(faces, n_vertices: int, adjacency=None) -> sp.csr_matrix:
    """Umbrella Laplacian ``I - D^-1 A``.

    Parameters
    ----------
    faces : (F,3) int array_like
        Triangles.
    n_vertices : int
        Number of vertices ``V`` (isolated vertices get a zero row).
    adjacency : (V,V) sparse, optional
        Precomputed ``mesh.vertex_adjacency(faces, V)``.

    Returns
    -------
    (V,V) scipy.sparse.csr_matrix
        Row-normalised, positive on the diagonal; ``L @ X`` are the Laplacian
        coordinates of ``X (V,3)`` in scene units.
    """
    A = vertex_adjacency(faces, n_vertices) if adjacency is None else adjacency
    deg = np.asarray(A.sum(axis=1)).ravel()
    inv = np.divide(1.0, deg, out=np.zeros_like(deg), where=deg > 0)
    # isolated vertices get a zero row instead of identity
    L = sp.diags((deg > 0).astype(float)) - sp.diags(inv) @ A
    return L.tocsr()


def cotangent_laplacian(vertices, faces) -> sp.csr_matrix:
    """Cotangent Laplacian ``L_ij = -(cot a_ij + cot b_ij)/2``, ``L_ii = -sum_j L_ij``.

    Parameters
    ----------
    vertices : (V,3) array_like
        Positions, scene units.
    faces : (F,3) int array_like
        Triangles.

    Returns
    -------
    (V,V) scipy.sparse.csr_matrix
        Symmetric positive semi-definite (the negative of libigl's
        ``cotmatrix``); dimensionless weights, so ``L @ X`` is in scene units.
    """
    V = np.asarray(vertices, dtype=np.float64)
    F = np.asarray(faces, dtype=np.int64)
    n = len(V)
    rows, cols, vals = [], [], []
    for k in range(3):
        i, j, o = F[:, (k + 1) % 3], F[:, (k + 2) % 3], F[:, k]
        u, w = V[i] - V[o], V[j] - V[o]
        cross = np.linalg.norm(np.cross(u, w), axis=1)
        cot = np.einsum("ij,ij->i", u, w) / np.maximum(cross, 1e-300)
        rows += [i, j]
        cols += [j, i]
        vals += [-0.5 * cot, -0.5 * cot]
    r, c, v = np.concatenate(rows), np.concatenate(cols), np.concatenate(vals)
    W = sp.coo_matrix((v, (r, c)), shape=(n, n)).tocsr()
    L = W - sp.diags(np.asarray(W.sum(axis=1)).ravel())
    return L.tocsr()


def laplacian(vertices, faces, kind: str = "uniform", adjacency=None) -> sp.csr_matrix:
    """``uniform_laplacian`` or ``cotangent_laplacian`` by name (``"uniform"``/``"cotangent"``)."""
    if kind == "uniform":
        return uniform_laplacian(faces, len(vertices), adjacency)
    if kind in ("cotangent", "cot"):
        return cotangent_laplacian(vertices, faces)
    raise ValueError(f"unknown Laplacian kind {kind!r}; use 'uniform' or 'cotangent'")
