"""The inner-lip contact loop: the closed edge loop where the upper and lower lip meet.

Dinev et al. 2018, "User-Guided Lip Correction for Facial Performance
Capture", Fig. 2: the mouth and inner-lip regions are bands around the line
where the lips meet (:mod:`.regions` builds them). :func:`inner_lip_loop`
finds that loop automatically or takes it from a selected edge loop
(:func:`order_edge_loop`); :func:`loop_width` measures the mouth width from
it.

How the loop is found (no template, works in any scene unit): on the mesh
pieces that are not inside another (teeth, tongue and eyes are), vertex pairs
that are close in space, face each other across an air gap (opposite normals,
each in front of the other) and are far apart on the mesh (a path ``detour``
times their distance) are *contact pairs*. On a face in a rest pose they mark the lips,
whose facing surfaces are a fraction of a millimetre to a few millimetres apart
while the mesh path between them runs around the mouth corner. Contact
vertices connected on the mesh (or through one vertex between them) form
groups; on a body, eyelids, fingers and toes form bigger groups than the lips,
so the mouth is the group nearest to the rays through the artist's sketch,
else the largest group straddling the mesh's mirror plane
(:func:`inner_lip_loop`, Notes). It splits into two sides (the two lips). The
contact need not reach the mouth corners: near a corner the lips close like a
wedge, and on a coarse mesh the vertex across it sits beside rather than in
front, so the pairs stop an edge or two short (on lips parted in the middle the
contact even falls apart). The corners are therefore where the slit between the
lips ends: from the outermost upper and lower contact vertices in sight (not
hidden behind the skin, as a mouth interior is), the shortest mesh path from
one lip to the other, kept on that side of them, runs around the end of the
slit, and its far point is the corner. The loop is the union of two cheapest
edge paths between the corners, one over each lip, along the front of the
contact, with edge costs proportional to the local gap, so they follow the
line where the lips are closest. The detection does not depend on the scene unit, orientation
or vertex order.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components as _cc
from scipy.sparse.csgraph import dijkstra as _dijkstra

from ..errors import RegionError, RegionMeshError
from ..geometry.mesh import edge_length_graph, vertex_adjacency, vertex_normals

__all__ = ["order_edge_loop", "inner_lip_loop", "loop_width"]

_FLOOR = 0.5
_FRONT = 0.3  # cosine: a partner lies in front of a vertex along its normal
_SIDE = 0.5  # coarse meshes: or sideways by at most this many of its edge lengths


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


def region_mesh(vertices, faces):
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


def _contact_pairs(V, F, comp, G, max_gap, detour, side_offset=0.0):
    """Nearest facing, far-on-the-mesh partner of each vertex of ``comp`` (``G``: edge-length graph).

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
    # each in front of the other: along its normal, or (on a coarse mesh, where the nearest vertex across
    # the gap sits up to half an edge to the side) in front with a sideways offset under half an edge
    ell = _mean_edge_length(V, F)
    for a, b, sgn in ((i, j, 1.0), (j, i, -1.0)):
        c = sgn * np.einsum("ij,ij->i", u, N[a])
        side = dist * np.sqrt(np.maximum(1.0 - c * c, 0.0))
        ok &= (c > _FRONT) | ((c > 0) & (side <= side_offset * ell[a]))
    i, j, dist = i[ok], j[ok], dist[ok]
    if len(i) == 0:
        return partner, gap
    # far on the mesh: the shortest mesh path from i to j is more than `detour` times their distance
    # (and more than twice the gap), so they face each other across an opening, not across a crease
    reach = np.maximum(detour * dist, _FLOOR * max_gap)
    near = np.zeros(len(i), dtype=bool)
    src, inv = np.unique(i, return_inverse=True)
    for s0 in range(0, len(src), 256):
        sel = (inv >= s0) & (inv < s0 + 256)
        D = _dijkstra(G, indices=src[s0 : s0 + 256], limit=float(reach.max()))
        near[sel] = D[inv[sel] - s0, j[sel]] <= reach[sel]
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


