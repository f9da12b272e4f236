"""Geodesic distance on a triangle mesh, from a set of source vertices up to a limit.

Edge-path (Dijkstra) distances over the mesh edges, weighted by their
length, bound the region that can lie within the limit; on that sub-mesh the
exact polyhedral geodesic distance of Mitchell, Mount and Papadimitriou 1987
("The Discrete Geodesic Problem"), as implemented by libigl's
``exact_geodesic``, replaces them when libigl is available. Used for the
geodesic bands of the lip regions (:mod:`facelab_addon.core.lips.regions`),
the contact-loop search (:mod:`facelab_addon.core.lips.lip_loop`) and the
lip-contour weights of retargeting. Positions and distances are in scene
units. No bpy in this module.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse.csgraph import dijkstra as _dijkstra

from ..errors import MeshError
from .mesh import edge_length_graph, face_areas

__all__ = ["geodesic_distance", "exact_geodesic_safe"]


#: A triangle whose smallest height is below this share of the mesh's mean edge length is a sliver.
SLIVER = 1e-6


def exact_geodesic_safe(vertices, faces) -> bool:
    """Whether libigl's ``exact_geodesic`` can be run on this triangle mesh without crashing the process.

    libigl (MMP) assumes an oriented 2-manifold of proper triangles; on other input it can end in a
    segmentation fault (a perturbed grid with holes, flipped or duplicated triangles, an edge shared by
    three triangles, slivers). The mesh must have: finite positions; no triangle with a repeated corner
    or a height below :data:`SLIVER` of the mean edge length; every edge in at most two triangles, which
    run along it in opposite directions (consistent orientation, no duplicate triangles); and no vertex
    where two fans of triangles meet (a bow tie: more than two boundary edges at a vertex).

    Parameters
    ----------
    vertices : (V,3) float
    faces : (F,3) int
        Indices into ``vertices``.
    """
    V = np.asarray(vertices, dtype=np.float64)
    F = np.asarray(faces, dtype=np.int64)
    if len(F) == 0:
        return True
    if not np.isfinite(V[np.unique(F)]).all():
        return False
    if ((F[:, 0] == F[:, 1]) | (F[:, 1] == F[:, 2]) | (F[:, 2] == F[:, 0])).any():
        return False
    e = np.stack([V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 1]], V[F[:, 0]] - V[F[:, 2]]], axis=1)
    length = np.linalg.norm(e, axis=2)  # (F,3)
    mean = float(length.mean())
    if not mean > 0:
        return False
    height = 2.0 * face_areas(V, F) / np.maximum(length.max(axis=1), 1e-300)
    if (height < SLIVER * mean).any():
        return False
    half = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])  # directed edges
    if len(np.unique(half, axis=0)) != len(half):  # an edge run twice the same way: flipped or duplicated
        return False
    und, count = np.unique(np.sort(half, axis=1), axis=0, return_counts=True)
    if (count > 2).any():  # non-manifold edge
        return False
    boundary = und[count == 1]
    per_vertex = np.bincount(boundary.ravel(), minlength=len(V))
    return bool((per_vertex <= 2).all())


def geodesic_distance(vertices, faces, sources, limit=np.inf, *, exact: bool = True) -> np.ndarray:
    """Geodesic distance from a set of source vertices, up to ``limit``.

    Edge-path (Dijkstra) distances first find the vertices that may lie within
    ``limit``; on that sub-mesh the exact polyhedral geodesic distance
    (libigl ``exact_geodesic``) is computed when libigl is available.

    Parameters
    ----------
    vertices : (V,3) array_like
        Positions, scene units.
    faces : (F,3) int array_like
        Triangles.
    sources : (s,) int array_like
        Source vertex indices (distance 0).
    limit : float
        Distances beyond ``limit`` (scene units) are not needed; they are
        reported as ``inf``.
    exact : bool
        Use libigl's exact geodesics (default); ``False`` returns the
        edge-path distance, an overestimate of up to about 15 percent. The
        edge-path distance is also what a mesh libigl cannot take gives
        (:func:`exact_geodesic_safe`: slivers, flipped or non-manifold triangles).

    Returns
    -------
    (V,) float64 ndarray
        Distance in scene units; ``inf`` beyond ``limit`` or unreachable.
    """
    V = np.asarray(vertices, dtype=np.float64)
    F = np.asarray(faces)
    nv = len(V)
    if V.ndim != 2 or V.shape[1] != 3 or F.ndim != 2 or F.shape[1] != 3 or not np.issubdtype(F.dtype, np.integer):
        raise MeshError(f"Expected vertices (V,3) and integer triangles (F,3), got {V.shape} and {F.shape} "
                        f"{F.dtype}; triangulate the mesh first.")
    F = F.astype(np.int64)
    if F.size and (F.min() < 0 or F.max() >= nv):
        raise MeshError(f"Face indices are out of range [0, {nv}); the faces do not belong to this mesh.")
    if not np.isfinite(V).all():
        raise MeshError("The mesh has NaN or infinite coordinates; fix it before measuring distances on it.")
    src = np.asarray(sources)
    if src.size == 0 or not np.issubdtype(src.dtype, np.integer) or src.min() < 0 or src.max() >= nv:
        raise MeshError(f"The source vertices must be a non-empty set of vertex indices in [0, {nv}); "
                        "select the vertices to measure from.")
    src = np.unique(src.astype(np.int64))
    if not limit >= 0:
        raise MeshError(f"The distance limit must be a non-negative distance, got {limit!r}.")
    G, _, _ = edge_length_graph(V, F, nv)
    reach = 1.5 * limit if np.isfinite(limit) else np.inf
    dg = _dijkstra(G, directed=False, indices=src, min_only=True, limit=reach)
    out = dg
    if exact:
        try:
            import igl
        except Exception:  # pragma: no cover - libigl missing: edge-path distance
            igl = None
        if igl is not None:
            sub = np.isfinite(dg)
            fsel = sub[F].all(axis=1) & (face_areas(V, F) > 0)  # exact geodesics need proper triangles
            SF = F[fsel]
            if not exact_geodesic_safe(V, SF):  # libigl would crash the process (segfault): edge paths instead
                SF = SF[:0]
            used = np.unique(SF)
            remap = -np.ones(nv, dtype=np.int64)
            remap[used] = np.arange(len(used))
            srcs = remap[src]
            srcs = srcs[srcs >= 0]
            if len(srcs) and len(SF):
                d = igl.exact_geodesic(
                    V=np.ascontiguousarray(V[used]),
                    F=np.ascontiguousarray(remap[SF]),
                    VS=np.ascontiguousarray(srcs),
                    FS=np.zeros(0, dtype=np.int64),
                    VT=np.arange(len(used), dtype=np.int64),
                    FT=np.zeros(0, dtype=np.int64),
                )
                d = np.asarray(d, dtype=np.float64)
                out = np.full(nv, np.inf)
                out[used] = np.where(np.isfinite(d), np.minimum(d, dg[used]), dg[used])
                out[src] = 0.0
    out = np.asarray(out, dtype=np.float64).copy()
    out[out > limit] = np.inf
    return out
