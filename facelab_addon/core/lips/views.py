"""Sketch views of the lip refinement: one camera and its two inner-lip contours.

Dinev et al. 2018 §5 sketch the inner-lip silhouettes from one camera. A single view cannot see
how far the lips sit toward the camera, so FaceLab lets the artist sketch the same frame from
several cameras (a helmet stereo pair, a witness camera); each :class:`SketchView` contributes its
own ``E_silh`` terms to one solve. :class:`ViewMatcher` holds what one view needs between
iterations: the resampled (and pressed) sketch, its camera rays, the candidate silhouette edges
near the sketch, and the matching of every sketch pixel to the closest silhouette vertex of its
lip (upper / lower told apart by the image-space direction of the vertex normals).

Shapes: vertices (V,3) float64 scene units; pixels (N,2), top-left origin, y down.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..capture.camera import Camera
from ..errors import CameraError, SketchError
from ..geometry.deform import PointConstraints
from ..geometry.mesh import edge_faces, faces_within
from ..geometry.polyline import resample_polyline, y_at
from ..geometry.silhouette import facing, projected_normals
from .contact import contact_terms, one_line
from .camera_checks import require_camera_outside
from .swapped_strokes import check_swapped_strokes

__all__ = ["SketchView", "ViewMatcher", "press_lips", "prepare_sketch", "square_pixels"]


@dataclass
class SketchView:
    """One camera and the inner-lip contours sketched through it.

    Attributes
    ----------
    camera : Camera
    upper, lower : (N,2) float or list of (N_i,2)
        Upper and lower inner-lip strokes, pixels of ``camera`` (top-left origin, y down).
    name : str
        What to call the view in messages (for example the camera object's name).
    """

    camera: Camera
    upper: object
    lower: object
    name: str = ""


def square_pixels(view: SketchView) -> SketchView:
    """``view`` in square pixels: the camera's coarser pixel axis (the smaller focal length, a render pixel aspect
    not 1) scaled up to the finer one, its strokes with it; the same rays, so every pixel size of the solve
    (resampling, matching, tolerances) means the same length across and along the image. A view whose pixels
    are square is returned as it is.
    """
    cam = view.camera
    fx, fy = float(cam.K[0, 0]), float(cam.K[1, 1])
    if abs(fx - fy) <= 1e-9 * max(fx, fy):
        return view
    s = np.array([max(fx, fy) / fx, max(fx, fy) / fy])
    K = np.diag([s[0], s[1], 1.0]) @ cam.K
    out = Camera(K, cam.R, cam.t, max(1, round(cam.width * s[0])), max(1, round(cam.height * s[1])))
    return SketchView(out, [p * s for p in _as_polylines(view.upper)], [p * s for p in _as_polylines(view.lower)],
                      name=view.name)


def press_lips(upper, lower, overlap_upper=None, overlap_lower=None):
    """Where the lower contour is drawn above the upper one, move both to their mid-line.

    Parameters
    ----------
    upper, lower : (N,2), (M,2) float
        Resampled contours, pixels (image y down, so "above" = smaller y).
    overlap_upper, overlap_lower : (N,), (M,) float, optional
        How far (pixels) the captured lips already overlap in the image at each sample's column
        (the captured lower lip's silhouette that far above the upper lip's; 0 or less: none).
        A crossing that deep is the overlap itself and is taken as drawn; a deeper one is pressed
        by what it adds, so a crossing of ``c`` px over an overlap of ``o`` px moves each contour
        ``max(c - o, 0) / 2`` toward the other. Default: no overlap (every crossing is pressed).

    Returns
    -------
    upper, lower : ndarrays of the same shapes
        Copies with the crossing stretches moved toward their mid-line.
    pressed_upper, pressed_lower : (N,), (M,) bool
        Which samples were moved.
    """
    U = np.array(upper, dtype=np.float64)
    Lw = np.array(lower, dtype=np.float64)
    out = []
    for P, Q, ov, sign in ((U, Lw, overlap_upper, 1.0), (Lw, U, overlap_lower, -1.0)):
        qy = y_at(P[:, 0], Q)  # the other contour's y at each sample's column
        cross = np.where(np.isfinite(qy), sign * (P[:, 1] - qy), 0.0)  # > 0: lower drawn above upper
        o = np.zeros(len(P)) if ov is None else np.nan_to_num(np.maximum(np.asarray(ov, float), 0.0))
        move = np.maximum(cross - o, 0.0)
        out.append((P[:, 1] - sign * 0.5 * move, move > 0))
    U[:, 1], pu = out[0]
    Lw[:, 1], pl = out[1]
    return U, Lw, pu, pl


def _as_polylines(sketch):
    if sketch is None:
        return []
    if isinstance(sketch, np.ndarray) and sketch.ndim == 2:
        return [sketch]
    if isinstance(sketch, (list, tuple)) and len(sketch) and np.ndim(sketch[0]) == 1:
        return [np.asarray(sketch, dtype=np.float64)]
    return [np.asarray(s, dtype=np.float64) for s in sketch]


def prepare_sketch(camera: Camera, upper, lower, spacing: float = 1.0, where: str = "", press: bool = True):
    """Validate, resample (1 px) and press the sketched contours.

    Parameters
    ----------
    camera : Camera
    upper, lower : (N,2) float or list of (N_i,2)
        Sketched polylines in pixels (one or several strokes per lip).
    spacing : float
        Sample spacing, pixels.
    where : str
        Names the view in messages (``" in camera 'Cam'"``); empty for one view.
    press : bool
        Press the contours where they cross (:func:`press_lips`); False returns them as drawn.

    Returns
    -------
    upper, lower : (N,2), (M,2) ndarrays
        Samples about ``spacing`` px apart, pressed where they cross (with ``press``).

    Raises
    ------
    SketchError
        Missing lip, too-short or non-finite stroke, or a stroke outside the frame.
    """
    out = []
    for name, sk in (("upper", upper), ("lower", lower)):
        lines = [np.asarray(p, dtype=np.float64).reshape(-1, 2) for p in _as_polylines(sk) if len(p)]
        if not lines:
            raise SketchError(
                f"No {name}-lip stroke{where}: draw both the upper and the lower inner-lip contour "
                f"(layers 'Upper lip' and 'Lower lip') on this frame."
            )
        for p in lines:
            if not np.isfinite(p).all():
                raise SketchError(f"The {name}-lip stroke{where} has invalid (NaN) points; erase it and draw it again.")
        # a piece under 2 px (a tap of the pen between pieces of a contour) carries no line: it is left out, and
        # only a lip drawn as nothing but such pieces is refused
        lines = [p for p in lines if len(p) >= 2 and np.linalg.norm(p.max(0) - p.min(0)) >= 2.0]
        if not lines:
            raise SketchError(f"The {name}-lip stroke{where} is too short (under 2 px); draw the whole contour.")
        samples = []
        for p in lines:
            bad = ~camera.in_frame(p, margin=-0.5)
            if bad.any():
                q = p[np.flatnonzero(bad)[0]]
                raise SketchError(
                    f"The {name}-lip stroke{where} leaves the camera frame (point at {q[0]:.0f}, {q[1]:.0f} px, "
                    f"frame {camera.width}x{camera.height}); redraw it inside the camera frame."
                )
            samples.append(resample_polyline(p, spacing))
        out.append(np.concatenate(samples))
    if not press:
        return out[0], out[1]
    U, Lw, _, _ = press_lips(out[0], out[1])
    return U, Lw


def _envelope_y(x, a, b, upper: bool):
    """(N,) image y of the envelope of segments ``a``-``b`` (E,2) at columns ``x`` (N,), NaN where none covers.

    The upper lip's envelope is its lowest silhouette (largest y, image y down), the lower lip's its highest.
    """
    if len(a) == 0:
        return np.full(len(x), np.nan)
    x0, x1 = np.minimum(a[:, 0], b[:, 0]), np.maximum(a[:, 0], b[:, 0])
    dx = b[:, 0] - a[:, 0]
    t = (x[:, None] - a[None, :, 0]) / np.where(np.abs(dx) < 1e-12, 1e-12, dx)[None]
    y = a[None, :, 1] + np.clip(t, 0.0, 1.0) * (b[:, 1] - a[:, 1])[None]
    cover = (x[:, None] >= x0[None]) & (x[:, None] <= x1[None])
    env = np.where(cover, y, -np.inf).max(axis=1) if upper else np.where(cover, y, np.inf).min(axis=1)
    return np.where(np.isfinite(env), env, np.nan)


def _lip_silhouette_y(camera, X, faces, near, x, uv=None):
    """``(yu, yl)`` (N,) each: image y of the upper lip's lowest and the lower lip's highest silhouette of ``X``
    at image columns ``x`` (pixels, y down), NaN where that lip has no silhouette.

    The silhouette edges among ``faces`` with both ends in ``near`` are split into upper and lower
    lip by their projected normals. ``uv`` (V,2): ``camera.project(X)`` if already made.
    """
    F = np.asarray(faces)
    Fn = F[faces_within(near, F)]
    none = np.full(len(x), np.nan)
    if len(Fn) == 0:
        return none, none
    edges, ef = edge_faces(Fn)
    inner = (ef >= 0).all(axis=1)
    edges, ef = edges[inner], ef[inner]
    s = facing(X, Fn, camera) > 0
    E = edges[s[ef[:, 0]] != s[ef[:, 1]]]
    if len(E) == 0:
        return none, none
    sil = np.unique(E)
    side = projected_normals(X[sil], _vertex_normals_subset(X, Fn, sil), camera)[:, 1] > 0
    up_v = np.zeros(len(X), bool)
    up_v[sil[side]] = True
    lo_v = np.zeros(len(X), bool)
    lo_v[sil[~side]] = True
    uv = camera.project(X) if uv is None else uv
    Eu, El = E[up_v[E].all(axis=1)], E[lo_v[E].all(axis=1)]
    return (_envelope_y(x, uv[Eu[:, 0]], uv[Eu[:, 1]], upper=True),
            _envelope_y(x, uv[El[:, 0]], uv[El[:, 1]], upper=False))


def _lip_overlap_px(camera, X, faces, near, x, uv=None):
    """(N,) how far (pixels) the lower lip's silhouette of ``X`` lies above the upper lip's at image columns ``x``.

    The upper lip's lowest silhouette minus the lower lip's highest one (:func:`_lip_silhouette_y`, image y
    down): positive where the lips overlap in the image, 0 where a lip has no silhouette.
    """
    yu, yl = _lip_silhouette_y(camera, X, faces, near, x, uv)
    return np.nan_to_num(yu - yl)


def _closest_to_rays(X, idx, origins, dirs):
    """For each ray, the index (into ``idx``) of the closest point and its distance."""
    P = X[idx]  # (S,3)
    rel = P[None, :, :] - origins[:, None, :]  # (N,S,3)
    along = np.einsum("nsd,nd->ns", rel, dirs)
    perp2 = np.einsum("nsd,nsd->ns", rel, rel) - along**2
    perp2[along <= 0] = np.inf  # behind the camera
    j = np.argmin(perp2, axis=1)
    return j, np.sqrt(np.maximum(perp2[np.arange(len(j)), j], 0.0))


def _on_envelope(sil, sil_uv, edges, ids, upper: bool, tol_px: float = 1.0):
    """The vertices ``ids`` on the envelope of the silhouette edges among them.

    ``sil`` (S,) sorted silhouette vertex ids and ``sil_uv`` (S,2) their projections, ``edges``
    (E,2) silhouette edges, ``ids`` a subset of ``sil`` (one lip). For the upper lip, a vertex stays
    when no silhouette edge of that lip passes more than ``tol_px`` below it at its image column
    (image y down); for the lower lip, above it.
    """
    member = np.isin(edges, ids).all(axis=1)
    E = np.searchsorted(sil, edges[member])
    if len(E) == 0:
        return ids
    a, b = sil_uv[E[:, 0]], sil_uv[E[:, 1]]
    x0, x1 = np.minimum(a[:, 0], b[:, 0]), np.maximum(a[:, 0], b[:, 0])
    p = sil_uv[np.searchsorted(sil, ids)]
    dx = b[:, 0] - a[:, 0]
    t = (p[:, 0:1] - a[None, :, 0]) / np.where(np.abs(dx) < 1e-12, 1e-12, dx)[None]
    y = a[None, :, 1] + np.clip(t, 0.0, 1.0) * (b[:, 1] - a[:, 1])[None]
    cover = (p[:, 0:1] >= x0[None]) & (p[:, 0:1] <= x1[None])
    if upper:
        env = np.where(cover, y, -np.inf).max(axis=1)
        keep = ~np.isfinite(env) | (p[:, 1] >= env - tol_px)
    else:
        env = np.where(cover, y, np.inf).min(axis=1)
        keep = ~np.isfinite(env) | (p[:, 1] <= env + tol_px)
    return ids[keep]


def _vertex_normals_subset(X, F, idx):
    """(len(idx),3) area-weighted unit normals of vertices ``idx`` (sorted unique) using triangles ``F``."""
    idx = np.asarray(idx, dtype=np.int64)
    touch = np.isin(F, idx).any(axis=1)
    Ft = F[touch]
    fn = np.cross(X[Ft[:, 1]] - X[Ft[:, 0]], X[Ft[:, 2]] - X[Ft[:, 0]])
    pos = np.searchsorted(idx, Ft)  # position of each corner in idx (valid where it is a member)
    pos = np.minimum(pos, len(idx) - 1)
    member = idx[pos] == Ft
    vn = np.zeros((len(idx), 3))
    for c in range(3):
        m = member[:, c]
        for d in range(3):
            vn[:, d] += np.bincount(pos[m, c], weights=fn[m, d], minlength=len(idx))
    return vn / np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-300)


#: A silhouette vertex projecting more than this (pixels) beyond a stroke's end is held to the contour's tangent
#: plane there instead of the end sample's ray.
END_TOL_PX = 0.5
#: A silhouette vertex projecting farther than this fraction of the sketch's width beyond a stroke's end gets no term
#: from that stroke (it is left to the smoothness terms): that far out, the stroke's tangent line at its end no
#: longer says where the lip is. A stroke stopping short of a mouth corner would otherwise pull the corner onto the
#: straight extension of its end (a lower lip that curves up to the corner, drawn to short of it: the corner is
#: pulled down and out along that straight line).
END_REACH = 0.05


def _stroke_ends(samples, gap: float = 1.5):
    """(N,2) unit outward directions at the stroke ends among resampled ``samples`` (N,2), zero elsewhere.

    Strokes are told apart by a jump of more than ``gap`` pixels between consecutive samples (the samples of
    one stroke are at most 1 px apart).
    """
    P = np.asarray(samples, dtype=np.float64)
    out = np.zeros_like(P)
    if len(P) < 2:
        return out
    jump = np.linalg.norm(np.diff(P, axis=0), axis=1) > gap
    first = np.r_[True, jump]
    last = np.r_[jump, True]
    for i in np.flatnonzero(first):
        j = min(i + 3, len(P) - 1)
        out[i] = P[i] - P[j]
    for i in np.flatnonzero(last):
        j = max(i - 3, 0)
        out[i] = P[i] - P[j]
    nrm = np.linalg.norm(out, axis=1, keepdims=True)
    return np.divide(out, nrm, out=np.zeros_like(out), where=nrm > 1e-12)


#: The upper and lower strokes' ends meet at a mouth corner when they are at most this fraction of the sketch's
#: width apart (scale-free: a few pixels at any resolution).
CORNER_TOL = 0.04
#: The weight of a mouth corner's plane, in sketch samples (each sample adds ``lambda_silh``). The corner is one
#: vertex against the many samples matched along the contour: at 1 it hardly moves (any_face --errors, corners:
#: +0.2 point); 20 recovers most of what the sketch shows without changing the wide / narrow errors' results.
CORNER_WEIGHT = 20.0


def _mouth_corners(upper, lower, out_u, out_l, tol_frac: float = CORNER_TOL):
    """The mouth corners the sketch shows: where the upper and lower strokes' ends meet.

    Parameters
    ----------
    upper, lower : (N,2), (M,2) float
        Resampled strokes, pixels.
    out_u, out_l : (N,2), (M,2) float
        :func:`_stroke_ends` of each (non-zero at the stroke ends).
    tol_frac : float
        The ends meet when they are at most this fraction of the sketch's width apart.

    Returns
    -------
    axis : (2,) float
        Unit direction along the mouth's width in the image (the sketch's principal direction, x >= 0).
    corners : list of (side, point, i_upper, i_lower)
        ``side`` -1 / +1 (the end of the mouth toward -``axis`` / +``axis``), ``point`` (2,) the corner in pixels
        (the two ends' midpoint), and the indices of the two end samples. A side whose ends do not meet (a mouth
        drawn open there, or only partly) has no entry.
    """
    P = np.concatenate([upper, lower])
    C = P - P.mean(0)
    _, _, vt = np.linalg.svd(C, full_matrices=False)
    axis = vt[0] if vt[0][0] >= 0 else -vt[0]
    width = float(np.ptp(P @ axis))
    eu = np.flatnonzero(np.linalg.norm(out_u, axis=1) > 0)
    el = np.flatnonzero(np.linalg.norm(out_l, axis=1) > 0)
    corners = []
    if len(eu) == 0 or len(el) == 0 or width <= 0:
        return axis, corners
    for side in (-1.0, 1.0):
        iu = eu[np.argmax(side * (upper[eu] @ axis))]
        il = el[np.argmax(side * (lower[el] @ axis))]
        # the ends must be the strokes' extremes on that side (not an inner end of a stroke drawn in pieces)
        if side * upper[iu] @ axis < np.max(side * (upper @ axis)) - 1.0:
            continue
        if side * lower[il] @ axis < np.max(side * (lower @ axis)) - 1.0:
            continue
        if np.linalg.norm(upper[iu] - lower[il]) <= tol_frac * width:
            corners.append((side, 0.5 * (upper[iu] + lower[il]), int(iu), int(il)))
    return axis, corners


def _contour_planes(camera, samples):
    """(N,3) unit normals of the planes through the camera centre and the sketch's tangent lines.

    A vertex on such a plane projects onto the sketch's tangent line at that sample: the plane
    constrains the distance across the contour and leaves the position along it free.
    """
    t = np.gradient(samples, axis=0) if len(samples) > 1 else np.array([[1.0, 0.0]])
    t /= np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-12)
    _, d0 = camera.rays(samples)
    _, d1 = camera.rays(samples + t)
    m = np.cross(d0, d1)
    return m / np.maximum(np.linalg.norm(m, axis=1, keepdims=True), 1e-300)


class ViewMatcher:
    """One sketch view, prepared for the iterations of the refinement.

    Parameters
    ----------
    view : SketchView
    vertices : (V,3) float
        The captured mesh, scene units.
    faces : (F,3) int
    fixed : (V,) bool
        Hidden vertices: never lip silhouettes.
    envelope : bool
        Match only the silhouette vertices on the lip's envelope (the lowest upper-lip and the
        highest lower-lip silhouette at each image column: the edge of the mouth opening the artist
        draws), not those of silhouette folds hidden behind it.
    reach_px : float, optional
        Silhouette vertices farther than this (pixels) from the sketch are ignored; default
        ``max(20, 0.15 * sketch width)``.
    where : str
        Names the view in messages.
    press : bool
        Press crossing contours (:func:`press_lips`, by what they add to the captured overlap); False:
        follow them as drawn (a crossing is one lip in front of the other).
    contact : float
        Where the two contours are drawn on one line (:func:`~facelab_addon.core.lips.contact.one_line`), the
        lips' silhouette vertices matched there are pulled together in 3D with this weight per sample (times
        ``lambda_silh``; :func:`~facelab_addon.core.lips.contact.contact_terms`); 0: off.
    projection : ((V,) float, (V,2) float), optional
        ``camera.depth(vertices)`` and ``camera.project(vertices)`` when already known (a solver that
        matches many sketches on one mesh keeps them); default computed here.

    Attributes
    ----------
    near : (V,) bool
        Free vertices in front of the camera projecting within ``reach_px`` of the sketch.
    upper, lower : (N,2), (M,2) float
        The resampled, pressed sketch.

    Notes
    -----
    With ``silhouette_rays="nearest"`` a matched silhouette vertex is pulled onto the ray of the sketch
    sample nearest to its projection; a vertex projecting beyond a stroke's end is held to the contour's
    tangent plane at the end instead (:data:`END_TOL_PX`): the stroke ends where the lips meet, it does
    not say where the mouth corner is, and the end sample's ray would slide the lips sideways. A vertex
    farther beyond the end than :data:`END_REACH` of the sketch's width gets no term from that stroke. Where the
    upper and lower strokes' ends meet (:func:`_mouth_corners`, within :data:`CORNER_TOL` of the sketch's
    width) they do say it: a capture corner lying inside the sketched one is pulled back out along the
    mouth's width (:data:`CORNER_WEIGHT`).
    """

    in_lip_region = False  # set by restrict(): the search is limited to a painted lip region's inside
    warning = ""  # what the artist should check in this view's sketch (core.lips.swapped_strokes), empty if nothing

    def __init__(self, view: SketchView, vertices, faces, fixed, reach_px=None, where: str = "",
                 envelope: bool = True, press: bool = True, contact: float = 0.0, projection=None):
        self.envelope = bool(envelope)
        self.contact = float(contact)
        cam = view.camera
        if not isinstance(cam, Camera):
            raise CameraError("No camera given: set the scene camera (the one the backplate belongs to).")
        self.camera, self.where = cam, where
        up_raw, lo_raw = prepare_sketch(cam, view.upper, view.lower, where=where, press=False)
        sketch = np.concatenate([up_raw, lo_raw])
        V0, F = vertices, faces
        n = len(V0)
        depth, uv = (cam.depth(V0), cam.project(V0)) if projection is None else projection
        width = float(np.ptp(sketch[:, 0]))
        self.width = width
        if reach_px is None:
            reach_px = max(20.0, 0.15 * width)
        # the mouth area in this view: the sketch's box grown by a quarter of its width (at least reach_px)
        margin = max(reach_px, 40.0, 0.25 * width)
        lo, hi = sketch.min(0) - margin, sketch.max(0) + margin
        box = depth > 0
        for k in (0, 1):  # inside the box, per image axis
            box &= np.isfinite(uv[:, k]) & (uv[:, k] >= lo[k]) & (uv[:, k] <= hi[k])
        cand = box & ~fixed
        near = np.zeros(n, bool)
        if cand.any():
            from scipy.spatial import cKDTree

            d_sk, _ = cKDTree(sketch).query(uv[cand], distance_upper_bound=reach_px)
            near[np.flatnonzero(cand)[np.isfinite(d_sk)]] = True
        if not near.any():
            require_camera_outside(cam, V0, F, fixed, depth, where)
            if (depth[~fixed] <= 0).mean() > 0.5:
                raise CameraError(
                    f"The face is behind the camera{where}; select the camera that looks at the face (the one the "
                    "backplate belongs to)."
                )
            raise SketchError(
                f"No part of the face projects near the lip strokes{where}; draw them over the mouth in this "
                "camera's view (or pick the camera they were drawn in)."
            )
        fs = facing(V0, F[faces_within(cand, F)], cam)  # judged on the whole mouth area, not only the lip edges
        if fs.size and (fs > 0).mean() < 0.3:
            raise CameraError(
                f"The camera{where} sees the face from behind (the mouth area faces away from it); use a camera "
                "in front of the face."
            )
        self.near = near
        # a crossing drawn where the captured lips already overlap in this view is, up to that overlap, the
        # overlap itself: only what it adds is pressed
        # overlaps under 2.5 % of the sketch's width (about 1 mm; where the silhouettes meet near the corners)
        # count as none, from 5 % on in full, so the pressing does not hinge on near-ties of the silhouettes
        tol = 0.025 * width
        lo_x = max(up_raw[:, 0].min(), lo_raw[:, 0].min())
        hi_x = min(up_raw[:, 0].max(), lo_raw[:, 0].max())
        if hi_x > lo_x:
            pad = 0.1 * (hi_x - lo_x)  # the corners, where the two strokes meet, say nothing of their order
            cols = np.linspace(lo_x + pad, hi_x - pad, 64)
            self.warning = check_swapped_strokes(up_raw, lo_raw, *_lip_silhouette_y(cam, V0, F, near, cols, uv), cols,
                                                 where)

        def overlap(x):
            o = _lip_overlap_px(cam, V0, F, near, x, uv)
            return o * np.clip(o / tol - 1.0, 0.0, 1.0)

        if press:
            self.upper, self.lower, _, _ = press_lips(up_raw, lo_raw, overlap(up_raw[:, 0]), overlap(lo_raw[:, 0]))
        else:
            self.upper, self.lower = up_raw, lo_raw
        self.sketch = np.concatenate([self.upper, self.lower])
        # (N,) the lower sample each upper sample shares a line with (sealed lips), -1 elsewhere
        self.partner = one_line(self.upper, self.lower, width) if self.contact > 0 else np.full(len(self.upper), -1)
        self.o_u, self.d_u = cam.rays(self.upper)
        self.o_l, self.d_l = cam.rays(self.lower)
        self.n_u = _contour_planes(cam, self.upper)
        self.n_l = _contour_planes(cam, self.lower)
        self.out_u = _stroke_ends(self.upper)
        self.out_l = _stroke_ends(self.lower)
        self.axis, self.corners = _mouth_corners(self.upper, self.lower, self.out_u, self.out_l)
        if self.corners:
            # the plane through the camera centre and the image line through each corner across the mouth's width
            pts = np.array([c[1] for c in self.corners])
            _, d0 = cam.rays(pts)
            _, d1 = cam.rays(pts + np.array([-self.axis[1], self.axis[0]]))
            m = np.cross(d0, d1)
            self.corner_planes = m / np.maximum(np.linalg.norm(m, axis=1, keepdims=True), 1e-300)

    def restrict(self, faces, region_vertices, in_lip_region: bool = False):
        """Limit the silhouette search to triangles of ``region_vertices`` (V,) bool near the sketch.

        ``in_lip_region``: the region is a painted lip region's inside (a failed search then names it).
        """
        self.in_lip_region = bool(in_lip_region)
        F = np.asarray(faces)
        rf = np.flatnonzero(faces_within(region_vertices, F))
        self.Fr = F[rf]
        edges, ef = edge_faces(self.Fr)
        inner = (ef >= 0).all(axis=1)
        edges, ef = edges[inner], ef[inner]
        keep = self.near[edges].all(axis=1)
        self.edges, self.ef = edges[keep], ef[keep]

    def correspondences(self, X, lambda_silh: float, silhouette_rays: str = "nearest", sample_weights=None):
        """Silhouette vertices of ``X`` matched to the sketch rays.

        ``sample_weights`` (N+M,) float, optional: a weight per sketch sample (upper samples first),
        multiplying ``lambda_silh`` for the pixels of that sample (0: the sample adds no term).

        Returns
        -------
        constraints : list of PointConstraints
            Point-to-ray terms of ``E_silh`` (weight ``lambda_silh`` per sketch pixel).
        distance_px : (N+M,) float
            Distance of every sketch ray to its matched vertex, in pixels at the vertex's depth.
        matched : dict
            ``{"upper": ids, "lower": ids}`` matched vertex indices.
        """
        cam, where = self.camera, self.where
        s = facing(X, self.Fr, cam) > 0
        sil_edges = self.edges[s[self.ef[:, 0]] != s[self.ef[:, 1]]]
        sil = np.unique(sil_edges)
        if len(sil) == 0:
            raise SketchError(
                f"The mesh has no lip silhouette near the strokes{where}; check that the strokes follow the inner "
                "lips and that the camera looks at the mouth."
            )
        normals = _vertex_normals_subset(X, self.Fr, sil)
        sil_uv = cam.project(X[sil]) if self.envelope else None
        side = projected_normals(X[sil], normals, cam)[:, 1] > 0  # True: upper lip (image y down)
        cons, dist_px, matched, per_sample = [], [], {}, {}
        nu = len(self.upper)
        sw = None if sample_weights is None else np.asarray(sample_weights, dtype=np.float64)
        for name, lipmask, samples, o, d, pn, out in (
                ("upper", side, self.upper, self.o_u, self.d_u, self.n_u, self.out_u),
                ("lower", ~side, self.lower, self.o_l, self.d_l, self.n_l, self.out_l)):
            ws = None if sw is None else (sw[:nu] if name == "upper" else sw[nu:])
            ids = sil[lipmask]
            if self.envelope and len(ids):
                ids = _on_envelope(sil, sil_uv, sil_edges, ids, upper=(name == "upper"))
            if len(ids) == 0:
                raise SketchError(
                    f"No {name}-lip silhouette found near the {name}-lip stroke{where}; draw the contours over the "
                    "inner lips in camera view, upper above lower (a lip that is a separate mesh piece is held "
                    "unless it is the largest piece: pass the hidden parts as 'fixed' / the FL_fixed group)."
                    + (" Only the inside of the lip region (FL_lips) is searched: check that it covers both lips "
                       "under the strokes, from corner to corner (run Auto Regions again or paint FL_lips), or "
                       "refine without it (turn off Only FL_lips)." if self.in_lip_region else "")
                )
            j, dist = _closest_to_rays(X, ids, o, d)
            vid = ids[j]
            per_sample[name] = vid
            matched[name] = np.unique(vid)
            dist_px.append(dist * cam.K[0, 0] / np.maximum(cam.depth(X[vid]), 1e-12))
            if ws is not None:
                keep = ws > 0
                if not keep.any():
                    continue
                vid, o, d, ws = vid[keep], o[keep], d[keep], ws[keep]
            if silhouette_rays in ("nearest", "normal"):
                uv, inv = np.unique(vid, return_inverse=True)
                cnt = np.bincount(inv.ravel(), weights=None if ws is None else ws, minlength=len(uv))
                pv = cam.project(X[uv])
                k = np.argmin(((pv[:, None, :] - samples[None]) ** 2).sum(-1), axis=1)
                if silhouette_rays == "normal":
                    m = pn[k]
                    cons.append(PointConstraints(uv, np.ones((len(uv), 1)), np.broadcast_to(cam.center, (len(uv), 3)),
                                                 m[:, :, None] * m[:, None, :], lambda_silh * cnt))
                else:
                    # a vertex projecting beyond the end of a stroke (outward along the stroke's end direction)
                    # is held to the contour's tangent plane there, not pulled onto the end sample's ray: the
                    # sketch ends where the lips meet, it does not say where the mouth corner is
                    ahead = np.einsum("ij,ij->i", pv - samples[k], out[k])
                    beyond = ahead > END_TOL_PX
                    keep = ~beyond
                    # far beyond the end the stroke's tangent line says nothing: no term from this stroke
                    beyond &= ahead <= END_REACH * self.width
                    if keep.any():
                        oo, dd = cam.rays(samples[k[keep]])
                        cons.append(PointConstraints.rays(uv[keep], oo, dd, strength=lambda_silh * cnt[keep]))
                    if beyond.any():
                        m = pn[k[beyond]]
                        nb = int(beyond.sum())
                        cons.append(PointConstraints(uv[beyond], np.ones((nb, 1)), np.broadcast_to(cam.center, (nb, 3)),
                                                     m[:, :, None] * m[:, None, :], lambda_silh * cnt[beyond]))
            else:
                cons.append(PointConstraints.rays(vid, o, d, strength=lambda_silh * (1.0 if ws is None else ws)))
        if self.corners and silhouette_rays == "nearest" and len(matched) == 2:
            cons += self._corner_constraints(X, matched, lambda_silh, sw, nu)
        if self.contact > 0 and (self.partner >= 0).any():
            # sealed lips drawn on one line: the lips' silhouettes there meet in 3D, not only on the same rays
            c = contact_terms(per_sample["upper"], per_sample["lower"], self.partner, self.contact * lambda_silh,
                              None if sw is None else sw[:nu])
            if c is not None:
                cons.append(c)
        return cons, np.concatenate(dist_px), matched

    def _corner_constraints(self, X, matched, lambda_silh, sw, nu):
        """Each mouth corner the sketch shows (:func:`_mouth_corners`) pulls the capture's corner back out to it.

        The capture's corner on a side is the lateral extreme (along the sketch's width, in the image) of the
        matched silhouette vertices of both lips: where the upper and lower silhouettes meet. The nearest-sample
        matching pulls across the contour only, so a corner pulled in along the mouth is never pulled back out.
        When the capture's corner projects more than :data:`END_TOL_PX` inside the sketched one, it is held to
        the plane through the camera centre and the image line through the sketched corner across the mouth's
        width (along the width only: the stroke ends' midpoint does not say where each lip's silhouette ends
        across it). A corner already as far out as the sketch's gets nothing (the tangent plane at the stroke
        end holds it, as before). Weight :data:`CORNER_WEIGHT` samples (times the smaller sample weight of the two
        ends).

        Returns
        -------
        list of PointConstraints
            Empty, or one term of one row per corner pulled.
        """
        cand = np.union1d(matched["upper"], matched["lower"])
        if len(cand) == 0:
            return []
        along = self.camera.project(X[cand]) @ self.axis
        ids, ws, rows = [], [], []
        for k, (side, pt, iu, il) in enumerate(self.corners):
            j = np.argmax(side * along)
            if side * (along[j] - pt @ self.axis) > -END_TOL_PX:
                continue  # the capture's corner is already as far out as the sketch's: the contour holds it
            w = CORNER_WEIGHT
            if sw is not None:
                w *= min(sw[iu], sw[nu + il])
            if w > 0:
                ids.append(cand[j])
                ws.append(w)
                rows.append(k)
        if not ids:
            return []
        m = self.corner_planes[rows]
        c = len(ids)
        return [PointConstraints(np.asarray(ids), np.ones((c, 1)), np.broadcast_to(self.camera.center, (c, 3)),
                                 m[:, :, None] * m[:, None, :], lambda_silh * np.asarray(ws))]
