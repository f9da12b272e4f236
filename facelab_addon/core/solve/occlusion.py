"""Silhouette edges of the candidate contour loops: which loop is the occluding contour.

Bhat et al. 2013, "High Fidelity Facial Animation Capture and Retargeting
With Contours", §4.2 "Contour constraints" (occluding contour). Per frame and
camera, the occluding contour is the edge contour with the most *silhouette
edges*: edges shared by a triangle facing the camera and one facing away
(perspective test ``n . (c - x) > 0``).

* :func:`silhouette_edge_counts` / :func:`select_occluding_loop` count them
  for whole loops given as vertex chains.
* The private helpers count them for every candidate half of a
  :class:`~facelab_addon.core.solve.contour_loops.ContourLoops` at once. All
  candidate edges are stacked once (``CandidatePack``, kept as ``loops._pack``) and
  only the triangles next to them are evaluated (about 3,300 of ICT-FaceKit's
  26,719 vertices). Counted edges can be restricted to those bounding the
  opening (the lip or lid lies on the far side of the edge from the opening
  in the image, "above" along the projected face ``up``), to those near a
  tracked curve, or to the envelope of the opening (no other candidate's
  silhouette nearer to it).

Functions taking ``loops`` read a ContourLoops' packed candidates
(``loops._pack``, ``loops.halves``) and its ``up`` axis; the loops module
imports this one (it picks its rest-pose default halves by these counts).

Conventions: vertices float64 (V,3) scene units; triangles int64 (F,3),
consistently wound; pixels top-left origin, y down; cameras OpenCV
(``core.capture.camera.Camera``). NumPy only, no bpy.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import FaceLabError, MeshError
from ..geometry.mesh import edge_faces
from ..geometry.polyline import point_to_polyline_distance

__all__ = ["silhouette_edge_counts", "select_occluding_loop"]


@dataclass
class CandidatePack:
    """Every candidate half's edges stacked, for one-shot silhouette tests of all candidates."""

    tri: np.ndarray  # (u,3) unique triangles next to candidate edges
    inv: np.ndarray  # (N,2) each edge's two triangles as rows of tri
    ok: np.ndarray  # (N,) the edge has two triangles
    hid: np.ndarray  # (N,) packed half index of each edge
    n_halves: int
    offsets: dict  # curve name -> (first, end) packed half indices
    flat: np.ndarray  # (9,u) flat indices into vertices.ravel() of the triangles' corners
    edges: np.ndarray  # (N,2) edge vertices
    third: np.ndarray  # (N,) the vertex of the edge's first triangle that is not on the edge
    upper: np.ndarray  # (N,) the edge belongs to an upper half (lip or lid above the opening)

    def __getitem__(self, i):  # old tuple layout: (tri, inv), ok, hid, n_halves, offsets, flat
        return ((self.tri, self.inv), self.ok, self.hid, self.n_halves, self.offsets, self.flat)[i]


def pack_candidates(loops) -> CandidatePack:
    """Stack the triangles next to every candidate half's edges for one-shot facing tests."""
    tris, half_of, edges, upper = [], [], [], []
    offsets = {}
    k = 0
    for name, halves in loops.halves.items():
        offsets[name] = (k, k + len(halves))
        for h in halves:
            tris.append(h.edge_tris)
            half_of.append(np.full(len(h.edge_tris), k))
            edges.append(np.stack([h.chain[:-1], h.chain[1:]], axis=1))
            upper.append(np.full(len(h.edge_tris), name.endswith("upper")))
            k += 1
    T = np.concatenate(tris) if tris else np.zeros((0, 2, 3), np.int64)
    E = np.concatenate(edges) if edges else np.zeros((0, 2), np.int64)
    ok = (T >= 0).all(axis=(1, 2))
    hid = np.concatenate(half_of) if half_of else np.zeros(0, np.int64)
    # unique triangles (neighbouring rings share their strip) and each edge's two entries into them
    tri, inv = np.unique(np.maximum(T, 0).reshape(-1, 3), axis=0, return_inverse=True)
    # flat indices into vertices.ravel() of (a_x, a_y, a_z, b_x, ..., c_z) of every unique triangle: (9,n)
    flat = np.ascontiguousarray((3 * tri[:, [0, 0, 0, 1, 1, 1, 2, 2, 2]] + np.tile([0, 1, 2], 3)).T)
    T0 = np.maximum(T[:, 0], 0)
    not_edge = (T0 != E[:, :1]) & (T0 != E[:, 1:])
    third = T0[np.arange(len(T0)), np.argmax(not_edge, axis=1)]
    return CandidatePack(tri=np.ascontiguousarray(tri), inv=inv.reshape(-1, 2), ok=ok, hid=hid, n_halves=k, offsets=offsets,
                 flat=flat, edges=E, third=third,
                 upper=np.concatenate(upper) if upper else np.zeros(0, bool))