def _mean_edge_length(V, F):
    """(V,) mean length of the edges at each vertex (0 on unused vertices)."""
    E = np.r_[F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]
    L = np.linalg.norm(V[E[:, 0]] - V[E[:, 1]], axis=1)
    tot = np.bincount(E.ravel(), weights=np.r_[L, L], minlength=len(V))
    cnt = np.bincount(E.ravel(), minlength=len(V))
    return tot / np.maximum(cnt, 1)


def _outer_pieces(V, F, nv):
    """(V,) bool: the mesh pieces that can hold the lips, and the vertex adjacency.

    A piece whose bounding box lies inside a larger piece's (teeth, tongue, eyeballs inside a head) is
    left out: its facing surfaces (upper and lower teeth) are never the lips. Everything else counts,
    so a head modelled separately from the body, or lips that are separate pieces, are searched too.
    """
    A = vertex_adjacency(F, nv)
    used = np.zeros(nv, dtype=bool)
    used[F.ravel()] = True
    ncomp, lab = _cc(A, directed=False)
    counts = np.bincount(lab[used], minlength=ncomp)
    ids = np.flatnonzero(counts)
    lo = np.array([V[lab == c].min(axis=0) for c in ids])
    hi = np.array([V[lab == c].max(axis=0) for c in ids])
    keep = np.zeros(ncomp, dtype=bool)
    for n, c in enumerate(ids):
        inside = (counts[ids] > counts[c]) & (lo <= lo[n]).all(axis=1) & (hi >= hi[n]).all(axis=1)
        keep[c] = not inside.any()
    return keep[lab] & used, A


def _mirror_plane(V, mask):
    """``(axis, centre)`` of the mesh's left-right mirror plane among the x, y, z planes, or None.

    The plane through the median along an axis whose mirror image of the vertices lands on the
    vertices (mean distance below 2 % of the size); the best of the three axes.
    """
    from scipy.spatial import cKDTree

    P = V[mask]
    if len(P) > 4000:
        P = P[np.random.default_rng(0).choice(len(P), 4000, replace=False)]
    size = float(np.linalg.norm(np.ptp(P, axis=0)))
    if not size > 0:
        return None
    tree = cKDTree(P)
    best = None
    for a in range(3):
        c = float(np.median(P[:, a]))
        Q = P.copy()
        Q[:, a] = 2 * c - Q[:, a]
        err = float(np.mean(tree.query(Q)[0])) / size
        if best is None or err < best[2]:
            best = (a, c, err)
    return (best[0], best[1]) if best[2] < 0.02 else None


def _group_shape(V, grp, partner):
    """``(contact_axis, width_axis, width)`` of a contact group: partner direction, corner-to-corner axis."""
    u = V[partner[grp]] - V[grp]
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    P = V[grp] - V[grp].mean(axis=0)
    w0 = np.linalg.svd(P, full_matrices=False)[2][0]
    u -= np.outer(u @ w0, w0)
    dvert = np.linalg.eigh(u.T @ u)[1][:, -1]
    P -= np.outer(P @ dvert, dvert)
    wax = np.linalg.svd(P, full_matrices=False)[2][0]
    s = P @ wax
    return dvert, wax, float(s.max() - s.min())


def _ray_distance(P, rays):
    """(N,) distance of points ``P`` to the nearest of the rays ``(origins (R,3), directions (R,3))``."""
    O, D = (np.asarray(r, dtype=np.float64).reshape(-1, 3) for r in rays)
    if len(O) > 200:
        pick = np.linspace(0, len(O) - 1, 200).astype(int)
        O, D = O[pick], D[pick]
    D = D / np.linalg.norm(D, axis=1, keepdims=True)
    out = np.full(len(P), np.inf)
    for o, d in zip(O, D):
        w = P - o
        t = np.maximum(w @ d, 0.0)
        out = np.minimum(out, np.linalg.norm(w - t[:, None] * d, axis=1))
    return out


