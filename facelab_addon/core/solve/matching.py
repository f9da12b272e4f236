"""Tracked curves matched to the mesh's occluding contours.

Bhat et al. 2013, "High Fidelity Facial Animation Capture and Retargeting
With Contours", §4.2 "Contour constraints" (Fig. 2b). For every tracked curve
(:class:`~facelab_addon.core.solve.contour_loops.TrackedCurve`),
:func:`match_contours`:

1. **Chooses the occluding contour.** In the curve's camera, the candidate
   half loop (:mod:`.contour_loops`) with the most silhouette edges
   (:mod:`.occlusion`). Each tracked curve (upper lip, lower lip, upper lid,
   lower lid) chooses its half independently: on ICT-FaceKit the upper- and
   lower-lip silhouettes lie on different rings (neutral: rings 7 and 6;
   rolling the upper lip moves its silhouette to ring 10), and so do the
   eyelid silhouettes (rings 1 and 2). Only silhouette edges that can be the
   tracked line count: those bounding the opening and, when a tracked curve
   is given, those near it; near-ties go to the previous loop, then to the
   half closest to the curve.
2. **Matches it to the curve.** The half's points are projected into the
   camera; the half is split at the corners and at the middle of the lips
   (eyelids: at the eye corners); each split point is matched to the
   closest point of the tracked curve, and the points between two split
   points by arc length. The result (:class:`CurveCorrespondence`) is a set
   of surface points on mesh edges (two vertices and barycentric weights)
   with pixel targets, fitted like 2D markers (Eq. 1).
3. **Lifts eyelid targets** onto the eyeball (§4.1, :mod:`.eyelids`): 3D
   targets fitted like bundles (Eq. 2).

The correspondence is computed on the mesh of the previous frame (or the
previous solver iterate) and can be re-run after each solve (the paper
iterates correspondence and solve; one iteration suffices there).
``sliding=False`` freezes the correspondence of ``previous`` (the same mesh
points keep their parameter on the curve): the fixed contours of the paper's
Fig. 6a. On the 26,719-vertex ICT face, :func:`match_contours` with two
cameras and six curves per camera takes a few milliseconds.

:func:`contour_residuals` (distance to the matched targets) and
:func:`contour_curve_distance` (distance to the tracked curve, sliding
allowed) measure a fit.

Conventions: vertices float64 (V,3) scene units; triangles int64 (F,3);
pixels top-left origin, y down; cameras OpenCV (``core.capture.camera.Camera``).
NumPy/SciPy only, no bpy.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ..errors import FaceLabError, MeshError
from ..geometry.polyline import (
    arc_length,
    closest_arc_length,
    point_to_polyline_distance,
    points_at_arc_length,
)
from .contour_loops import CURVE_NAMES, ContourLoops, LoopHalf
from .eyelids import lift_eyelids
from .occlusion import gather_corners, near_curve_counts, candidate_silhouettes

__all__ = [
    "MatchParams",
    "CurveCorrespondence",
    "match_contours",
    "contour_residuals",
    "contour_curve_distance",
]


@dataclass(frozen=True)
class MatchParams:
    """Options of the contour selection and matching (:func:`match_contours`).

    Attributes
    ----------
    eyelids : {'3d', '2d', 'both'}
        Eyelid constraints as 3D targets on the eyeball (``camera=-1``; the
        paper's corrective), as 2D pixel targets (the paper's blendshape
        fit), or both.
    eyelid_height : {'current', 'rest'}
        Which sphere a 3D eyelid target is lifted onto. ``'current'``: the
        eyeball sphere grown by the lid point's height over the eyeball on
        the mesh being matched (the current fit), so the target keeps the
        rig's lid thickness for this expression and only the tracked curve
        moves it; a lid that matches the image is its own fixed point
        (unbiased). ``'rest'``: grown by the rest-pose height
        (``ContourLoops.eyelid_offset``); biased wherever the rig changes
        the lid's height over the eye.
    eyelid_min_cos : float
        3D eyelid targets are kept only where the camera ray meets the
        eyeball at an angle whose cosine (ray against sphere normal,
        dimensionless) is at least this: towards the eyeball's limb seen from
        that camera the lift is ill-conditioned, and lid points beyond it are
        hidden by the eye.
    curve_tolerance : float
        Only silhouette edges within this fraction (dimensionless) of the
        tracked curve's length, and at least 2 px, of the curve count for the
        selection: a silhouette elsewhere (an outer outline of the lip, a
        fold) cannot be what the tracker followed. When no candidate has a
        silhouette edge near the curve, the one closest to the curve is used.
    near_tie : float
        Halves whose silhouette count is within this fraction (dimensionless)
        of the best count are treated as tied; ties go to the previous loop,
        then to the half whose projection is closest to the curve
        (silhouettes of a tangled lip can spread over several rings with
        similar counts).

    Raises
    ------
    FaceLabError
        ``eyelids`` or ``eyelid_height`` not one of the choices above.
    """

    eyelids: str = "3d"
    eyelid_height: str = "current"
    eyelid_min_cos: float = 0.25
    curve_tolerance: float = 0.02
    near_tie: float = 0.25

    def __post_init__(self):
        if self.eyelids not in ("3d", "2d", "both"):
            raise FaceLabError(f"eyelids must be '3d', '2d' or 'both', got {self.eyelids!r}.")
        if self.eyelid_height not in ("current", "rest"):
            raise FaceLabError(f"eyelid_height must be 'current' or 'rest', got {self.eyelid_height!r}.")


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


def _match_half(half: LoopHalf, P, C, S):
    """Targets (arc-length params on C) of the half's points given their projections P (c,2)."""
    sp_ = half.splits
    s_split = closest_arc_length(P[sp_], C, S)
    s = np.empty(len(P))
    u = arc_length(P)
    for k in range(len(sp_) - 1):
        i0, i1 = sp_[k], sp_[k + 1]
        du = u[i0 : i1 + 1] - u[i0]
        tot = du[-1]
        w = du / tot if tot > 1e-12 else np.linspace(0.0, 1.0, i1 - i0 + 1)
        s[i0 : i1 + 1] = s_split[k] + w * (s_split[k + 1] - s_split[k])
    return s


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
        d = [float(np.mean(point_to_polyline_distance(proj[int(k)], Cs))) for k in best]
        return int(best[int(np.argmin(d))])
    return int(best[np.argmin(np.abs(best - default))])


