"""Candidate edge loops for the occluding contours of the inner lips and eyelids.

Bhat et al. 2013, "High Fidelity Facial Animation Capture and Retargeting
With Contours", §4.2 "Contour constraints" (candidates, Fig. 2a).

The tracked curves (:class:`TrackedCurve`) are *primary contours*: the
inner-lip and eyelid lines an artist or tracker follows in the footage. They
are silhouettes, so the mesh points that project onto them change as the lips
roll; the candidates are the edge loops such a silhouette can lie on.
:func:`contour_loops` builds them once on the rest mesh:

* concentric closed edge loops around the mouth opening, from the loop where
  the lips weld to the mouth bag (or the border of the mouth hole) outward
  over the lip roll, past the line where the lips touch, onto the lip fronts;
  and around each eye opening, outward over the eyelid margin. A loop is
  grown by one ring of triangles at a time (:func:`edge_loop_rings`), so it
  follows the mesh's edge flow (on ICT-FaceKit: 14 rings of 74 vertices
  around the mouth, 4 rings of 42-46 vertices around each eye);
* each loop split at the two mouth (eye) corners into an upper and a lower
  half, the paper's "edge contour" ("a subset of connected edges from an
  edge-loop"). All loops of one opening split at the same anatomical corner
  (the corner's mesh column); each tracked curve later chooses its half
  independently (:mod:`.matching`);
* per curve, a default half: the one with the most silhouette edges
  (:mod:`.occlusion`) in the rest pose seen from the front.

Conventions: vertices float64 (V,3) scene units; triangles int64 (F,3); face
axes ``up`` / ``forward`` default to :mod:`facelab_addon.core.geometry.axes`
(Y up, looking along +Z). NumPy/SciPy only, no bpy.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from ..capture.camera import Camera
from ..errors import FaceLabError, MeshError
from ..geometry.axes import Y_UP, Z_FORWARD, unit_axis
from ..geometry.mesh import edge_faces, validate_mesh, vertex_adjacency
from ..geometry.sphere import fit_sphere
from ..lips.mouth import find_mouth
from .occlusion import edge_lookup, half_silhouette_counts, CandidatePack, pack_candidates

__all__ = [
    "MOUTH_CURVES",
    "EYELID_CURVES",
    "CURVE_NAMES",
    "TrackedCurve",
    "ContourLoops",
    "contour_loops",
    "edge_loop_rings",
]

MOUTH_CURVES = ("mouth_upper", "mouth_lower")
EYELID_CURVES = ("eyelid_left_upper", "eyelid_left_lower", "eyelid_right_upper", "eyelid_right_lower")
#: Every tracked-curve name :func:`~facelab_addon.core.solve.matching.match_contours` understands.
CURVE_NAMES = MOUTH_CURVES + EYELID_CURVES


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
class LoopHalf:
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
        fitted sphere). Used by ``match_contours`` with ``MatchParams(eyelid_height='rest')``;
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
    halves: dict = field(default_factory=dict, repr=False)  # curve name -> list[LoopHalf], one per loop
    info: dict = field(default_factory=dict)
    pack_candidates: CandidatePack | None = field(default=None, repr=False)
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
    """(upper LoopHalf, lower LoopHalf) of one closed loop split at its two corner vertices."""
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
        out.append(LoopHalf(vertices=pv, bary=pb, splits=splits, chain=chain.astype(np.int64), edge_tris=tris))
    return out[0], out[1]


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
    up=Y_UP,
    forward=Z_FORWARD,
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
    up = unit_axis(up, "up")
    forward = unit_axis(forward, "forward")
    lateral = unit_axis(np.cross(up, forward), "up x forward")
    up = unit_axis(np.cross(forward, lateral), "up")
    fixed = np.zeros(nv, bool) if fixed is None else np.asarray(fixed, dtype=bool)
    if fixed.shape != (nv,):
        raise FaceLabError(f"'fixed' must be a mask of {nv} vertices, got shape {fixed.shape}; build it on this mesh.")
    Ff = F[~fixed[F].any(axis=1)]
    if len(Ff) == 0:
        raise FaceLabError("Every triangle touches a fixed vertex; 'fixed' must mark only the hidden parts.")
    info = {}

    if mouth_loop is None:
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

    lookup = edge_lookup(F)
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
    out._pack = pack_candidates(out)
    # default halves: the rest pose seen from the front of each region
    for name in out.halves:
        region = out.loops_for(name)
        P = np.concatenate([V[lp] for lp in region])
        ctr = P.mean(axis=0)
        ext = float(np.ptp(P, axis=0).max())
        cam = Camera.look_at(ctr + 20.0 * ext * forward, ctr, up, 50.0, 36.0, 1920, 1080)
        counts = half_silhouette_counts(V, cam, out)[slice(*out._pack.offsets[name])]
        best = np.flatnonzero(counts == counts.max())
        out.default_loop[name] = int(best[len(best) // 2])
    return out