def edge_lookup(F):
    """Function mapping sorted vertex pairs (k,2) to their two adjacent triangles (k,2) (-1 if none)."""
    e, ef = edge_faces(F)
    base = np.int64(F.max() + 1)
    keys = e[:, 0] * base + e[:, 1]

    def lookup(E):
        q = E[:, 0] * base + E[:, 1]
        i = np.searchsorted(keys, q)
        i = np.minimum(i, len(keys) - 1)
        found = keys[i] == q
        if not found.all():
            raise MeshError("A candidate loop edge is not an edge of the mesh; rebuild the contour loops on this mesh.")
        return ef[i]

    return lookup


def _facing_from_coords(G, center):
    """(k,) bool facing test from gathered corner coordinates G (9,k) (a_xyz, b_xyz, c_xyz rows).

    ``n . (center - a)`` has the sign of ``n . (center - centroid)`` (the centroid is in the plane).
    """
    ax, ay, az = G[0], G[1], G[2]
    ux, uy, uz = G[3] - ax, G[4] - ay, G[5] - az
    vx, vy, vz = G[6] - ax, G[7] - ay, G[8] - az
    return ((uy * vz - uz * vy) * (center[0] - ax) + (uz * vx - ux * vz) * (center[1] - ay)
            + (ux * vy - uy * vx) * (center[2] - az)) > 0


def _facing_sign(V, tris, camera):
    """(k,) bool: triangle (k,3) faces the camera (perspective test, ``n . (c - x) > 0``)."""
    T = np.asarray(tris, dtype=np.int64)
    G = np.concatenate([V[T[:, j]].T for j in range(3)])
    return _facing_from_coords(G, camera.center)


def gather_corners(V, loops):
    """(9,k) corner coordinates of the candidate triangles (one gather for all cameras)."""
    return np.ascontiguousarray(V).reshape(-1)[loops._pack.flat]


def candidate_silhouettes(V, camera, loops, G=None, inner: bool = True):
    """Silhouette edges of all candidate halves seen from ``camera``.

    With ``inner`` only silhouette edges that bound the opening are kept: the
    lip (lid) lies on the far side of the edge from the opening in the image,
    i.e. above the edge for upper halves and below it for lower halves, with
    "above" along the projected face ``up`` axis. A silhouette where the
    surface folds the other way (the lower lip's outline against the chin,
    seen from below) is an outer silhouette, not the inner-lip line a
    tracker follows.

    Returns
    -------
    idx : (k,) int64
        Packed edge indices (into ``loops._pack``).
    mid : (k,2) float64
        Projected edge midpoints, pixels.
    ends : (k,2,2) float64
        Projected edge end points, pixels.
    up : (k,2) float64
        Projected face ``up`` direction at each edge (pixels per edge length).
    """
    pk = loops._pack
    if G is None:
        G = gather_corners(V, loops)
    s = _facing_from_coords(G, camera.center)[pk.inv]
    idx = np.flatnonzero(pk.ok & (s[:, 0] != s[:, 1]))
    e = pk.edges[idx]
    a, b, r = V[e[:, 0]], V[e[:, 1]], V[pk.third[idx]]
    h = np.sqrt(((b - a) ** 2).sum(axis=1, keepdims=True))
    P = camera.P
    pts = np.concatenate([a, b, r, 0.5 * (a + b), 0.5 * (a + b) + h * loops.up])
    q = pts @ P[:, :3].T + P[:, 3]
    q = (q[:, :2] / q[:, 2:3]).reshape(5, len(idx), 2)
    up = q[4] - q[3]
    if inner and len(idx):
        t = q[1] - q[0]
        n = np.stack([-t[:, 1], t[:, 0]], axis=1)  # a normal of the projected edge
        side_body = np.einsum("ij,ij->i", q[2] - q[0], n)  # where the surface lies (both triangles: a fold)
        side_up = np.einsum("ij,ij->i", up, n)
        keep = ((side_body * side_up) > 0) == pk.upper[idx]
        idx, q, up = idx[keep], q[:, keep], up[keep]
    return idx, q[3], np.stack([q[0], q[1]], axis=1), up


def half_silhouette_counts(V, camera, loops, G=None, inner: bool = True):
    """(H,) silhouette-edge count of every candidate half (all curve names packed); see :func:`candidate_silhouettes`."""
    idx = candidate_silhouettes(V, camera, loops, G, inner)[0]
    return np.bincount(loops._pack.hid[idx], minlength=loops._pack.n_halves)