def _choose_group(V, groups, partner, rays, mirror):
    """Index of the lip contact group among ``groups`` (lists of vertex ids), and how it was chosen.

    With sketch ``rays``, the group nearest to them (the lips are where the artist drew). Otherwise
    the largest group that straddles the mesh's mirror plane with its corners on either side and its
    lips facing along the plane (the mouth; eyelids, fingers and toes lie off the midline, a cleft
    between the buttocks faces across it); the largest group when there is none.
    """
    if rays is not None:
        score = [float(np.median(_ray_distance(V[g], rays))) for g in groups]
        return int(np.argmin(score)), "sketch"
    sizes = np.array([len(g) for g in groups])
    if mirror is not None:
        a, c = mirror
        ok = []
        for n, g in enumerate(groups):
            dvert, wax, width = _group_shape(V, g, partner)
            x = V[g, a]
            ok.append(x.min() < c < x.max() and abs(x.mean() - c) < 0.25 * width and abs(wax[a]) > 0.7
                      and abs(dvert[a]) < 0.5)
        ok = np.array(ok)
        if ok.any():
            return int(np.flatnonzero(ok)[np.argmax(sizes[ok])]), "midline"
    return int(np.argmax(sizes)), "largest"


def _front(V, F, grp, toward, width):
    """Unit direction the mouth faces: to ``toward`` (a camera centre), else the mean skin normal around it."""
    c = V[grp].mean(axis=0)
    if toward is not None:
        f = np.asarray(toward, dtype=np.float64).reshape(3) - c
    else:
        N = vertex_normals(V, F)
        near = np.linalg.norm(V - c, axis=1) < 0.6 * width
        f = N[near].sum(axis=0)
    n = np.linalg.norm(f)
    return f / n if n > 0 else None


def _contact_groups(V, F, comp, A, G, max_gap, detour, side_offset, rays, mirror):
    """The lip contact group for one pairing rule: ``(partner, gap, group vertex ids, width)``, or None."""
    nv = len(V)
    partner, gap = _contact_pairs(V, F, comp, G, max_gap, detour, side_offset)
    cv = np.flatnonzero(partner >= 0)
    if len(cv) < 6:
        return None
    # groups: contact vertices connected on the mesh, merged across partner links
    pos = -np.ones(nv, dtype=np.int64)
    pos[cv] = np.arange(len(cv))
    pl = pos[partner[cv]]
    link = pl >= 0
    Plink = sp.coo_matrix((np.ones(link.sum()), (np.flatnonzero(link), pl[link])), shape=(len(cv), len(cv)))
    Acv = A[cv]
    ngrp, glab = _cc(Acv[:, cv] + Acv @ Acv.T + Plink + Plink.T, directed=False)
    groups = [cv[glab == g] for g in range(ngrp) if (glab == g).sum() >= 6]
    if not groups:
        return None
    grp = groups[_choose_group(V, groups, partner, rays, mirror)[0]]
    return partner, gap, grp, _group_shape(V, grp, partner)[2]