def match_contours(
    vertices,
    faces,
    cameras,
    curves,
    loops: ContourLoops,
    params: MatchParams = MatchParams(),
    *,
    previous=None,
    sliding: bool = True,
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
    params : MatchParams
        Eyelid mode and lift, and the selection's curve tolerance and tie
        fraction.
    previous : list of CurveCorrespondence, optional
        The previous frame's (or iteration's) correspondences. With
        ``sliding=True`` the previous loop wins ties in the silhouette count.
    sliding : bool
        True (default): re-select the occluding contour and re-match. False:
        for curves present in ``previous`` keep its surface points and curve
        parameters (only the target positions are re-read from this frame's
        curve): the fixed contours of the paper's Fig. 6a.

    Returns
    -------
    list of CurveCorrespondence
        One per curve (two per eyelid curve with ``params.eyelids='both'``: 2D
        first, then 3D), in the order of ``curves``. A 3D eyelid
        correspondence holds only the kept points (``params.eyelid_min_cos``), and
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
    if not isinstance(params, MatchParams):
        raise FaceLabError(f"params must be a MatchParams, got {type(params).__name__}; pass MatchParams(...).")
    eyelids, near_tie = params.eyelids, params.near_tie
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
                    G = gather_corners(V, loops)
                sil = candidate_silhouettes(V, cam, loops, G)
                n_all = np.bincount(loops._pack.hid[sil[0]], minlength=loops._pack.n_halves)
                counts_cache[ci] = (sil[0], sil[1], n_all)
            sil_idx, sil_mid, all_counts = counts_cache[ci]
            tol = max(2.0, params.curve_tolerance * S[-1])
            Cs = C if len(C) <= 128 else np.concatenate([C[:: len(C) // 64], C[-1:]])  # coarse, for ranking
            halves = loops.halves[name]
            # shortcut: a clear winner by count whose matched points already lie along the curve needs no more
            ic = all_counts[lo:hi]
            k = int(np.argmax(ic))
            s = None
            if ic[k] > 0 and len(_candidates(ic, near_tie)) == 1:
                P = _project(Pm, half_points(V, halves[k]), name)
                s = _match_half(halves[k], P, C, S)
                d = P - points_at_arc_length(C, S, s)
                if np.median(d[:, 0] ** 2 + d[:, 1] ** 2) > tol * tol:
                    s = None
            if s is None:
                counts = near_curve_counts(sil_idx, sil_mid, loops, lo, hi, Cs, tol)
                best = _candidates(counts, near_tie)
                proj = {}
                if len(best) > 1:
                    for kk in best:
                        proj[int(kk)] = _project(Pm, half_points(V, halves[kk]), name)
                k = _choose(counts, proj, Cs, p0.loop if p0 is not None else None, loops.default_loop[name], near_tie)
                P = proj.get(k)
                if P is None:
                    P = _project(Pm, half_points(V, halves[k]), name)
                s = _match_half(halves[k], P, C, S)
            half = halves[k]
            pv, pb = half.vertices, half.bary
            t = s / S[-1]
        px = points_at_arc_length(C, S, s)
        for want3d in kinds:
            if not want3d:
                out.append(CurveCorrespondence(name, ci, pv, pb, pixels=px, loop=k, curve_t=t, source_camera=ci))
            else:
                lift.append((len(out), name.split("_")[1], ci))
                out.append(CurveCorrespondence(name, -1, pv, pb, targets=None, loop=k, curve_t=t, source_camera=ci,
                                               pixels=px))
    if lift:
        lift_eyelids(V, cameras, loops, out, lift, params.eyelid_min_cos, params.eyelid_height)
        out = [c for c in out if not (c.camera < 0 and c.targets is None)]
    return out


def half_points(V, half: LoopHalf):
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


def contour_curve_distance(vertices, cameras, correspondences, curves) -> np.ndarray:
    """Pixel distance of every 2D contour point to its tracked curve (polyline).

    Unlike the matched-point residual, sliding along the curve is not an
    error here: this is how far the mesh's contour lies from the drawn curve.

    Parameters
    ----------
    vertices : (V,3) float
    cameras : list of Camera
    correspondences : list of CurveCorrespondence
    curves : list of TrackedCurve

    Returns
    -------
    (n,) float64
        Distances (pixels) of all points of the 2D correspondences.
    """
    V = np.asarray(vertices, float)
    by = {(c.name, int(c.camera)): np.asarray(c.pixels, float) for c in curves or []}
    out = []
    for cc in correspondences or []:
        if getattr(cc, "pixels", None) is None or cc.camera < 0 or (cc.name, int(cc.camera)) not in by:
            continue
        v, b = np.asarray(cc.vertices), np.asarray(cc.bary, float)
        X = np.einsum("ck,ckd->cd", b, V[v])
        out.append(point_to_polyline_distance(cameras[cc.camera].project(X), by[(cc.name, int(cc.camera))]))
    return np.concatenate(out) if out else np.zeros(0)
