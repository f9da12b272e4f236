"""Mouth and inner-lip regions for lip-correction learning.

Dinev et al. 2018, "User-Guided Lip Correction for Facial Performance
Capture", §4 and Fig. 2: the mesh is split into a *mouth region* whose capture
is trusted (blue) and an *inner-lip region* (red) that is predicted from it;
the rest (gray) is ignored. §6.2 notes that the regions should follow the
boundary between high- and low-confidence capture: too small a lip region
keeps badly captured corners, too large a one throws away useful input.

In FaceLab the regions are vertex groups (``FL_mouth``, ``FL_lips``) and a
triangle belongs to a region when all three of its vertices do
(:func:`faces_in_region`). :func:`auto_regions` proposes both regions as
geodesic bands around the *inner-lip contact loop* (the closed curve where the
upper and lower lip meet), which :func:`inner_lip_loop` finds automatically or
takes from a selected edge loop.

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

from ..errors import MeshError, RegionError
from ..geometry.mesh import unique_edges, vertex_adjacency, vertex_normals

__all__ = [
    "RegionError",
    "faces_in_region",
    "region_vertex_mask",
    "region_border",
    "validate_regions",
    "order_edge_loop",
    "inner_lip_loop",
    "geodesic_distance",
    "auto_regions",
    "inner_lip_vertices",
    "loop_width",
    "DEFAULT_LIP_WIDTH",
    "DEFAULT_MOUTH_WIDTH",
]

#: Default inner-lip band half-width, as a fraction of the mouth width (corner
#: to corner distance of the contact loop). About 5.5 mm on ICT-FaceKit.
DEFAULT_LIP_WIDTH = 0.12
#: Default width of the mouth band outside the lip band, as a fraction of the
#: mouth width. About 2 cm on ICT-FaceKit.
DEFAULT_MOUTH_WIDTH = 0.45


# --------------------------------------------------------------------------
# Regions as triangle sets
# --------------------------------------------------------------------------


def faces_in_region(faces, vertex_mask) -> np.ndarray:
    """Triangles whose three vertices are all in a vertex region.

    Parameters
    ----------
    faces : (F,3) int array_like
        Triangles.
    vertex_mask : (V,) bool array_like, or (k,) int array_like
        The region as a boolean mask over vertices, or as vertex indices
        (for example the members of a vertex group).

    Returns
    -------
    (n,) int64 ndarray
        Sorted indices of the triangles inside the region.
    """
    F = np.asarray(faces, dtype=np.int64)
    m = np.asarray(vertex_mask)
    if m.dtype != bool:
        idx = m.astype(np.int64).ravel()
        n = int(max(F.max(initial=-1), idx.max(initial=-1)) + 1)
        mask = np.zeros(n, dtype=bool)
        mask[idx] = True
        m = mask
    if F.size and F.max() >= len(m):
        raise MeshError(
            f"The region mask has {len(m)} entries but the faces use vertex {int(F.max())}; "
            "build the mask on the same mesh as the faces."
        )
    return np.flatnonzero(m[F].all(axis=1)).astype(np.int64)


def region_vertex_mask(faces, region_faces, n_vertices: int) -> np.ndarray:
    """(V,) bool: vertices used by the triangles ``faces[region_faces]``."""
    F = np.asarray(faces, dtype=np.int64)
    m = np.zeros(int(n_vertices), dtype=bool)
    m[F[np.asarray(region_faces, dtype=np.int64)].ravel()] = True
    return m


def region_border(faces, region_faces, n_vertices: int | None = None) -> np.ndarray:
    """Border vertices of a triangle region: used by a region and a non-region triangle.

    These are the vertices held fixed (Dirichlet) when the inner-lip region is
    rebuilt from predicted deformation gradients (Dinev et al. 2018, §4, last
    paragraph). Vertices on an open mesh boundary that touch only region
    triangles are not border vertices.

    Parameters
    ----------
    faces : (F,3) int array_like
        All triangles of the mesh.
    region_faces : (n,) int array_like
        Indices of the region's triangles.
    n_vertices : int, optional
        Vertex count ``V`` (default: ``faces.max() + 1``).

    Returns
    -------
    (b,) int64 ndarray
        Sorted vertex indices.
    """
    F = np.asarray(faces, dtype=np.int64)
    nv = int(F.max() + 1) if n_vertices is None else int(n_vertices)
    inside = np.zeros(len(F), dtype=bool)
    inside[np.asarray(region_faces, dtype=np.int64)] = True
    a = np.zeros(nv, dtype=bool)
    b = np.zeros(nv, dtype=bool)
    a[F[inside].ravel()] = True
    b[F[~inside].ravel()] = True
    return np.flatnonzero(a & b).astype(np.int64)


def validate_regions(faces, mouth_faces, lip_faces, n_vertices: int):
    """Check a mouth/lip region pair and return both as sorted unique int64 arrays.

    Parameters
    ----------
    faces : (F,3) int array_like
        Triangles of the mesh.
    mouth_faces, lip_faces : (m,), (n,) int array_like
        Triangle indices of the mouth (trusted) and inner-lip (predicted) regions.
    n_vertices : int
        Vertex count ``V``.

    Returns
    -------
    mouth_faces : (m,) int64 ndarray
    lip_faces : (n,) int64 ndarray

    Raises
    ------
    RegionError
        If a region is empty, indices are out of range, the regions share
        triangles, or a connected piece of the lip region has no border vertex
        (its position would be undetermined).
    """
    F = np.asarray(faces, dtype=np.int64)
    out = []
    for name, group, r in (("mouth", "FL_mouth", mouth_faces), ("inner-lip", "FL_lips", lip_faces)):
        r = np.unique(np.asarray(r, dtype=np.int64).ravel())
        if r.size == 0:
            raise RegionError(
                f"The {name} region is empty (no triangle has all three vertices in '{group}'); "
                "assign vertices to the group or run Auto Regions."
            )
        if r[0] < 0 or r[-1] >= len(F):
            raise RegionError(
                f"The {name} region refers to triangle {int(r[-1] if r[-1] >= len(F) else r[0])}, but the mesh has "
                f"{len(F)} triangles; rebuild the regions on this mesh (Auto Regions)."
            )
        out.append(r)
    mouth, lips = out
    both = np.intersect1d(mouth, lips)
    if both.size:
        raise RegionError(
            f"The mouth and inner-lip regions overlap in {both.size} triangles (first {both[:5].tolist()}); "
            "remove the shared vertices from one of 'FL_mouth'/'FL_lips' so only the border ring is shared."
        )
    border = region_border(F, lips, n_vertices)
    if border.size == 0:
        raise RegionError(
            "The inner-lip region has no border with the rest of the mesh, so its position is undetermined; "
            "make 'FL_lips' a band that does not cover a whole mesh piece (Auto Regions does this)."
        )
    # every connected piece of the lip region must touch the border
    LF = F[lips]
    used = np.unique(LF)
    remap = -np.ones(int(n_vertices), dtype=np.int64)
    remap[used] = np.arange(len(used))
    ncomp, lab = _cc(vertex_adjacency(remap[LF], len(used)), directed=False)
    has_border = np.zeros(ncomp, dtype=bool)
    has_border[lab[remap[border]]] = True
    if not has_border.all():
        bad = used[~has_border[lab]]
        raise RegionError(
            f"{int((~has_border).sum())} piece(s) of the inner-lip region have no border vertex "
            f"(first vertices {bad[:5].tolist()}); remove them from 'FL_lips' or connect them to the mouth region."
        )
    return mouth, lips


# --------------------------------------------------------------------------
# Edge loops
# --------------------------------------------------------------------------


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
    F = np.asarray(faces, dtype=np.int64)
    loop = np.asarray(loop_vertices, dtype=np.int64).ravel()
    nv = int(F.max() + 1) if n_vertices is None else int(n_vertices)
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


def _edge_graph(vertices, faces, n_vertices):
    E, _ = unique_edges(faces)
    w = np.linalg.norm(vertices[E[:, 0]] - vertices[E[:, 1]], axis=1)
    G = sp.coo_matrix((np.r_[w, w], (np.r_[E[:, 0], E[:, 1]], np.r_[E[:, 1], E[:, 0]])), shape=(n_vertices,) * 2)
    return G.tocsr(), E, w


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
    V = np.asarray(vertices, dtype=np.float64)
    F = np.asarray(faces, dtype=np.int64)
    nv = len(V)
    if V.ndim != 2 or V.shape[1] != 3 or F.ndim != 2 or F.shape[1] != 3:
        raise MeshError(f"Expected vertices (V,3) and triangles (F,3), got {V.shape} and {F.shape}; triangulate first.")
    if not np.isfinite(V).all():
        raise MeshError("The rest mesh has NaN or infinite coordinates; fix the mesh before finding the lip loop.")
    if loop is not None:
        return order_edge_loop(F, loop, nv)

    comp, A = _largest_component(F, nv)
    G, E, elen = _edge_graph(V, F, nv)
    in_comp = comp[E[:, 0]]
    if max_gap is None:
        max_gap = 2.0 * float(np.median(elen[in_comp]))
    max_gap = float(max_gap)
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


# --------------------------------------------------------------------------
# Geodesic bands
# --------------------------------------------------------------------------


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
        edge-path distance, an overestimate of up to about 15 percent.

    Returns
    -------
    (V,) float64 ndarray
        Distance in scene units; ``inf`` beyond ``limit`` or unreachable.
    """
    V = np.asarray(vertices, dtype=np.float64)
    F = np.asarray(faces, dtype=np.int64)
    src = np.unique(np.asarray(sources, dtype=np.int64))
    nv = len(V)
    G, _, _ = _edge_graph(V, F, nv)
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
            fsel = sub[F].all(axis=1)
            SF = F[fsel]
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
                out = np.full(nv, np.inf)
                out[used] = np.minimum(np.asarray(d, dtype=np.float64), dg[used])
                out[src] = 0.0
    out = np.asarray(out, dtype=np.float64).copy()
    out[out > limit] = np.inf
    return out


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