def inner_lip_loop(vertices, faces, loop=None, *, max_gap=None, detour: float = 5.0, rays=None, toward=None,
                   gap_name: str = "max_gap") -> np.ndarray:
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
        length of the searched mesh pieces (about 5 mm on ICT-FaceKit). Raise it
        if the mouth is open in the rest pose.
    detour : float
        Contact pairs must be further apart along the mesh than ``detour``
        times their distance (and than twice ``max_gap``): the path between
        the lips runs around the mouth corner, across an ordinary fold such as
        an eyelid crease it is short. A ratio of distances, so the same on a
        fine and on a coarse mesh.
    rays : ((N,3), (N,3)) array_like pair, optional
        Rays through the artist's lip sketch (origins, directions), in the
        space of ``vertices``: of several contact groups (lips, eyelids,
        fingers, toes) the one nearest to the rays is the mouth.
    toward : (3,) array_like, optional
        The camera centre in the space of ``vertices``: the loop follows the
        side of the lip contact that faces it. Default: the side the skin around
        the mouth faces.
    gap_name : str
        How the failure messages name ``max_gap`` (an operator's setting name).

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
        into a loop; the message suggests ``max_gap`` (as ``gap_name``) or
        selecting the loop.

    Notes
    -----
    Without ``rays`` the mouth is told from eyelids, fingers and toes (often
    bigger contact groups than the lips) by the mesh's mirror plane: the lip
    contact straddles it with its corners on either side. Pieces lying inside
    a larger piece's bounding box (teeth, tongue, eyeballs) are not searched.
    Only the contact within a quarter of the mouth width of its front (along
    ``toward``) is used, and the corners are followed from the contact in
    sight from there, so contact deeper in an attached mouth interior does
    not pull the loop inside. The corners are the ends of the slit between
    the lips, not of the contact (module docstring): the same on a fine and
    on a coarse mesh of the same mouth.
    """
    V, F = region_mesh(vertices, faces)
    nv = len(V)
    if loop is not None:
        return order_edge_loop(F, loop, nv)
    if max_gap is not None and not (np.isfinite(max_gap) and max_gap > 0):
        raise RegionError(f"{gap_name} must be a positive distance, got {max_gap!r}; leave it unset or give the "
                          "lip gap.")

    comp, A = _outer_pieces(V, F, nv)
    G, E, elen = edge_length_graph(V, F, nv)
    in_comp = comp[E[:, 0]]
    if max_gap is None:
        max_gap = 2.0 * float(np.median(elen[in_comp]))
    max_gap = float(max_gap)
    if not max_gap > 0:
        raise RegionError("Every edge of the mesh has zero length, so no lips can be found; fix the mesh "
                          "(Mesh > Clean Up > Merge by Distance) or select the inner-lip edge loop.")
    mirror = _mirror_plane(V, comp) if rays is None else None
    # facing partners along the normals; on a coarse mesh the lips' vertices also pair sideways (within half
    # an edge), which is used when it reveals a much wider contact than the strict pairs
    found = [_contact_groups(V, F, comp, A, G, max_gap, detour, s, rays, mirror) for s in (0.0, _SIDE)]
    if found[0] is None or (found[1] is not None and found[0][3] < 0.75 * found[1][3]):
        found[0] = found[1]
    hint = (
        f"no pair of facing lip surfaces was found; close the mouth in the rest pose, raise {gap_name}, "
        "or select the inner-lip edge loop and use it instead."
    )
    if found[0] is None:
        raise RegionError(f"Cannot find the inner-lip line: {hint}")
    partner, gap, grp, _ = found[0]
    # the front of the contact: within a quarter of the mouth width of its front-most point
    _, _, width0 = _group_shape(V, grp, partner)
    front = _front(V, F, grp, toward, width0)
    if front is not None:
        depth = (V[grp] @ front).max() - V[grp] @ front
        keep = depth <= 0.25 * width0
        if keep.sum() >= 6:
            grp = grp[keep]
    gml = _cc(A[grp][:, grp], directed=False)[1]  # the mesh pieces of the group

    # the two lips: split by the direction to the partner
    dvert, wax, _ = _group_shape(V, grp, partner)
    side_v = np.sign((V[partner[grp]] - V[grp]) @ dvert)
    side = np.zeros(nv)
    for c in np.unique(gml):  # each mesh piece of the group takes its majority side
        sel = gml == c
        side[grp[sel]] = 1.0 if side_v[sel].sum() >= 0 else -1.0
    up, lo = grp[side[grp] > 0], grp[side[grp] < 0]
    if len(up) < 3 or len(lo) < 3:
        raise RegionError(
            f"Cannot find the inner-lip line: only one lip was found ({len(up)}/{len(lo)} vertices); {hint}"
        )

    # mouth corners: where the slit between the lips ends beyond each end of the contact (along the width axis)
    s = (V - V[grp].mean(axis=0)) @ wax
    if front is not None:  # from the contact that is in sight (not a mouth interior behind the cheeks)
        tol = np.maximum(gap, _mean_edge_length(V, F))
        seen = _in_sight(V, F[comp[F].all(axis=1)], grp, front, tol[grp])
        if seen[side[grp] > 0].any() and seen[side[grp] < 0].any():
            up, lo = up[seen[side[grp] > 0]], lo[seen[side[grp] < 0]]
    a, b = int(up[np.argmin(s[up])]), int(lo[np.argmin(s[lo])])
    cl = _slit_end(V, G, comp & (s <= max(s[a], s[b])), a, b)
    a, b = int(up[np.argmax(s[up])]), int(lo[np.argmax(s[lo])])
    cr = _slit_end(V, G, comp & (s >= min(s[a], s[b])), a, b)
    up, lo = grp[side[grp] > 0], grp[side[grp] < 0]

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
        return _shortest_path(Gs, cl, cr)

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
    if width < 4.0 * float(np.median(gap[grp])):
        raise RegionError(
            f"Only a small patch of lip contact was found ({width:.3g} scene units wide, near vertex {cl}); "
            f"the mouth is probably open in the rest pose. Close it, raise {gap_name}, or select the inner-lip "
            "edge loop and use it instead."
        )
    return loop


def _in_sight(V, F, idx, f, tol):
    """(len(idx),) bool: vertices ``idx`` with no triangle of ``F`` more than ``tol`` in front of them along ``f``."""
    e1 = np.cross(f, [1.0, 0.0, 0.0] if abs(f[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    B = np.c_[e1, np.cross(f, e1)]
    Q, T = V[idx] @ B, V @ B  # (N,2), (V,2) projected along f
    dq, dv = V[idx] @ f, V @ f
    lo_, hi_ = T[F].min(axis=1), T[F].max(axis=1)
    F = F[(hi_ >= Q.min(axis=0)).all(axis=1) & (lo_ <= Q.max(axis=0)).all(axis=1)]
    seen = np.ones(len(idx), dtype=bool)
    if len(F) == 0:
        return seen
    a, b, c = T[F[:, 0]], T[F[:, 1]], T[F[:, 2]]
    det = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])
    F, a, b, c, det = F[det != 0], a[det != 0], b[det != 0], c[det != 0], det[det != 0]
    for k in range(len(idx)):
        q = Q[k]
        l1 = ((b[:, 0] - q[0]) * (c[:, 1] - q[1]) - (c[:, 0] - q[0]) * (b[:, 1] - q[1])) / det
        l2 = ((c[:, 0] - q[0]) * (a[:, 1] - q[1]) - (a[:, 0] - q[0]) * (c[:, 1] - q[1])) / det
        l3 = 1.0 - l1 - l2
        hit = (l1 >= 0) & (l2 >= 0) & (l3 >= 0) & (F != idx[k]).all(axis=1)
        if hit.any():
            d = l1[hit] * dv[F[hit, 0]] + l2[hit] * dv[F[hit, 1]] + l3[hit] * dv[F[hit, 2]]
            seen[k] = not (d > dq[k] + tol[k]).any()
    return seen


def _shortest_path(G, a: int, b: int):
    """(P,) int64 vertex ids of the shortest path from ``a`` to ``b`` in the sparse graph ``G``, or None."""
    dist, pred = _dijkstra(G, indices=a, return_predecessors=True)
    if not np.isfinite(dist[b]):
        return None
    p = [b]
    while p[-1] != a:
        p.append(int(pred[p[-1]]))
    return np.asarray(p[::-1], dtype=np.int64)


def _slit_end(V, G, comp, a, b):
    """The end of the slit between two lips: the far point of the shortest mesh path from ``a`` to ``b``."""
    keep = sp.diags(comp.astype(np.float64))
    Gc = (keep @ G @ keep).tocsr()
    p = _shortest_path(Gc, a, b)
    if p is None:
        return a
    m = 0.5 * (V[a] + V[b])
    return int(p[np.argmax(np.linalg.norm(V[p] - m, axis=1))])


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

