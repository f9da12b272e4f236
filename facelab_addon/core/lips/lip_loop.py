"""The inner-lip contact loop: the closed edge loop where the upper and lower lip meet.

Dinev et al. 2018, "User-Guided Lip Correction for Facial Performance
Capture", Fig. 2: the mouth and inner-lip regions are bands around the line
where the lips meet (:mod:`.regions` builds them). :func:`inner_lip_loop`
finds that loop automatically or takes it from a selected edge loop
(:func:`order_edge_loop`); :func:`loop_width` measures the mouth width from
it.

How the loop is found (no template, works in any scene unit): on the largest
connected surface, vertex pairs that are close in space, face each other across
an air gap (opposite normals, each in front of the other) and are far apart on
the mesh (more than ``hops`` edge rings) are *contact pairs*. On a face in a
rest pose they mark the lips, whose facing surfaces are a fraction of a
millimetre to a few millimetres apart while the mesh path between them runs
around the mouth corner. The largest group of contact vertices splits into two
sides (the two lips); the loop is the union of two cheapest edge paths between
the mouth corners, one over each lip, with edge costs proportional to the local
gap, so they follow the line where the lips are closest. On ICT-FaceKit the
loop (about 80 vertices) runs along the 74-vertex lip rings where the
neutral lips are about 1 mm apart; detection takes about 0.3 s and does not
depend on the scene unit, orientation or vertex order.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components as _cc
from scipy.sparse.csgraph import dijkstra as _dijkstra

from ..errors import RegionError, RegionMeshError
from ..geometry.mesh import edge_length_graph, vertex_adjacency, vertex_normals

__all__ = ["order_edge_loop", "inner_lip_loop", "loop_width"]


def order_edge_loop(faces, loop_vertices, n_vertices: int | None = None) -> np.ndarray:
    """Order a selected closed edge loop.

    Parameters
    ----------
    faces : (F,3) int array_like
        Triangles.
    loop_vertices : (L,) int array_like
        The loop's vertices, in any order (for example a Blender edge-loop
        selection), or already in loop order.
    n_vertices : int, optional
        Vertex count ``V``.

    Returns
    -------
    (L,) int64 ndarray
        The same vertices in loop order (the closing edge, last to first, is
        implied). If the input is already a valid cycle its order and starting
        vertex are kept.

    Raises
    ------
    RegionError
        If the vertices do not form one closed chain of mesh edges.
    """
    F = _region_faces(faces)
    loop = np.asarray(loop_vertices)
    if loop.size and not np.issubdtype(loop.dtype, np.integer):
        raise RegionError(f"The lip loop must be vertex indices (integers), got {loop.dtype}; reselect the edge loop.")
    loop = loop.astype(np.int64).ravel()
    nv = int(F.max() + 1) if n_vertices is None else int(n_vertices)
    if F.max() >= nv:
        raise RegionMeshError(f"Face indices are out of range [0, {nv}); the faces do not belong to this mesh.")
    if loop.size < 3 or len(np.unique(loop)) != loop.size:
        raise RegionError(
            f"The lip loop needs at least 3 distinct vertices, got {loop.size} ({len(np.unique(loop))} distinct); "
            "select the inner-lip edge loop (Alt+click an edge of it)."
        )
    if loop.min() < 0 or loop.max() >= nv:
        raise RegionError(f"The lip loop refers to vertices outside the mesh (0..{nv - 1}); reselect the edge loop.")
    A = vertex_adjacency(F, nv)
    # already an ordered cycle?
    nxt = np.roll(loop, -1)
    if np.all(np.asarray(A[loop, nxt]).ravel() > 0):
        return loop
    sub = A[loop][:, loop].tocsr()
    deg = np.diff(sub.indptr)
    if not np.all(deg == 2):
        raise RegionError(
            f"The selected vertices are not a single closed edge loop ({int((deg != 2).sum())} vertices have "
            f"{'fewer' if (deg < 2).any() else 'more'} than two selected neighbours); "
            "select exactly one closed loop (Alt+click an edge of the inner-lip line)."
        )
    order = [0]
    prev = -1
    for _ in range(loop.size - 1):
        cur = order[-1]
        nb = sub.indices[sub.indptr[cur] : sub.indptr[cur + 1]]
        nb = [j for j in nb if j != prev]
        prev = cur
        order.append(int(nb[0]))
    if len(set(order)) != loop.size:
        raise RegionError(
            "The selected vertices form more than one closed loop; select only the inner-lip edge loop."
        )
    return loop[np.asarray(order)]


def _region_faces(faces):
    """(F,3) int64 triangles, non-empty, non-negative (RegionMeshError otherwise)."""
    F = np.asarray(faces)
    if F.ndim != 2 or F.shape[1] != 3 or len(F) == 0:
        raise RegionMeshError(f"Expected a non-empty (F,3) array of triangles, got shape {F.shape}; triangulate "
                              "the mesh first (Ctrl+T).")
    if not np.issubdtype(F.dtype, np.integer):
        raise RegionMeshError(f"Face indices must be integers, got {F.dtype}; pass the mesh's triangle indices.")
    F = F.astype(np.int64)
    if F.min() < 0:
        raise RegionMeshError("Face indices must not be negative; the faces do not belong to this mesh.")
    return F


def _region_mesh(vertices, faces):
    """``(V, F)`` float64 (V,3) and int64 (F,3), checked: finite positions, indices in range (RegionMeshError)."""
    V = np.asarray(vertices)
    if V.ndim != 2 or V.shape[1] != 3 or len(V) == 0 or not np.issubdtype(V.dtype, np.number):
        raise RegionMeshError(f"Expected vertices as a non-empty (V,3) array of numbers, got shape {V.shape}; "
                              "pass the mesh's vertex positions.")
    V = V.astype(np.float64)
    F = _region_faces(faces)
    if not np.isfinite(V).all():
        raise RegionMeshError("The rest mesh has NaN or infinite coordinates; fix the mesh before finding the lip "
                              "loop.")
    if F.max() >= len(V):
        raise RegionMeshError(f"Face indices are out of range [0, {len(V)}); the faces do not belong to this mesh.")
    return V, F


def _largest_component(faces, n_vertices):
    A = vertex_adjacency(faces, n_vertices)
    _, lab = _cc(A, directed=False)
    used = np.zeros(n_vertices, dtype=bool)
    used[np.asarray(faces).ravel()] = True
    counts = np.bincount(lab[used], minlength=lab.max() + 1)
    return lab == int(np.argmax(counts)), A


def _contact_pairs(V, F, comp, A, max_gap, hops):
    """Nearest facing, far-on-the-mesh partner of each vertex of ``comp``.

    Returns ``partner (V,) int (-1: none)`` and ``gap (V,) float (inf: none)``.
    """
    from scipy.spatial import cKDTree

    nv = len(V)
    idx = np.flatnonzero(comp)
    N = vertex_normals(V, F)
    # make normals point out of the surface: away from the component centroid
    c = V[idx].mean(axis=0)
    if np.sum(np.einsum("ij,ij->i", N[idx], V[idx] - c)) < 0:
        N = -N
    tree = cKDTree(V[idx])
    pairs = tree.query_pairs(float(max_gap), output_type="ndarray")
    partner = -np.ones(nv, dtype=np.int64)
    gap = np.full(nv, np.inf)
    if len(pairs) == 0:
        return partner, gap
    i, j = idx[pairs[:, 0]], idx[pairs[:, 1]]
    d = V[j] - V[i]
    dist = np.linalg.norm(d, axis=1)
    ok = dist > 1e-9 * max_gap  # coincident vertices: an unwelded seam, not a lip contact
    u = d / np.where(ok, dist, 1.0)[:, None]
    ok &= np.einsum("ij,ij->i", N[i], N[j]) < -0.3
    ok &= np.einsum("ij,ij->i", u, N[i]) > 0.3
    ok &= np.einsum("ij,ij->i", -u, N[j]) > 0.3
    i, j, dist = i[ok], j[ok], dist[ok]
    if len(i) == 0:
        return partner, gap
    # far on the mesh: j is not within `hops` edge rings of i
    src = np.unique(i)
    row = -np.ones(nv, dtype=np.int64)
    row[src] = np.arange(len(src))
    S = sp.csr_matrix((np.ones(len(src)), (np.arange(len(src)), src)), shape=(len(src), nv))
    R = (A + sp.identity(nv, format="csr")).tocsr()
    for _ in range(int(hops)):
        S = (S @ R).tocsr()
        S.data[:] = 1.0
    near = np.asarray(S[row[i], j]).ravel() > 0
    i, j, dist = i[~near], j[~near], dist[~near]
    if len(i) == 0:
        return partner, gap
    # nearest partner per vertex, both directions
    a = np.r_[i, j]
    b = np.r_[j, i]
    dd = np.r_[dist, dist]
    order = np.lexsort((dd, a))
    a, b, dd = a[order], b[order], dd[order]
    first = np.r_[True, a[1:] != a[:-1]]
    partner[a[first]] = b[first]
    gap[a[first]] = dd[first]
    return partner, gap


def inner_lip_loop(vertices, faces, loop=None, *, max_gap=None, hops: int = 8) -> np.ndarray:
    """The inner-lip contact loop: the closed line where upper and lower lip meet.

    Parameters
    ----------
    vertices : (V,3) array_like
        Rest-pose positions (lips closed or nearly closed), scene units.
    faces : (F,3) int array_like
        Triangles.
    loop : (L,) int array_like, optional
        An explicit loop, for example the vertices of a selected edge loop, in
        any order. It is checked and ordered (:func:`order_edge_loop`) and
        automatic detection is skipped.
    max_gap : float, optional
        Largest distance between the lips, scene units, for two facing
        surfaces to count as lips in contact. Default: twice the median edge
        length of the largest mesh piece (about 5 mm on ICT-FaceKit). Raise it
        if the mouth is open in the rest pose.
    hops : int
        Contact pairs must be more than this many edge rings apart on the mesh
        (rejects ordinary folds such as eyelid creases).

    Returns
    -------
    (L,) int64 ndarray
        Vertex indices in loop order (closed: the last vertex connects to the
        first by a mesh edge). It runs along one lip from corner to corner and
        back along the other.

    Raises
    ------
    RegionError
        If no pair of facing lip surfaces is found, or they cannot be joined
        into a loop; the message suggests ``max_gap`` or selecting the loop.
    """
    V, F = _region_mesh(vertices, faces)
    nv = len(V)
    if loop is not None:
        return order_edge_loop(F, loop, nv)
    if max_gap is not None and not (np.isfinite(max_gap) and max_gap > 0):
        raise RegionError(f"max_gap must be a positive distance, got {max_gap!r}; leave it unset or give the lip gap.")

    comp, A = _largest_component(F, nv)
    G, E, elen = edge_length_graph(V, F, nv)
    in_comp = comp[E[:, 0]]
    if max_gap is None:
        max_gap = 2.0 * float(np.median(elen[in_comp]))
    max_gap = float(max_gap)
    if not max_gap > 0:
        raise RegionError("Every edge of the mesh has zero length, so no lips can be found; fix the mesh "
                          "(Mesh > Clean Up > Merge by Distance) or select the inner-lip edge loop.")
    partner, gap = _contact_pairs(V, F, comp, A, max_gap, hops)
    has = partner >= 0
    hint = (
        "no pair of facing lip surfaces was found; close the mouth in the rest pose, raise max_gap, "
        "or select the inner-lip edge loop and use it instead."
    )
    if has.sum() < 6:
        raise RegionError(f"Cannot find the inner-lip line: {hint}")

    # groups: contact vertices connected on the mesh, merged across partner links
    cv = np.flatnonzero(has)
    pos = -np.ones(nv, dtype=np.int64)
    pos[cv] = np.arange(len(cv))
    Asub = A[cv][:, cv]
    pl = pos[partner[cv]]
    link = pl >= 0
    Plink = sp.coo_matrix((np.ones(link.sum()), (np.flatnonzero(link), pl[link])), shape=(len(cv), len(cv)))
    nmesh, mlab = _cc(Asub, directed=False)
    ngrp, glab = _cc(Asub + Plink + Plink.T, directed=False)
    best = int(np.argmax(np.bincount(glab)))
    grp = cv[glab == best]
    gml = mlab[glab == best]

    # the two lips: split by the direction to the partner
    u = V[partner[grp]] - V[grp]
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    w, vecs = np.linalg.eigh(u.T @ u)
    dvert = vecs[:, -1]
    side_v = np.sign(u @ dvert)
    side = np.zeros(nv)
    for c in np.unique(gml):  # each mesh piece of the group takes its majority side
        sel = gml == c
        side[grp[sel]] = 1.0 if side_v[sel].sum() >= 0 else -1.0
    up, lo = grp[side[grp] > 0], grp[side[grp] < 0]
    if len(up) < 3 or len(lo) < 3:
        raise RegionError(
            f"Cannot find the inner-lip line: only one lip was found ({len(up)}/{len(lo)} vertices); {hint}"
        )

    # mouth corners: extremes of the contact group along the mouth's width axis
    P = V[grp] - V[grp].mean(axis=0)
    P -= np.outer(P @ dvert, dvert)
    _, _, vt = np.linalg.svd(P, full_matrices=False)
    s = P @ vt[0]
    cl, cr = int(grp[np.argmin(s)]), int(grp[np.argmax(s)])

    # edge costs proportional to the local gap (cheap where the lips are closest)
    gfield = np.where(np.isfinite(gap), np.minimum(gap, max_gap), max_gap) / max_gap
    cost = elen * (0.05 + 0.5 * (gfield[E[:, 0]] + gfield[E[:, 1]]))

    def path(forbidden):
        allow = comp & ~forbidden
        allow[[cl, cr]] = True
        ok = allow[E[:, 0]] & allow[E[:, 1]]
        e = E[ok]
        c = cost[ok]
        Gs = sp.coo_matrix((np.r_[c, c], (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])), shape=(nv, nv)).tocsr()
        dist, pred = _dijkstra(Gs, indices=cl, return_predecessors=True)
        if not np.isfinite(dist[cr]):
            return None
        p = [cr]
        while p[-1] != cl:
            p.append(int(pred[p[-1]]))
        return np.asarray(p[::-1], dtype=np.int64)

    forb = np.zeros(nv, dtype=bool)
    forb[lo] = True
    p1 = path(forb)
    forb = np.zeros(nv, dtype=bool)
    forb[up] = True
    if p1 is not None:
        forb[p1[1:-1]] = True
    p2 = path(forb)
    if p1 is None or p2 is None or len(p1) + len(p2) - 2 < 3:
        raise RegionError(f"Cannot join the upper and lower lip into a closed loop; {hint}")
    loop = np.r_[p1, p2[::-1][1:-1]].astype(np.int64)
    width = loop_width(V, loop)
    if width < 4.0 * max_gap:
        raise RegionError(
            f"Only a small patch of lip contact was found ({width:.3g} scene units wide, near vertex {cl}); "
            "the mouth is probably open in the rest pose. Close it, raise max_gap, or select the inner-lip "
            "edge loop and use it instead."
        )
    return loop


def loop_width(vertices, loop) -> float:
    """Mouth width: extent of the loop along its principal axis (corner to corner), scene units.

    Parameters
    ----------
    vertices : (V,3) array_like
        Positions, scene units.
    loop : (L,) int array_like
        Loop vertex indices (for example from :func:`inner_lip_loop`).

    Returns
    -------
    float
    """
    P = np.asarray(vertices, dtype=np.float64)[np.asarray(loop, dtype=np.int64)]
    c = P.mean(axis=0)
    _, _, vt = np.linalg.svd(P - c, full_matrices=False)
    s = (P - c) @ vt[0]
    return float(s.max() - s.min())

