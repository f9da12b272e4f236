"""Discrete mesh Laplacians.

* ``uniform_laplacian``: the umbrella operator of Laplacian surface editing
  (Sorkine et al. 2004, [SCOL*04] in Dinev et al. 2018 §5):
  ``delta_i = v_i - mean(v_j for neighbours j)``. It depends on topology only,
  so a solver built on it can be factored once per mesh topology.
* ``cotangent_laplacian``: the cotangent operator (used by Bhat et al. 2013
  §4.3 for the out-of-subspace corrective).
* ``poisson_operator``: the gradient-domain Poisson system ``L x = D g`` of a
  triangle region, which turns per-triangle deformation gradients back into
  positions (Dinev et al. 2018 §4; Sumner and Popović 2004).

Both return sparse ``(V,V)`` matrices ``L`` with ``L @ ones = 0``; the
Laplacian coordinates of positions ``X (V,3)`` are ``L @ X`` (scene units).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ..errors import MeshError, UsageError
from .mesh import vertex_adjacency

__all__ = ["uniform_laplacian", "cotangent_laplacian", "laplacian", "poisson_operator"]


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
    if adjacency is None:
        F = np.asarray(faces)
        if F.size and (F.ndim != 2 or F.shape[1] != 3 or not np.issubdtype(F.dtype, np.integer)
                       or F.min() < 0 or F.max() >= int(n_vertices)):
            raise MeshError(f"faces must be an (F,3) integer array with indices in [0, {int(n_vertices)}); "
                            "the faces do not belong to this mesh.")
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
    raise UsageError(f"unknown Laplacian kind {kind!r}; use 'uniform' or 'cotangent'")


def poisson_operator(rest_vertices, faces, region_faces):
    """Gradient-domain Poisson operator of a triangle region.

    For positions ``x`` (one coordinate) the per-triangle gradient is
    ``G x`` (3 per triangle, in the rest triangle's plane). The energy
    ``Σ_t a_t ||(G x)_t - g_t||²`` has normal equations ``L x = D g`` with
    ``L = Gᵀ A G`` (the cotangent Laplacian of the region) and ``D = Gᵀ A``.
    Targets for coordinate ``c`` from deformation gradients ``F (n,3,3)`` are
    ``g_t = F_t[c, :]``, i.e. the matrix ``F.transpose(0,2,1).reshape(3n, 3)``.

    Parameters
    ----------
    rest_vertices : (V,3) array_like
        Rest positions, scene units.
    faces : (F,3) int array_like
        Triangles.
    region_faces : (n,) int array_like
        Triangles of the region.

    Returns
    -------
    L : (V,V) scipy.sparse.csr_matrix
        Stiffness matrix, units of area / length² (unitless); zero outside
        the region's vertices.
    D : (V,3n) scipy.sparse.csr_matrix
        Divergence operator, units of area (scene units²).
    """
    R = np.asarray(rest_vertices, dtype=np.float64)
    T = np.asarray(faces, dtype=np.int64)[np.asarray(region_faces, dtype=np.int64)]
    n = len(T)
    p0, p1, p2 = R[T[:, 0]], R[T[:, 1]], R[T[:, 2]]
    nrm = np.cross(p1 - p0, p2 - p0)
    a2 = np.linalg.norm(nrm, axis=1)
    nh = nrm / a2[:, None]
    grads = np.stack(
        [np.cross(nh, p2 - p1), np.cross(nh, p0 - p2), np.cross(nh, p1 - p0)], axis=1
    ) / a2[:, None, None]  # (n, corner, xyz)
    rows = (3 * np.arange(n)[:, None, None] + np.arange(3)[None, None, :]).repeat(3, axis=1)  # (n, corner, axis)
    cols = np.broadcast_to(T[:, :, None], (n, 3, 3))
    G = sp.csr_matrix((grads.ravel(), (rows.ravel(), cols.ravel())), shape=(3 * n, len(R)))
    area = np.repeat(0.5 * a2, 3)
    D = (G.T @ sp.diags(area)).tocsr()
    L = (D @ G).tocsr()
    return L, D