def envelope_counts(V, camera, loops, G=None):
    """(H,) per half, its inner silhouette edges that bound the opening in the image (nothing nearer to it).

    For the lower lip (lid) an edge counts when no silhouette edge of another
    candidate of the same curve lies above it at the same lateral image
    position; for the upper lip, none below it: the line an artist draws
    along the dark opening (ignoring occlusion by other parts).
    """
    pk = loops._pack
    idx, mid, ends, up = candidate_silhouettes(V, camera, loops, G)
    counts = np.zeros(pk.n_halves, dtype=np.int64)
    if len(idx) == 0:
        return counts
    for name, (lo, hi) in pk.offsets.items():
        sel = (pk.hid[idx] >= lo) & (pk.hid[idx] < hi)
        if not sel.any():
            continue
        u = up[sel].mean(axis=0)
        u /= max(np.linalg.norm(u), 1e-300)
        lat = np.array([-u[1], u[0]])
        hs = pk.hid[idx[sel]]
        m_lat, m_up = mid[sel] @ lat, mid[sel] @ u
        e_lat, e_up = ends[sel] @ lat, ends[sel] @ u  # (k,2)
        lo_l, hi_l = e_lat.min(axis=1), e_lat.max(axis=1)
        # height of every edge j at every midpoint i's lateral position (where j spans it)
        span = (m_lat[:, None] >= lo_l[None]) & (m_lat[:, None] <= hi_l[None]) & (hs[:, None] != hs[None])
        dl = e_lat[:, 1] - e_lat[:, 0]
        w = (m_lat[:, None] - e_lat[None, :, 0]) / np.where(np.abs(dl) < 1e-12, 1e-12, dl)[None]
        hj = e_up[None, :, 0] + np.clip(w, 0, 1) * (e_up[:, 1] - e_up[:, 0])[None]
        sign = -1.0 if name.endswith("upper") else 1.0  # nearer the opening: below an upper lip, above a lower
        beaten = (span & (sign * (hj - m_up[:, None]) > 0.5)).any(axis=1)
        counts += np.bincount(hs[~beaten], minlength=pk.n_halves)
    return counts


def near_curve_counts(idx, mid, loops, lo, hi, C, tol):
    """(hi-lo,) per candidate half, its silhouette edges whose projection lies within ``tol`` px of curve C."""
    hid = loops._pack.hid[idx]
    sel = (hid >= lo) & (hid < hi)
    if not sel.any():
        return np.zeros(hi - lo, dtype=np.int64)
    Cs = C if len(C) <= 128 else np.concatenate([C[:: len(C) // 64], C[-1:]])  # C may already be coarse
    M, h = mid[sel], hid[sel]
    box = ((M >= Cs.min(axis=0) - tol) & (M <= Cs.max(axis=0) + tol)).all(axis=1)  # cheap rejection first
    M, h = M[box], h[box]
    near = point_to_polyline_distance(M, Cs) <= tol if len(M) else np.zeros(0, bool)
    return np.bincount(h[near] - lo, minlength=hi - lo)


def silhouette_edge_counts(vertices, faces, camera, loops, *, closed: bool = True) -> np.ndarray:
    """Number of silhouette edges of each candidate loop seen from a camera.

    A silhouette edge is shared by a triangle facing the camera and one
    facing away (Bhat et al. 2013, §4.2). Only the triangles next to the
    loops' edges are evaluated.

    Parameters
    ----------
    vertices : (V,3) float
        Current mesh, scene units.
    faces : (F,3) int
        Triangles (consistently wound).
    camera : Camera
    loops : list of (n,) int
        Ordered vertex chains.
    closed : bool
        The chains are closed loops (the last vertex joins the first).

    Returns
    -------
    (K,) int64
    """
    V = np.asarray(vertices, dtype=np.float64)
    F = np.asarray(faces, dtype=np.int64)
    if len(loops) == 0:
        return np.zeros(0, np.int64)
    lookup = edge_lookup(F)
    out = []
    for lp in loops:
        lp = np.asarray(lp, dtype=np.int64)
        nxt = np.roll(lp, -1) if closed else lp[1:]
        cur = lp if closed else lp[:-1]
        E = np.sort(np.stack([cur, nxt], axis=1), axis=1)
        ef = lookup(E)
        ok = (ef >= 0).all(axis=1)
        s = _facing_sign(V, F[np.maximum(ef.ravel(), 0)], camera).reshape(-1, 2)
        out.append(int((ok & (s[:, 0] != s[:, 1])).sum()))
    return np.asarray(out, dtype=np.int64)


def select_occluding_loop(vertices, faces, camera, loops) -> int:
    """Index of the candidate loop with the most silhouette edges from ``camera``.

    Ties go to the lowest index. See :func:`silhouette_edge_counts`.
    """
    if len(loops) == 0:
        raise FaceLabError("No candidate loops to choose from; build them with contour_loops().")
    return int(np.argmax(silhouette_edge_counts(vertices, faces, camera, loops)))