def auto_regions(vertices, faces, loop=None, lip_width=None, mouth_width=None, *, return_distance: bool = False):
    """Propose the mouth (trusted) and inner-lip (predicted) regions.

    Both are geodesic bands around the inner-lip contact loop (Dinev et al.
    2018, Fig. 2): the lip region holds the vertices within ``lip_width`` of
    the loop (on both lips, including the inner lip surface that curls into
    the mouth); the mouth region holds the vertices between ``lip_width`` and
    ``lip_width + mouth_width`` on the face side (a mouth bag behind the lips
    is left out), plus the lip vertices on the shared border, so the triangles
    between the two bands belong to the mouth region.

    Parameters
    ----------
    vertices : (V,3) array_like
        Rest-pose positions, scene units.
    faces : (F,3) int array_like
        Triangles.
    loop : (L,) int array_like, optional
        The inner-lip loop (for example a selected edge loop); found with
        :func:`inner_lip_loop` when omitted.
    lip_width : float, optional
        Geodesic half-width of the lip band, scene units. Default
        ``DEFAULT_LIP_WIDTH`` times the mouth width (corner to corner).
    mouth_width : float, optional
        Geodesic width of the mouth band, scene units. Default
        ``DEFAULT_MOUTH_WIDTH`` times the mouth width.
    return_distance : bool
        Also return the (V,) geodesic distance to the loop and the loop.

    Returns
    -------
    mouth_mask : (V,) bool ndarray
    lip_mask : (V,) bool ndarray
    distance : (V,) float64 ndarray, only if ``return_distance``
        Geodesic distance to the loop, scene units (``inf`` beyond the bands).
    loop : (L,) int64 ndarray, only if ``return_distance``

    Raises
    ------
    RegionError
        If the loop cannot be found or the widths are not positive.
    """
    V = np.asarray(vertices, dtype=np.float64)
    F = np.asarray(faces, dtype=np.int64)
    nv = len(V)
    loop = inner_lip_loop(V, F, loop)
    W = loop_width(V, loop)
    lw = DEFAULT_LIP_WIDTH * W if lip_width is None else float(lip_width)
    mw = DEFAULT_MOUTH_WIDTH * W if mouth_width is None else float(mouth_width)
    if not (lw > 0 and mw > 0 and np.isfinite(lw) and np.isfinite(mw)):
        raise RegionError(
            f"Region widths must be positive scene distances, got lip {lw} and mouth {mw}; fix the widths."
        )
    d = geodesic_distance(V, F, loop, limit=lw + mw)
    lip = d <= lw
    band = (d > lw) & np.isfinite(d)
    # keep the band on the face side: the largest piece once the lips are cut out
    A = vertex_adjacency(F, nv)
    keep = sp.diags((~lip).astype(np.float64))
    _, lab = _cc(keep @ A @ keep, directed=False)
    used = np.zeros(nv, dtype=bool)
    used[F.ravel()] = True
    counts = np.bincount(lab[used & ~lip], minlength=lab.max() + 1)
    face_side = lab == int(np.argmax(counts))
    mouth = band & face_side
    # share the border ring: lip vertices next to the mouth band
    shared = lip & (A @ mouth.astype(np.float64) > 0)
    mouth |= shared
    # a lip triangle with all three vertices shared would be in both regions
    for _ in range(10):
        both = lip[F].all(axis=1) & mouth[F].all(axis=1)
        if not both.any():
            break
        Fb = F[both]
        far = Fb[np.arange(len(Fb)), np.argmin(d[Fb], axis=1)]  # the vertex closest to the loop
        mouth[far] = False
    if not mouth.any() or not lip.any():
        raise RegionError(
            f"Auto Regions produced an empty {'mouth' if not mouth.any() else 'lip'} region (lip width {lw:.4g}, "
            f"mouth width {mw:.4g} scene units); increase the widths."
        )
    if return_distance:
        return mouth, lip, d, loop
    return mouth, lip


def inner_lip_vertices(vertices, faces, loop=None, lip_width=None) -> np.ndarray:
    """(V,) bool mask of the inner-lip region (the ``lip_mask`` of :func:`auto_regions`).

    Parameters
    ----------
    vertices : (V,3) array_like
        Rest-pose positions, scene units.
    faces : (F,3) int array_like
        Triangles.
    loop : (L,) int array_like, optional
        Inner-lip loop; found automatically when omitted.
    lip_width : float, optional
        Band half-width, scene units (default ``DEFAULT_LIP_WIDTH`` times the
        mouth width).

    Returns
    -------
    (V,) bool ndarray
    """
    V = np.asarray(vertices, dtype=np.float64)
    F = np.asarray(faces, dtype=np.int64)
    loop = inner_lip_loop(V, F, loop)
    lw = DEFAULT_LIP_WIDTH * loop_width(V, loop) if lip_width is None else float(lip_width)
    return geodesic_distance(V, F, loop, limit=lw) <= lw
