"""Triangle-mesh utilities shared by every solver.

Vertices are float64 ``(V,3)`` in scene units, triangles int64 ``(F,3)``.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ..errors import MeshError

__all__ = [
    "validate_mesh",
    "triangulate",
    "face_areas",
    "face_normals",
    "vertex_normals",
    "unique_edges",
    "edge_faces",
    "vertex_adjacency",
    "grow_region",
    "connected_components",
    "edge_length_graph",
    "faces_within",
]


def validate_mesh(vertices, faces, *, name: str = "mesh", min_area: float = 0.0):
    """Check a triangle mesh and return it as ``(float64 (V,3), int64 (F,3))``.

    Parameters
    ----------
    vertices : (V,3) array_like
        Vertex positions, scene units.
    faces : (F,3) array_like of int
        Triangles (0-based vertex indices).
    name : str
        Used in error messages (for example the Blender object name).
    min_area : float
        Triangles with area ``<= min_area`` (scene units squared) are
        degenerate. The default 0 rejects exactly-zero areas only.

    Raises
    ------
    MeshError
        On NaN/inf positions, non-triangles, out-of-range indices, repeated
        vertices in a triangle or degenerate (zero-area) triangles.
    """
    V = np.asarray(vertices, dtype=np.float64)
    F = np.asarray(faces)
    if V.ndim != 2 or V.shape[1] != 3 or len(V) == 0:
        raise MeshError(f"{name}: vertices must be a non-empty (V,3) array, got shape {V.shape}.")
    if F.ndim != 2 or F.shape[1] != 3 or len(F) == 0:
        raise MeshError(
            f"{name}: faces must be a non-empty (F,3) array of triangles, got shape {F.shape}; "
            "triangulate polygons first."
        )
    if not np.issubdtype(F.dtype, np.integer):
        raise MeshError(f"{name}: face indices must be integers.")
    F = F.astype(np.int64, copy=False)
    bad = ~np.isfinite(V).all(axis=1)
    if bad.any():
        idx = np.flatnonzero(bad)
        raise MeshError(
            f"{name}: {len(idx)} vertices have NaN or infinite coordinates (first: {idx[:5].tolist()}); "
            "fix or re-import the capture for this frame."
        )
    if F.min() < 0 or F.max() >= len(V):
        raise MeshError(f"{name}: face indices out of range [0, {len(V)}); the topology does not match the vertices.")
    rep = (F[:, 0] == F[:, 1]) | (F[:, 1] == F[:, 2]) | (F[:, 0] == F[:, 2])
    area = face_areas(V, F)
    degen = rep | (area <= min_area)
    if degen.any():
        idx = np.flatnonzero(degen)
        raise MeshError(
            f"{name}: {len(idx)} degenerate (zero-area) triangles, first faces {idx[:5].tolist()}; "
            "run Mesh > Clean Up > Degenerate Dissolve or fix the capture."
        )
    return V, F


def faces_within(mask, faces, *, every: bool = True) -> np.ndarray:
    """(F,) bool: the triangles with all three (``every``) or any (``every=False``) of their vertices in
    ``mask`` (V,) bool; ``mask[faces].all(axis=1)`` (or ``.any``) without the reduction along the short axis."""
    g = np.asarray(mask, bool)[np.asarray(faces)]
    if every:
        return g[:, 0] & g[:, 1] & g[:, 2]
    return g[:, 0] | g[:, 1] | g[:, 2]


def triangulate(poly_verts, poly_offsets):
    """Fan-triangulate polygons.

    Parameters
    ----------
    poly_verts : (C,) int array_like
        Concatenated polygon corner vertex indices.
    poly_offsets : (P+1,) int array_like
        Start of each polygon in ``poly_verts``; the last entry is ``C``.

    Returns
    -------
    tris : (F,3) int64 ndarray
    tri_poly : (F,) int64 ndarray
        The polygon each triangle came from.
    """
    pv = np.asarray(poly_verts, dtype=np.int64)
    off = np.asarray(poly_offsets, dtype=np.int64)
    sizes = np.diff(off)
    if (sizes < 3).any():
        raise MeshError("A polygon has fewer than 3 corners; clean up the mesh (Merge by Distance).")
    ntri = sizes - 2
    tri_poly = np.repeat(np.arange(len(sizes)), ntri)
    # k-th triangle of a polygon: (c0, c_{k+1}, c_{k+2})
    first = np.repeat(off[:-1], ntri)
    k = np.arange(len(tri_poly)) - np.repeat(np.cumsum(ntri) - ntri, ntri)
    tris = np.stack([pv[first], pv[first + k + 1], pv[first + k + 2]], axis=1)
    return tris, tri_poly


def face_areas(vertices, faces):
    """(F,) triangle areas, scene units squared."""
    V = np.asarray(vertices, dtype=np.float64)
    F = np.asarray(faces)
    # per coordinate (1D gathers): the products and sums of np.cross and np.linalg.norm, in their order
    X, Y, Z = (np.ascontiguousarray(V[:, k]) for k in range(3))
    F0, F1, F2 = (np.ascontiguousarray(F[:, k]) for k in range(3))
    x0, y0, z0 = X[F0], Y[F0], Z[F0]
    ax, ay, az = X[F1] - x0, Y[F1] - y0, Z[F1] - z0
    bx, by, bz = X[F2] - x0, Y[F2] - y0, Z[F2] - z0
    c0 = ay * bz - az * by
    c1 = az * bx - ax * bz
    c2 = ax * by - ay * bx
    return 0.5 * np.sqrt(c0 * c0 + c1 * c1 + c2 * c2)


def face_normals(vertices, faces, *, unit: bool = True):
    """(F,3) triangle normals (counter-clockwise = front); area-weighted if ``unit=False``."""
    V = np.asarray(vertices, dtype=np.float64)
    F = np.asarray(faces)
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    if unit:
        n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-300)
    return n


def vertex_normals(vertices, faces):
    """(V,3) unit vertex normals, area-weighted averages of the face normals."""
    V = np.asarray(vertices, dtype=np.float64)
    F = np.asarray(faces)
    fn = face_normals(V, F, unit=False)
    vn = np.zeros_like(V)
    for c in range(3):
        np.add.at(vn, F[:, c], fn)
    vn /= np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-300)
    return vn


def unique_edges(faces):
    """Unique undirected edges.

    Returns
    -------
    edges : (E,2) int64
        Sorted vertex pairs ``(a < b)``.
    face_edge : (F,3) int64
        Edge index of each triangle side ``(v0v1, v1v2, v2v0)``.
    """
    keys, base = _side_keys(faces)
    keys, inv = np.unique(keys, return_inverse=True)
    edges = np.stack([keys // base, keys % base], axis=1)
    return edges, inv.reshape(-1, 3)


def _side_keys(faces):
    """``(keys (3F,) int64, base)``: triangle side ``(v0v1, v1v2, v2v0)`` of each triangle in turn as
    ``min * base + max`` of its two vertices."""
    F = np.asarray(faces, dtype=np.int64)
    a, b = F.reshape(-1), F[:, [1, 2, 0]].reshape(-1)
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    base = np.int64(hi.max() + 1) if len(hi) else np.int64(1)
    return lo * base + hi, base


def edge_faces(faces):
    """Edges with their (up to two) adjacent triangles.

    Returns
    -------
    edges : (E,2) int64
    ef : (E,2) int64
        Adjacent triangle indices; ``-1`` for a border edge. Non-manifold
        edges keep their first two triangles.
    """
    F = np.asarray(faces, dtype=np.int64)
    edges, fe = unique_edges(F)
    ef = -np.ones((len(edges), 2), dtype=np.int64)
    e = fe.ravel()
    f = np.repeat(np.arange(len(F)), 3)
    order = np.argsort(e, kind="stable")
    e, f = e[order], f[order]
    first = np.r_[True, e[1:] != e[:-1]]
    ef[e[first], 0] = f[first]
    second = ~first & np.r_[False, first[:-1]]
    ef[e[second], 1] = f[second]
    return edges, ef


def vertex_adjacency(faces, n_vertices: int):
    """(V,V) symmetric CSR 0/1 adjacency matrix of the mesh edges."""
    F = np.asarray(faces, dtype=np.int64)
    n = int(n_vertices)
    i = np.concatenate([F[:, 0], F[:, 1], F[:, 2], F[:, 1], F[:, 2], F[:, 0]])
    j = np.concatenate([F[:, 1], F[:, 2], F[:, 0], F[:, 0], F[:, 1], F[:, 2]])
    A = sp.csr_matrix((np.ones(len(i)), (i, j)), shape=(n, n))
    A.data[:] = 1.0
    return A


def grow_region(mask, adjacency, rings: int):
    """Grow a (V,) bool vertex mask by ``rings`` edge rings over ``adjacency`` (V,V)."""
    m = np.asarray(mask, dtype=bool).copy()
    for _ in range(int(rings)):
        m = m | (adjacency @ m.astype(np.float64) > 0)
    return m


def connected_components(faces, n_vertices: int):
    """(V,) int component label of every vertex (isolated vertices get their own)."""
    from scipy.sparse.csgraph import connected_components as cc

    _, labels = cc(vertex_adjacency(faces, n_vertices), directed=False)
    return labels


def edge_length_graph(vertices, faces, n_vertices: int | None = None, *, min_length: float = 0.0):
    """Symmetric graph of the mesh edges weighted by their length (for Dijkstra and friends).

    Parameters
    ----------
    vertices : (V,3) array_like
        Positions, scene units.
    faces : (F,3) int array_like
        Triangles.
    n_vertices : int, optional
        Size of the graph (default ``len(vertices)``).
    min_length : float
        Lengths are clamped to at least this (scene units), so coincident
        vertices stay connected.

    Returns
    -------
    graph : (n,n) scipy.sparse.csr_matrix
        ``graph[a, b]`` = length of edge ``ab``, scene units.
    edges : (E,2) int64
        Sorted vertex pairs ``(a < b)``.
    lengths : (E,) float64
        Edge lengths, scene units (after the clamp).
    """
    V = np.asarray(vertices, dtype=np.float64)
    n = len(V) if n_vertices is None else int(n_vertices)
    keys, base = _side_keys(faces)
    keys = np.unique(keys)  # the edges of unique_edges, without their triangles
    E = np.stack([keys // base, keys % base], axis=1)
    w = np.linalg.norm(V[E[:, 0]] - V[E[:, 1]], axis=1)
    if min_length > 0:
        w = np.maximum(w, min_length)
    G = sp.coo_matrix((np.r_[w, w], (np.r_[E[:, 0], E[:, 1]], np.r_[E[:, 1], E[:, 0]])), shape=(n, n))
    return G.tocsr(), E, w
