"""Occluding contours of the inner lips and eyelids, matched to tracked curves.

Bhat et al. 2013, "High Fidelity Facial Animation Capture and Retargeting
With Contours", §4.2 "Contour constraints" (and the eyelid part of §4.1).

The tracked curves are *primary contours*: the inner-lip and eyelid lines an
artist or tracker follows in the footage. They are silhouettes, so the mesh
points that project onto them change as the lips roll. Following the paper:

1. **Candidates** (:func:`contour_loops`, once on the rest mesh). Concentric
   closed edge loops around the mouth opening, from the loop where the lips
   weld to the mouth bag (or the border of the mouth hole) outward over the
   lip roll, past the line where the lips touch, onto the lip fronts
   (Fig. 2a); and around each eye opening, outward over the eyelid margin.
   A loop is grown by one ring of triangles at a time, so it follows the
   mesh's edge flow (on ICT-FaceKit: 14 rings of 74 vertices around the
   mouth, 4 rings of 42-46 vertices around each eye).
2. **Occluding contour** (:func:`select_occluding_loop` for whole loops;
   :func:`match_contours` per half, as described here). Per frame and
   camera, the edge contour with the most *silhouette edges* (an edge shared
   by a triangle facing the camera and one facing away). Each loop is split at
   the two mouth (eye) corners into an upper and a lower half, and each
   tracked curve (upper lip, lower lip, upper lid, lower lid) chooses its half
   independently: on ICT-FaceKit the upper- and lower-lip silhouettes lie on
   different rings (neutral: rings 7 and 6; rolling the upper lip moves its
   silhouette to ring 10), and so do the eyelid silhouettes (rings 1 and 2).
   The paper's "edge contour" is "a subset of connected edges from an
   edge-loop"; the half-loop is that subset. Only silhouette edges that can
   be the tracked line count: those bounding the opening (the lip lies on
   the far side of the edge from the opening in the image) and, when a
   tracked curve is given, those near it; near-ties go to the previous loop,
   then to the half closest to the curve.
3. **Correspondence** (:func:`match_contours`). The contour's points are
   projected into the camera; the contour is split at the corners and at the
   middle of the lips (eyelids: at the eye corners); each split point is
   matched to the closest point of the tracked curve, and the points between
   two split points are matched by arc length (Fig. 2b). The result is a set
   of surface points on mesh edges (two vertices and barycentric weights)
   with pixel targets, fitted like 2D markers (Eq. 1).
4. **Eyelids on the cornea** (§4.1). The eyelid targets are projected from
   the camera onto the eyeball sphere (:mod:`facelab_addon.core.geometry.sphere`)
   grown by each lid point's current height over it (the lid margin's
   thickness on the mesh being matched, so a lid that matches the image
   is its own fixed point), giving 3D targets fitted like bundles (Eq. 2).

The correspondence is computed on the mesh of the previous frame (or the
previous solver iterate) and can be re-run after each solve (the paper
iterates correspondence and solve; one iteration suffices there).
``sliding=False`` freezes the correspondence of ``previous`` (the same mesh
points keep their parameter on the curve): the fixed contours of the paper's
Fig. 6a.

Cost: only the triangles next to candidate loop edges are evaluated; on the
26,719-vertex ICT face :func:`match_contours` with two cameras and six curves
per camera takes a few milliseconds.

Conventions: vertices float64 (V,3) scene units; triangles int64 (F,3);
pixels top-left origin, y down; cameras OpenCV (``core.capture.camera.Camera``).
NumPy/SciPy only, no bpy.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from ..capture.camera import Camera
from ..errors import FaceLabError, MeshError
from ..geometry.mesh import edge_faces, validate_mesh
from ..geometry.sphere import fit_sphere, project_to_sphere

__all__ = [
    "MOUTH_CURVES",
    "EYELID_CURVES",
    "CURVE_NAMES",
    "TrackedCurve",
    "ContourLoops",
    "CurveCorrespondence",
    "contour_loops",
    "ict_contour_loops",
    "edge_loop_rings",
    "silhouette_edge_counts",
    "select_occluding_loop",
    "match_contours",
    "contour_residuals",
    "synthetic_tracked_curves",
    "resample_polyline",
]

MOUTH_CURVES = ("mouth_upper", "mouth_lower")
EYELID_CURVES = ("eyelid_left_upper", "eyelid_left_lower", "eyelid_right_upper", "eyelid_right_lower")
#: Every tracked-curve name :func:`match_contours` understands.
CURVE_NAMES = MOUTH_CURVES + EYELID_CURVES

_ICT_UP = (0.0, 1.0, 0.0)
_ICT_FORWARD = (0.0, 0.0, 1.0)


# --------------------------------------------------------------------------
# Data
# --------------------------------------------------------------------------


@dataclass
class TrackedCurve:
    """A tracked 2D curve on one frame.

    Attributes
    ----------
    name : str
        One of :data:`CURVE_NAMES`: ``'mouth_upper'``, ``'mouth_lower'``,
        ``'eyelid_left_upper'``, ``'eyelid_left_lower'``,
        ``'eyelid_right_upper'``, ``'eyelid_right_lower'`` (left/right are the
        subject's, as in ICT-FaceKit's ``M_ScleraLeft``).
    camera : int
        Index into the list of cameras.
    pixels : (m,2) float
        Polyline from one corner to the other, pixels (top-left origin, y
        down). Orientation is arbitrary.
    """

    name: str
    camera: int
    pixels: np.ndarray


@dataclass
class _Half:
    """One half of a candidate loop, corner to corner, as surface points."""

    vertices: np.ndarray  # (c,2) int64 edge end points of each surface point
    bary: np.ndarray  # (c,2) float64
    splits: np.ndarray  # (s,) int indices of the split points (corners, middle) into the points
    chain: np.ndarray  # (n,) int64 loop vertices from corner 0 to corner 1
    edge_tris: np.ndarray  # (n-1,2,3) int64 the two triangles next to each edge (-1: none)


@dataclass
class ContourLoops:
    """Candidate edge loops for the occluding contours, built once from the rest mesh.

    Attributes
    ----------
    mouth : list of (n,) int64
        Closed, ordered mouth loops, inner (the lip/mouth-bag weld or the
        mouth hole) to outer (the lip fronts).
    eyes : dict str -> list of (n,) int64
        ``'left'`` / ``'right'`` -> eyelid loops, from the eye opening
        outward (empty dict when the mesh has no eyes).
    mouth_corners : (K,2) int64
        The two corner vertices of every mouth loop: on the thinnest loop
        (where the lips meet) its smallest and largest coordinate along
        ``lateral`` in the rest pose; on the other loops the vertices reached
        from there along the mesh edges crossing the loops (the corner's
        column), so all loops split at the same anatomical corner.
    eye_corners : dict str -> (K,2) int64
        The same for the eyelid loops (eye corners).
    eyeballs : dict str -> (n,) int64
        Eyeball (cornea) vertices the sphere is fitted to on each frame.
    eye_spheres : dict str -> (center (3,), radius float)
        Rest-pose eyeball spheres, scene units.
    eyelid_offset : (V,) float64
        Signed distance of every eyelid-loop vertex from its rest eyeball
        sphere, scene units (0 elsewhere): the lid margin's height over the
        eyeball (on ICT-FaceKit the eyelid rings lie 0.2 to 1.3 mm off the
        fitted sphere). Used by ``match_contours(eyelid_height='rest')``;
        the default lifts with the height on the matched mesh instead (ICT's
        lids change height when blinking).
    default_loop : dict str -> int
        Per curve name, the half chosen in the rest pose from a frontal
        camera (used when no half has a silhouette edge and nothing better is
        known).
    up, forward, lateral : (3,) float64
        Face axes (unit): up, the direction the face looks, ``up x forward``.
    n_vertices : int
    info : dict
        Diagnostics (ring sizes, where ring growth stopped).
    """

    mouth: list
    eyes: dict
    mouth_corners: np.ndarray
    eye_corners: dict
    eyeballs: dict
    eye_spheres: dict
    eyelid_offset: np.ndarray
    default_loop: dict
    up: np.ndarray
    forward: np.ndarray
    lateral: np.ndarray
    n_vertices: int
    halves: dict = field(default_factory=dict, repr=False)  # curve name -> list[_Half], one per loop
    info: dict = field(default_factory=dict)
    _pack: _Pack | None = field(default=None, repr=False)
    _sphere_cache: dict = field(default_factory=dict, repr=False)

    def needed_vertices(self) -> np.ndarray:
        """(n,) int64 sorted ids of every vertex :func:`match_contours` reads.

        The triangles next to candidate loop edges and the eyeball vertices: a
        solver may keep only these vertices up to date between iterations
        (about 3,300 of ICT-FaceKit's 26,719).
        """
        tri = self._pack.tri
        parts = [tri.ravel()] + [np.asarray(v, np.int64) for v in self.eyeballs.values()]
        for hs in self.halves.values():
            parts += [h.vertices.ravel() for h in hs]
        return np.unique(np.concatenate(parts))

    def curve_names(self):
        """Tracked-curve names this mesh can match (mouth always; eyelids when it has eyes)."""
        return [n for n in CURVE_NAMES if n in self.halves]

    def loops_for(self, name: str) -> list:
        """Candidate loops of a curve's region (``mouth`` or one eye)."""
        if name.startswith("mouth"):
            return self.mouth
        return self.eyes[name.split("_")[1]]


@dataclass
class CurveCorrespondence:
    """Surface points on the occluding contour and their targets (one residual block).

    Each point lies on a mesh edge: ``x = bary[:,0] V[vertices[:,0]] +
    bary[:,1] V[vertices[:,1]]``.

    Attributes
    ----------
    name : str
        The tracked curve's name.
    camera : int
        Camera of the 2D ``pixels`` targets; ``-1`` for 3D ``targets``.
    vertices : (c,2) int64
        Edge end points.
    bary : (c,2) float64
        Weights of the two end points (sum 1).
    pixels : (c,2) float64 or None
        2D targets in camera ``camera``, pixels.
    targets : (c,3) float64 or None
        3D targets (eyelid curve on the eyeball), scene units.
    loop : int
        Index of the chosen loop in ``ContourLoops.mouth`` /
        ``ContourLoops.eyes[side]``.
    curve_t : (c,) float64 or None
        Normalised arc length (0..1) of each target on the tracked curve,
        measured from its image-left end.
    source_camera : int
        The camera whose tracked curve made the targets.
    """

    name: str
    camera: int
    vertices: np.ndarray
    bary: np.ndarray
    pixels: np.ndarray | None = None
    targets: np.ndarray | None = None
    loop: int = -1
    curve_t: np.ndarray | None = None
    source_camera: int = -1

    def __len__(self) -> int:
        return len(self.vertices)

    def evaluate(self, vertices) -> np.ndarray:
        """Surface points on ``vertices`` (V,3) -> (c,3), or (T,V,3) -> (T,c,3), scene units."""
        X = np.asarray(vertices, dtype=np.float64)
        b = self.bary
        return b[:, 0, None] * X[..., self.vertices[:, 0], :] + b[:, 1, None] * X[..., self.vertices[:, 1], :]

    def matrix(self, n_vertices: int) -> sp.csr_matrix:
        """(c,V) sparse matrix ``A`` with ``A @ V == evaluate(V)``."""
        c = len(self.vertices)
        rows = np.repeat(np.arange(c), 2)
        return sp.csr_matrix((self.bary.ravel(), (rows, self.vertices.ravel())), shape=(c, int(n_vertices)))


# --------------------------------------------------------------------------
# Building the candidate loops
# --------------------------------------------------------------------------


def _unit(v, what):
    v = np.asarray(v, dtype=np.float64).reshape(3)
    n = np.linalg.norm(v)
    if not n > 1e-12:
        raise FaceLabError(f"The '{what}' axis is zero; pass a non-zero direction (ICT-FaceKit: up +Y, forward +Z).")
    return v / n


def _order_cycle(edges):
    """Order the vertices of a single cycle given its edges (k,2); None when not one simple cycle."""
    verts, inv = np.unique(edges, return_inverse=True)
    inv = inv.reshape(-1, 2)
    if len(verts) != len(edges) or len(verts) < 3:
        return None
    deg = np.bincount(inv.ravel(), minlength=len(verts))
    if not (deg == 2).all():
        return None
    nb = -np.ones((len(verts), 2), dtype=np.int64)
    fill = np.zeros(len(verts), dtype=np.int64)
    for a, b in inv:
        nb[a, fill[a]] = b
        fill[a] += 1
        nb[b, fill[b]] = a
        fill[b] += 1
    order = np.empty(len(verts), dtype=np.int64)
    order[0], prev = 0, -1
    for i in range(1, len(verts)):
        cur = order[i - 1]
        nxt = nb[cur, 0] if nb[cur, 0] != prev else nb[cur, 1]
        order[i], prev = nxt, cur
    if len(np.unique(order)) != len(verts) or order[-1] not in nb[0]:
        return None
    return verts[order]


def _border_components(faces, n_vertices):
    """Closed border loops of a triangle set: list of ordered vertex arrays (non-simple ones skipped)."""
    e, ef = edge_faces(faces)
    b = e[(ef < 0).any(axis=1)]
    if len(b) == 0:
        return []
    A = sp.coo_matrix((np.ones(len(b)), (b[:, 0], b[:, 1])), shape=(n_vertices, n_vertices))
    from scipy.sparse.csgraph import connected_components

    _, lab = connected_components(A, directed=False)
    out = []
    for k in np.unique(lab[b[:, 0]]):
        cyc = _order_cycle(b[lab[b[:, 0]] == k])
        if cyc is not None:
            out.append(cyc)
    return out


def edge_loop_rings(faces, start_loop, n_rings: int):
    """Concentric edge loops grown from a border loop, one ring of triangles at a time.

    Ring ``k+1`` is the outer border of the triangles touching rings
    ``0..k``. On a quad mesh (triangulated or not) whose edge flow runs
    around the opening, these are the mesh's edge loops parallel to the
    opening.

    Parameters
    ----------
    faces : (F,3) int
        Triangles to grow over (for example the free, visible part of the
        face). ``start_loop`` must be a border of these triangles.
    start_loop : (n,) int
        Ordered (or unordered) vertices of the starting border loop.
    n_rings : int
        Number of loops to return, including the start.

    Returns
    -------
    rings : list of (n_k,) int64
        Ordered closed loops (closing edge last -> first implied). Growth
        stops early when a ring is not a single simple loop (it reached
        another opening or a mesh border).
    """
    F = np.asarray(faces, dtype=np.int64)
    start = np.asarray(start_loop, dtype=np.int64).ravel()
    nv = int(max(F.max(), start.max()) + 1)
    in_loop = np.zeros(nv, dtype=bool)
    in_loop[start] = True
    # order the start loop from the border edges of F
    e, ef = edge_faces(F)
    be = e[(ef < 0).any(axis=1)]
    be = be[in_loop[be].all(axis=1)]
    ring0 = _order_cycle(be)
    if ring0 is None or len(ring0) != len(np.unique(start)):
        raise MeshError(
            f"The starting loop ({len(start)} vertices) is not a closed border of the given triangles; pass the "
            "loop where the lips meet the mouth bag (ICT-FaceKit: vertices 6632-6705) or the mouth hole's border, "
            "and mark the hidden parts (mouth bag, teeth) as 'fixed'."
        )
    rings = [ring0]
    used_v = in_loop.copy()
    claimed = np.zeros(len(F), dtype=bool)
    cur = in_loop
    for _ in range(int(n_rings) - 1):
        touch = cur[F].any(axis=1) & ~claimed
        if not touch.any():
            break
        claimed |= touch
        ce, cef = edge_faces(F[claimed])
        bedges = ce[(cef < 0).any(axis=1)]
        bedges = bedges[~used_v[bedges].any(axis=1)]
        ring = _order_cycle(bedges) if len(bedges) else None
        if ring is None:
            break
        rings.append(ring)
        cur = np.zeros(nv, dtype=bool)
        cur[ring] = True
        used_v |= cur
    return rings


def _split_half_points(V, chain, lateral, with_mid):
    """Surface points of a half chain (corner0 .. corner1) and the indices of its split points."""
    n = len(chain)
    pv = np.stack([chain, np.r_[chain[1:], chain[-2:-1]]], axis=1)  # each vertex with a neighbour
    pb = np.zeros((n, 2))
    pb[:, 0] = 1.0
    splits = [0, n - 1]
    if with_mid and n >= 3:
        lat = V[chain] @ lateral
        m = 0.5 * (lat[0] + lat[-1])
        d = lat - m
        cross = np.flatnonzero(d[:-1] * d[1:] <= 0)
        if len(cross):
            j = int(cross[np.argmin(np.abs(cross - (n - 1) / 2))])
            den = lat[j + 1] - lat[j]
            t = 0.0 if abs(den) < 1e-300 else float((m - lat[j]) / den)
            if t <= 1e-6:
                splits = [0, j, n - 1]
            elif t >= 1 - 1e-6:
                splits = [0, j + 1, n - 1]
            else:
                pv = np.insert(pv, j + 1, [chain[j], chain[j + 1]], axis=0)
                pb = np.insert(pb, j + 1, [1.0 - t, t], axis=0)
                splits = [0, j + 1, n]
        else:  # degenerate: split at the middle vertex
            splits = [0, (n - 1) // 2, n - 1]
    return pv.astype(np.int64), pb, np.asarray(sorted(set(splits)), dtype=np.int64)


def _ring_corners(V, F, rings, lateral, up):
    """(K,2) corner vertices of concentric rings, following the corner's mesh column.

    The reference ring is the thinnest one (smallest extent along ``up``
    relative to ``lateral``: the line where the lips or lids meet); its
    corners are its lateral extremes. Each further ring takes, for each
    corner, the vertex next to the previous ring's corner (joined by an edge,
    the closest if several), so every ring is split at the same anatomical
    corner. Rings far out on the lip fronts would otherwise put their lateral
    extremes beyond the mouth corner, on the cheek side of the lip.
    """
    from ..geometry.mesh import vertex_adjacency

    def extremes(r):
        lat = V[r] @ lateral
        return [int(r[np.argmin(lat)]), int(r[np.argmax(lat)])]

    thin = [np.ptp(V[r] @ up) / max(np.ptp(V[r] @ lateral), 1e-300) for r in rings]
    ref = int(np.argmin(thin))
    corners = [None] * len(rings)
    corners[ref] = extremes(rings[ref])
    A = vertex_adjacency(F, len(V)).tocsr()
    for step in (1, -1):
        k = ref
        while 0 <= k + step < len(rings):
            nxt = rings[k + step]
            on = np.zeros(len(V), dtype=bool)
            on[nxt] = True
            new = []
            for c in corners[k]:
                nb = A.indices[A.indptr[c] : A.indptr[c + 1]]
                cand = nb[on[nb]]
                if len(cand) == 0:
                    cand = nxt
                new.append(int(cand[np.argmin(np.linalg.norm(V[cand] - V[c], axis=1))]))
            if new[0] == new[1]:
                new = extremes(nxt)
            corners[k + step] = new
            k += step
    return np.asarray(corners, dtype=np.int64)


def _halves_of_loop(V, F_all, edge_index, loop, corners, up, lateral, with_mid):
    """(upper _Half, lower _Half) of one closed loop split at its two corner vertices."""
    n = len(loop)
    pos = {int(v): i for i, v in enumerate(loop)}
    i0, i1 = pos[int(corners[0])], pos[int(corners[1])]
    a = np.roll(loop, -i0)
    j1 = (i1 - i0) % n
    p1 = a[: j1 + 1]
    p2 = np.r_[a[j1:], a[:1]][::-1]
    h1 = V[p1[1:-1]] @ up if len(p1) > 2 else V[p1] @ up
    h2 = V[p2[1:-1]] @ up if len(p2) > 2 else V[p2] @ up
    upper, lower = (p1, p2) if h1.mean() >= h2.mean() else (p2, p1)
    out = []
    for chain in (upper, lower):
        E = np.sort(np.stack([chain[:-1], chain[1:]], axis=1), axis=1)
        ef = edge_index(E)
        tris = np.where(ef[..., None] >= 0, F_all[np.maximum(ef, 0)], -1)
        pv, pb, splits = _split_half_points(V, chain, lateral, with_mid)
        out.append(_Half(vertices=pv, bary=pb, splits=splits, chain=chain.astype(np.int64), edge_tris=tris))
    return out[0], out[1]


@dataclass
class _Pack:
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


def _pack(loops: ContourLoops) -> _Pack:
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
    return _Pack(tri=np.ascontiguousarray(tri), inv=inv.reshape(-1, 2), ok=ok, hid=hid, n_halves=k, offsets=offsets,
                 flat=flat, edges=E, third=third,
                 upper=np.concatenate(upper) if upper else np.zeros(0, bool))


def _edge_lookup(F):
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


def contour_loops(
    rest_vertices,
    faces,
    *,
    fixed=None,
    mouth_loop=None,
    eyeballs=None,
    eye_loops=None,
    n_mouth_loops: int = 14,
    n_eye_loops: int = 4,
    up=_ICT_UP,
    forward=_ICT_FORWARD,
) -> ContourLoops:
    """Find the candidate mouth and eyelid edge loops of a face mesh.

    Parameters
    ----------
    rest_vertices : (V,3) float
        Rest (neutral) pose, scene units.
    faces : (F,3) int
        Triangles.
    fixed : (V,) bool, optional
        Hidden vertices (mouth bag, teeth, gums, eyeballs, back of the
        head). The loops grow over the *free* triangles (no fixed vertex);
        the mouth and eye openings are borders of the free triangles.
    mouth_loop : (n,) int, optional
        The innermost mouth loop (a border of the free triangles: where the
        lips weld to the mouth bag, or the mouth hole). Default: found with
        :func:`facelab_addon.core.lips.mouth.find_mouth`.
    eyeballs : dict str -> (n,) int, optional
        ``'left'`` / ``'right'`` -> eyeball vertex ids (a sphere is fitted to
        them). Without eyeballs the mesh gets no eyelid contours.
    eye_loops : dict str -> (n,) int, optional
        The eye-opening border loops; default: for each eyeball, the border
        loop of the free triangles closest to the eyeball centre.
    n_mouth_loops, n_eye_loops : int
        Number of candidate loops, counted from the opening outward (the
        default 14 reaches the lip fronts on ICT-FaceKit; 4 covers the
        eyelid margin).
    up, forward : (3,) float
        Face up axis and the direction the face looks (ICT-FaceKit: +Y, +Z).

    Returns
    -------
    ContourLoops

    Raises
    ------
    FaceLabError
        When the mouth loop cannot be found or is not a border of the free
        triangles, or an eyeball is unusable.
    """
    V, F = validate_mesh(rest_vertices, faces, name="rest mesh")
    nv = len(V)
    up = _unit(up, "up")
    forward = _unit(forward, "forward")
    lateral = _unit(np.cross(up, forward), "up x forward")
    up = _unit(np.cross(forward, lateral), "up")
    fixed = np.zeros(nv, bool) if fixed is None else np.asarray(fixed, dtype=bool)
    if fixed.shape != (nv,):
        raise FaceLabError(f"'fixed' must be a mask of {nv} vertices, got shape {fixed.shape}; build it on this mesh.")
    Ff = F[~fixed[F].any(axis=1)]
    if len(Ff) == 0:
        raise FaceLabError("Every triangle touches a fixed vertex; 'fixed' must mark only the hidden parts.")
    info = {}

    if mouth_loop is None:
        from ..lips.mouth import find_mouth

        mouth_loop = find_mouth(V, F, fixed if fixed.any() else None, up=up, forward=forward).loop
    mouth = edge_loop_rings(Ff, mouth_loop, n_mouth_loops)
    info["mouth_ring_sizes"] = [len(r) for r in mouth]
    if len(mouth) < n_mouth_loops:
        info["mouth_rings_stopped"] = f"only {len(mouth)} of {n_mouth_loops} mouth rings are simple closed loops"

    eyes, spheres, eyeball_ids = {}, {}, {}
    offset = np.zeros(nv)
    if eyeballs:
        borders = None
        for side in ("left", "right"):
            if side not in eyeballs:
                continue
            ids = np.unique(np.asarray(eyeballs[side], dtype=np.int64).ravel())
            if len(ids) < 4 or ids.min() < 0 or ids.max() >= nv:
                raise FaceLabError(
                    f"The {side} eyeball needs at least 4 valid vertex ids (got {len(ids)}); pass the eyeball "
                    "(sclera) vertices, for ICT-FaceKit part M_Sclera" + side.capitalize() + "."
                )
            c, r = fit_sphere(V[ids])
            if eye_loops is not None and side in eye_loops:
                start = np.asarray(eye_loops[side], dtype=np.int64)
            else:
                if borders is None:
                    borders = _border_components(Ff, nv)
                    ml = set(mouth[0].tolist())
                    borders = [b for b in borders if len(b) >= 6 and not ml.intersection(b.tolist())]
                if not borders:
                    raise FaceLabError(
                        "No eye opening found among the borders of the free triangles; mark the eyeballs as "
                        "'fixed' or pass eye_loops."
                    )
                start = min(borders, key=lambda b: np.linalg.norm(V[b].mean(axis=0) - c))
                if np.linalg.norm(V[start].mean(axis=0) - c) > 2.0 * r:
                    raise FaceLabError(
                        f"No eye opening lies near the {side} eyeball (closest border is "
                        f"{np.linalg.norm(V[start].mean(axis=0) - c):.3g} scene units from its centre); pass eye_loops."
                    )
            rings = edge_loop_rings(Ff, start, n_eye_loops)
            eyes[side] = rings
            spheres[side] = (c, r)
            eyeball_ids[side] = ids
            for lp in rings:
                offset[lp] = np.linalg.norm(V[lp] - c, axis=1) - r
            info[f"eye_{side}_ring_sizes"] = [len(x) for x in rings]

    lookup = _edge_lookup(F)
    halves = {"mouth_upper": [], "mouth_lower": []}
    mouth_corners = _ring_corners(V, F, mouth, lateral, up)
    for lp, cor in zip(mouth, mouth_corners):
        hu, hl = _halves_of_loop(V, F, lookup, lp, cor, up, lateral, with_mid=True)
        halves["mouth_upper"].append(hu)
        halves["mouth_lower"].append(hl)
    eye_corners = {}
    for side, rings in eyes.items():
        halves[f"eyelid_{side}_upper"], halves[f"eyelid_{side}_lower"] = [], []
        eye_corners[side] = _ring_corners(V, F, rings, lateral, up)
        for lp, cor in zip(rings, eye_corners[side]):
            hu, hl = _halves_of_loop(V, F, lookup, lp, cor, up, lateral, with_mid=False)
            halves[f"eyelid_{side}_upper"].append(hu)
            halves[f"eyelid_{side}_lower"].append(hl)

    out = ContourLoops(
        mouth=mouth,
        eyes=eyes,
        mouth_corners=np.asarray(mouth_corners, dtype=np.int64).reshape(-1, 2),
        eye_corners=eye_corners,
        eyeballs=eyeball_ids,
        eye_spheres=spheres,
        eyelid_offset=offset,
        default_loop={},
        up=up,
        forward=forward,
        lateral=lateral,
        n_vertices=nv,
        halves=halves,
        info=info,
    )
    out._pack = _pack(out)
    # default halves: the rest pose seen from the front of each region
    for name in out.halves:
        region = out.loops_for(name)
        P = np.concatenate([V[lp] for lp in region])
        ctr = P.mean(axis=0)
        ext = float(np.ptp(P, axis=0).max())
        cam = Camera.look_at(ctr + 20.0 * ext * forward, ctr, up, 50.0, 36.0, 1920, 1080)
        counts = _half_counts(V, cam, out)[slice(*out._pack.offsets[name])]
        best = np.flatnonzero(counts == counts.max())
        out.default_loop[name] = int(best[len(best) // 2])
    return out


def ict_contour_loops(model, **kwargs) -> ContourLoops:
    """:func:`contour_loops` for an ICT-FaceKit model (``core.capture.ict.ICTModel``).

    Free surface: the ``M_Face`` part; mouth loop: vertices 6632-6705 (the
    lips' weld to the mouth bag); eyeballs: ``M_ScleraLeft`` /
    ``M_ScleraRight``. Keyword arguments are passed on.
    """
    from ...testing.synthetic import ICT_MOUTH_LOOP

    kw = dict(
        fixed=~model.part_vertex_mask("M_Face"),
        mouth_loop=ICT_MOUTH_LOOP,
        eyeballs={
            "left": np.flatnonzero(model.part_vertex_mask("M_ScleraLeft")),
            "right": np.flatnonzero(model.part_vertex_mask("M_ScleraRight")),
        },
    )
    kw.update(kwargs)
    return contour_loops(model.neutral, model.faces, **kw)


# --------------------------------------------------------------------------
# Silhouettes of the candidates
# --------------------------------------------------------------------------


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


def _gather(V, loops: ContourLoops):
    """(9,k) corner coordinates of the candidate triangles (one gather for all cameras)."""
    return np.ascontiguousarray(V).reshape(-1)[loops._pack.flat]


def _silhouettes(V, camera, loops: ContourLoops, G=None, inner: bool = True):
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
        G = _gather(V, loops)
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


def _half_counts(V, camera, loops: ContourLoops, G=None, inner: bool = True):
    """(H,) silhouette-edge count of every candidate half (all curve names packed); see :func:`_silhouettes`."""
    idx = _silhouettes(V, camera, loops, G, inner)[0]
    return np.bincount(loops._pack.hid[idx], minlength=loops._pack.n_halves)


def _envelope_counts(V, camera, loops: ContourLoops, G=None):
    """(H,) per half, its inner silhouette edges that bound the opening in the image (nothing nearer to it).

    For the lower lip (lid) an edge counts when no silhouette edge of another
    candidate of the same curve lies above it at the same lateral image
    position; for the upper lip, none below it: the line an artist draws
    along the dark opening (ignoring occlusion by other parts).
    """
    pk = loops._pack
    idx, mid, ends, up = _silhouettes(V, camera, loops, G)
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


def _near_curve_counts(idx, mid, loops: ContourLoops, lo, hi, C, tol):
    """(hi-lo,) per candidate half, its silhouette edges whose projection lies within ``tol`` px of curve C."""
    hid = loops._pack.hid[idx]
    sel = (hid >= lo) & (hid < hi)
    if not sel.any():
        return np.zeros(hi - lo, dtype=np.int64)
    Cs = C if len(C) <= 128 else np.concatenate([C[:: len(C) // 64], C[-1:]])  # C may already be coarse
    M, h = mid[sel], hid[sel]
    box = ((M >= Cs.min(axis=0) - tol) & (M <= Cs.max(axis=0) + tol)).all(axis=1)  # cheap rejection first
    M, h = M[box], h[box]
    near = _dist_to_polyline(M, Cs) <= tol if len(M) else np.zeros(0, bool)
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
    lookup = _edge_lookup(F)
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


# --------------------------------------------------------------------------
# Curve geometry
# --------------------------------------------------------------------------


def _arclength(P):
    d = P[1:] - P[:-1]
    S = np.empty(len(P))
    S[0] = 0.0
    np.cumsum(np.sqrt((d * d).sum(axis=1)), out=S[1:])
    return S


def resample_polyline(P, spacing: float):
    """Resample a polyline (m,d) at equal arc-length steps of about ``spacing`` (end points kept)."""
    P = np.asarray(P, dtype=np.float64)
    s = _arclength(P)
    n = max(2, int(np.ceil(s[-1] / max(spacing, 1e-12))) + 1)
    u = np.linspace(0.0, s[-1], n)
    return np.stack([np.interp(u, s, P[:, k]) for k in range(P.shape[1])], axis=1)


def _closest_param(Q, C, S):
    """Arc-length parameter on polyline C (m,2) (cumulative S) of the point closest to each Q (k,2)."""
    a = C[:-1]
    ab = C[1:] - a
    L2 = np.maximum(ab[:, 0] ** 2 + ab[:, 1] ** 2, 1e-300)
    qx = Q[:, 0, None] - a[None, :, 0]
    qy = Q[:, 1, None] - a[None, :, 1]
    t = np.clip((qx * ab[None, :, 0] + qy * ab[None, :, 1]) / L2[None], 0.0, 1.0)
    ex = qx - t * ab[None, :, 0]
    ey = qy - t * ab[None, :, 1]
    j = np.argmin(ex * ex + ey * ey, axis=1)
    return S[j] + t[np.arange(len(Q)), j] * (S[j + 1] - S[j])


def _eval_curve(C, S, s):
    return np.stack([np.interp(s, S, C[:, 0]), np.interp(s, S, C[:, 1])], axis=1)


def _canonical(pixels, name):
    """(m,2) float64 polyline ordered from its image-left end, validated."""
    C = np.asarray(pixels, dtype=np.float64)
    if C.ndim != 2 or C.shape[1] != 2 or len(C) < 2:
        raise FaceLabError(
            f"Tracked curve '{name}' must be a polyline of at least 2 points (m,2) in pixels, got shape {C.shape}; "
            "draw the curve from one corner to the other."
        )
    if not np.isfinite(C).all():
        raise FaceLabError(f"Tracked curve '{name}' has NaN or infinite points; redraw or re-track it on this frame.")
    d = C[1:] - C[:-1]
    seg = np.sqrt((d * d).sum(axis=1))
    if not (seg > 1e-9).all():
        keep = np.concatenate([[True], seg > 1e-9])
        C, seg = C[keep], seg[keep[1:]]
        if len(C) < 2:
            raise FaceLabError(f"Tracked curve '{name}' has zero length; draw it from one corner to the other.")
    if C[-1, 0] < C[0, 0]:
        C, seg = C[::-1], seg[::-1]
    S = np.empty(len(C))
    S[0] = 0.0
    np.cumsum(seg, out=S[1:])
    return C, S


def _match_half(half: _Half, P, C, S):
    """Targets (arc-length params on C) of the half's points given their projections P (c,2)."""
    sp_ = half.splits
    s_split = _closest_param(P[sp_], C, S)
    s = np.empty(len(P))
    u = _arclength(P)
    for k in range(len(sp_) - 1):
        i0, i1 = sp_[k], sp_[k + 1]
        du = u[i0 : i1 + 1] - u[i0]
        tot = du[-1]
        w = du / tot if tot > 1e-12 else np.linspace(0.0, 1.0, i1 - i0 + 1)
        s[i0 : i1 + 1] = s_split[k] + w * (s_split[k + 1] - s_split[k])
    return s


# --------------------------------------------------------------------------
# Matching
# --------------------------------------------------------------------------


def _candidates(counts, near_tie):
    """Halves whose silhouette count is within ``near_tie`` (fraction) of the best (all of them when all are 0)."""
    top = counts.max()
    if top == 0:
        return np.arange(len(counts))
    return np.flatnonzero(counts >= max(1, int(np.ceil((1.0 - near_tie) * top))))


def _choose(counts, proj, C, prev_loop, default, near_tie=0.0):
    """Index of the half with the most silhouette edges.

    Ties (counts within ``near_tie`` of the best): the previous loop, then the
    half whose projection is closest to the curve, then the default.
    """
    best = _candidates(counts, near_tie) if near_tie > 0 else np.flatnonzero(counts == counts.max())
    if len(best) == 1:
        return int(best[0])
    if prev_loop is not None and prev_loop in best:
        return int(prev_loop)
    if C is not None:
        Cs = C if len(C) <= 128 else np.concatenate([C[:: len(C) // 64], C[-1:]])  # coarse: enough to rank
        d = [float(np.mean(_dist_to_polyline(proj[int(k)], Cs))) for k in best]
        return int(best[int(np.argmin(d))])
    return int(best[np.argmin(np.abs(best - default))])


def _dist_to_polyline(Q, C):
    """(k,) distance of points Q (k,2) to the polyline C (m,2)."""
    ax, ay = C[:-1, 0], C[:-1, 1]
    bx, by = C[1:, 0] - ax, C[1:, 1] - ay
    L2 = np.maximum(bx * bx + by * by, 1e-300)
    qx = Q[:, 0, None] - ax[None]
    qy = Q[:, 1, None] - ay[None]
    t = np.clip((qx * bx + qy * by) / L2, 0.0, 1.0)
    ex = qx - t * bx
    ey = qy - t * by
    return np.sqrt((ex * ex + ey * ey).min(axis=1))


def match_contours(
    vertices,
    faces,
    cameras,
    curves,
    loops: ContourLoops,
    *,
    sliding: bool = True,
    previous=None,
    eyelids: str = "3d",
    eyelid_min_cos: float = 0.25,
    curve_tolerance: float = 0.02,
    near_tie: float = 0.25,
    eyelid_height: str = "current",
) -> list:
    """Occluding contours of the current mesh matched to the tracked curves (Bhat et al. 2013, §4.2).

    For every tracked curve: choose, in the curve's camera, the candidate half
    loop with the most silhouette edges; project its points; match its split
    points (mouth: both corners and the middle of the lip; eyelid: both eye
    corners) to the closest points of the curve; match the points between
    split points by arc length.

    Parameters
    ----------
    vertices : (V,3) float
        The mesh the correspondence is computed on (the previous frame's
        result, or the current solver iterate), scene units.
    faces : (F,3) int
        Triangles (only used for validation of the vertex count; the loops
        hold the triangles they need).
    cameras : list of Camera
    curves : list of TrackedCurve
    loops : ContourLoops
        From :func:`contour_loops` on the same topology.
    sliding : bool
        True (default): re-select the occluding contour and re-match. False:
        for curves present in ``previous`` keep its surface points and curve
        parameters (only the target positions are re-read from this frame's
        curve): the fixed contours of the paper's Fig. 6a.
    previous : list of CurveCorrespondence, optional
        The previous frame's (or iteration's) correspondences. With
        ``sliding=True`` the previous loop wins ties in the silhouette count.
    eyelids : {'3d', '2d', 'both'}
        Eyelid constraints as 3D targets on the eyeball (``camera=-1``; the
        paper's corrective), as 2D pixel targets (the paper's blendshape
        fit), or both.
    curve_tolerance : float
        Only silhouette edges within this fraction of the tracked curve's
        length (at least 2 px) of the curve count for the selection: a
        silhouette elsewhere (an outer outline of the lip, a fold) cannot be
        what the tracker followed. When no candidate has a silhouette edge
        near the curve, the one closest to the curve is used.
    near_tie : float
        Halves whose count is within this fraction of the best count are
        treated as tied; ties go to the previous loop, then to the half whose
        projection is closest to the curve (silhouettes of a tangled lip can
        spread over several rings with similar counts).
    eyelid_min_cos : float
        3D eyelid targets are kept only where the camera ray meets the
        eyeball at an angle whose cosine (ray against sphere normal) is at
        least this: towards the eyeball's limb seen from that camera the lift
        is ill-conditioned, and lid points beyond it are hidden by the eye.
    eyelid_height : {'current', 'rest'}
        Which sphere a 3D eyelid target is lifted onto. ``'current'``
        (default): the eyeball sphere grown by the lid point's height over
        the eyeball on ``vertices`` (the current fit), so the target keeps
        the rig's lid thickness for this expression and only the tracked
        curve moves it; a lid that matches the image is its own fixed point
        (unbiased). ``'rest'``: grown by the rest-pose height
        (``loops.eyelid_offset``); biased wherever the rig changes the lid's
        height over the eye (ICT blinks: ~0.4 mm RMS).

    Returns
    -------
    list of CurveCorrespondence
        One per curve (two per eyelid curve with ``eyelids='both'``: 2D
        first, then 3D), in the order of ``curves``. A 3D eyelid
        correspondence holds only the kept points (``eyelid_min_cos``), and
        is left out when fewer than two remain.

    Raises
    ------
    FaceLabError
        On unknown curve names, eyelid curves on a mesh without eyes, camera
        indices out of range, degenerate curves, or a contour behind a
        camera.
    """
    V = np.asarray(vertices, dtype=np.float64)
    if V.ndim != 2 or V.shape != (loops.n_vertices, 3):
        raise MeshError(
            f"The mesh has {V.shape[0] if V.ndim == 2 else '?'} vertices but the contour loops were built for "
            f"{loops.n_vertices}; rebuild the loops (contour_loops) on this mesh."
        )
    if eyelids not in ("3d", "2d", "both"):
        raise FaceLabError(f"eyelids must be '3d', '2d' or 'both', got {eyelids!r}.")
    if eyelid_height not in ("current", "rest"):
        raise FaceLabError(f"eyelid_height must be 'current' or 'rest', got {eyelid_height!r}.")
    prev = {}
    for pc in previous or []:
        key = (pc.name, pc.source_camera if pc.source_camera >= 0 else pc.camera, pc.camera < 0)
        prev[key] = pc
    counts_cache = {}
    G = None
    Pcache = {}
    lift = []  # (index into out, eye side, camera) of the 3D eyelid correspondences to lift
    out = []
    for cv in curves:
        name = cv.name
        if name not in CURVE_NAMES:
            raise FaceLabError(f"Unknown tracked curve '{name}'; use one of {', '.join(CURVE_NAMES)}.")
        if name not in loops.halves:
            raise FaceLabError(
                f"Tracked curve '{name}' needs eyelid loops, but the mesh has no eyes; pass the eyeball vertices "
                "to contour_loops (ict_contour_loops does this for ICT-FaceKit) or remove the eyelid curves."
            )
        ci = int(cv.camera)
        if not 0 <= ci < len(cameras):
            raise FaceLabError(
                f"Tracked curve '{name}' refers to camera {ci}, but {len(cameras)} camera(s) are given; "
                "assign the curve to one of the solve's cameras."
            )
        cam = cameras[ci]
        if ci not in Pcache:
            Pcache[ci] = cam.P
        Pm = Pcache[ci]
        C, S = _canonical(cv.pixels, name)
        is_eye = name.startswith("eyelid")
        kinds = [False] if not is_eye else {"3d": [True], "2d": [False], "both": [False, True]}[eyelids]
        # the 2D correspondence (selection + arc-length matching), shared by the 2D and 3D outputs
        p0 = None
        for want3d in kinds:
            p0 = prev.get((name, ci, want3d))
            if p0 is not None:
                break
        if not sliding and p0 is not None and p0.curve_t is not None:
            k = p0.loop
            pv, pb, t = p0.vertices, p0.bary, p0.curve_t
            s = t * S[-1]
        else:
            lo, hi = loops._pack.offsets[name]
            if ci not in counts_cache:
                if G is None:
                    G = _gather(V, loops)
                sil = _silhouettes(V, cam, loops, G)
                n_all = np.bincount(loops._pack.hid[sil[0]], minlength=loops._pack.n_halves)
                counts_cache[ci] = (sil[0], sil[1], n_all)
            sil_idx, sil_mid, all_counts = counts_cache[ci]
            tol = max(2.0, curve_tolerance * S[-1])
            Cs = C if len(C) <= 128 else np.concatenate([C[:: len(C) // 64], C[-1:]])  # coarse, for ranking
            halves = loops.halves[name]
            # shortcut: a clear winner by count whose matched points already lie along the curve needs no more
            ic = all_counts[lo:hi]
            k = int(np.argmax(ic))
            s = None
            if ic[k] > 0 and len(_candidates(ic, near_tie)) == 1:
                P = _project(Pm, _eval_points(V, halves[k]), name)
                s = _match_half(halves[k], P, C, S)
                d = P - _eval_curve(C, S, s)
                if np.median(d[:, 0] ** 2 + d[:, 1] ** 2) > tol * tol:
                    s = None
            if s is None:
                counts = _near_curve_counts(sil_idx, sil_mid, loops, lo, hi, Cs, tol)
                best = _candidates(counts, near_tie)
                proj = {}
                if len(best) > 1:
                    for kk in best:
                        proj[int(kk)] = _project(Pm, _eval_points(V, halves[kk]), name)
                k = _choose(counts, proj, Cs, p0.loop if p0 is not None else None, loops.default_loop[name], near_tie)
                P = proj.get(k)
                if P is None:
                    P = _project(Pm, _eval_points(V, halves[k]), name)
                s = _match_half(halves[k], P, C, S)
            half = halves[k]
            pv, pb = half.vertices, half.bary
            t = s / S[-1]
        px = _eval_curve(C, S, s)
        for want3d in kinds:
            if not want3d:
                out.append(CurveCorrespondence(name, ci, pv, pb, pixels=px, loop=k, curve_t=t, source_camera=ci))
            else:
                lift.append((len(out), name.split("_")[1], ci))
                out.append(CurveCorrespondence(name, -1, pv, pb, targets=None, loop=k, curve_t=t, source_camera=ci,
                                               pixels=px))
    if lift:
        _lift_eyelids(V, cameras, loops, out, lift, eyelid_min_cos, eyelid_height)
        out = [c for c in out if not (c.camera < 0 and c.targets is None)]
    return out


def _eyeball_sphere(V, loops, side):
    """Sphere fitted to the eyeball vertices of ``V``; refitted only when they moved."""
    P = V[loops.eyeballs[side]]
    hit = loops._sphere_cache.get(side)
    if hit is not None and hit[0].shape == P.shape and np.array_equal(hit[0], P):
        return hit[1]
    cr = fit_sphere(P)
    loops._sphere_cache[side] = (P.copy(), cr)
    return cr


def _lift_eyelids(V, cameras, loops, out, lift, min_cos, height="current"):
    """Project the 2D targets of the 3D eyelid correspondences onto the eyeball (batched per eye and camera).

    Each target lies on the camera ray of its curve pixel, on the eyeball sphere
    grown by the lid point's height over it: the current height on ``V``
    (``height='current'``) or the rest height (``'rest'``).
    """
    groups = {}
    for i, side, ci in lift:
        groups.setdefault((side, ci), []).append(i)
    spheres = {}
    for (side, ci), idx in groups.items():
        if side not in spheres:
            spheres[side] = _eyeball_sphere(V, loops, side)
        c, r = spheres[side]
        cam = cameras[ci]
        cs = [out[i] for i in idx]
        px = np.concatenate([cc.pixels for cc in cs])
        pv = np.concatenate([cc.vertices for cc in cs])
        pb = np.concatenate([cc.bary for cc in cs])
        if height == "current":
            P = pb[:, 0, None] * V[pv[:, 0]] + pb[:, 1, None] * V[pv[:, 1]]
            rad = np.linalg.norm(P - c, axis=1)
        else:
            off = loops.eyelid_offset
            rad = r + pb[:, 0] * off[pv[:, 0]] + pb[:, 1] * off[pv[:, 1]]
        X, hit = project_to_sphere(cam, px, c, rad)
        # keep points whose ray meets the eyeball clearly: near the limb seen from this camera the lift is
        # ill-conditioned (and a lid point beyond the limb is hidden by the eye itself)
        ray = X - cam.center
        nrm = X - c
        cos = -np.einsum("ij,ij->i", ray, nrm) / (
            np.sqrt(np.einsum("ij,ij->i", ray, ray) * np.maximum(np.einsum("ij,ij->i", nrm, nrm), 1e-300)))
        keep = hit & (cos >= min_cos)
        start = 0
        for i, cc in zip(idx, cs):
            n = len(cc.vertices)
            kp = keep[start : start + n]
            Xi = X[start : start + n]
            start += n
            cc.pixels = None
            if kp.sum() < 2:
                continue  # dropped by the caller
            if kp.all():
                cc.targets = Xi
            else:
                cc.vertices, cc.bary, cc.curve_t, cc.targets = cc.vertices[kp], cc.bary[kp], cc.curve_t[kp], Xi[kp]


def _eval_points(V, half: _Half):
    b = half.bary
    return b[:, 0, None] * V[half.vertices[:, 0]] + b[:, 1, None] * V[half.vertices[:, 1]]


def _project(P, X, name):
    """(n,2) pixels of world points X (n,3) by the (3,4) projection P; raises when a point is behind the camera."""
    h = X @ P[:, :3].T + P[:, 3]
    if (h[:, 2] <= 0).any():
        raise FaceLabError(
            f"The contour for '{name}' is behind the camera; check the camera calibration and the curve's camera."
        )
    return h[:, :2] / h[:, 2:3]


def contour_residuals(vertices, cameras, correspondences) -> list:
    """Residual length of every correspondence point.

    Parameters
    ----------
    vertices : (V,3) float
        Mesh, scene units.
    cameras : list of Camera
    correspondences : list of CurveCorrespondence

    Returns
    -------
    list of (c,) float64
        Reprojection distance in pixels for 2D correspondences; 3D distance
        in scene units for ``camera == -1``.
    """
    V = np.asarray(vertices, dtype=np.float64)
    out = []
    for cc in correspondences:
        X = cc.evaluate(V)
        if cc.camera >= 0:
            out.append(np.linalg.norm(cameras[cc.camera].project(X) - cc.pixels, axis=1))
        else:
            out.append(np.linalg.norm(X - cc.targets, axis=1))
    return out


# --------------------------------------------------------------------------
# Ground truth for tests and benchmarks
# --------------------------------------------------------------------------


def synthetic_tracked_curves(
    vertices,
    faces,
    cameras,
    loops: ContourLoops,
    *,
    names=None,
    spacing_px: float = 0.25,
    noise_px: float = 0.0,
    seed: int = 0,
) -> list:
    """The truth's occluding contours as a tracker would deliver them.

    For every camera and curve name, the half loop with the most silhouette
    edges on the *envelope of the opening* (silhouette edges that bound the
    mouth or eye opening with no other candidate's silhouette nearer to the
    opening at the same lateral image position: the line an artist traces
    along the dark opening; ties go to the rest-pose default) is projected
    and resampled every ``spacing_px`` pixels, corner to corner, ordered
    from image-left.

    Parameters
    ----------
    vertices : (V,3) float
        The ground-truth mesh, scene units.
    faces : (F,3) int
    cameras : list of Camera
    loops : ContourLoops
    names : list of str, optional
        Curve names to make (default: all the loops support).
    spacing_px : float
        Sample spacing along the curve, pixels.
    noise_px : float
        Standard deviation of Gaussian noise added to every sample, pixels.
    seed : int
        Noise seed.

    Returns
    -------
    list of TrackedCurve
        Curves whose samples all fall inside the image; the others are left
        out (a tracker cannot follow them).
    """
    V = np.asarray(vertices, dtype=np.float64)
    if V.shape != (loops.n_vertices, 3):
        raise MeshError(f"The truth has {len(V)} vertices, the loops were built for {loops.n_vertices}.")
    names = loops.curve_names() if names is None else list(names)
    rng = np.random.default_rng(seed)
    out = []
    for ci, cam in enumerate(cameras):
        counts = _envelope_counts(V, cam, loops)
        for name in names:
            if name not in loops.halves:
                raise FaceLabError(f"The loops have no '{name}' candidates; use one of {loops.curve_names()}.")
            lo, hi = loops._pack.offsets[name]
            c = counts[lo:hi]
            best = np.flatnonzero(c == c.max())
            k = int(best[np.argmin(np.abs(best - loops.default_loop[name]))])
            X = _eval_points(V, loops.halves[name][k])
            if (cam.depth(X) <= 0).any():
                continue
            P = resample_polyline(cam.project(X), spacing_px)
            if noise_px > 0:
                P = P + rng.normal(0.0, noise_px, P.shape)
            if not cam.in_frame(P).all():
                continue
            if P[-1, 0] < P[0, 0]:
                P = P[::-1]
            out.append(TrackedCurve(name=name, camera=ci, pixels=P))
    return out
