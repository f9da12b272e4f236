"""Tracked contours drawn in Blender -> ``core.solve.contour_loops.TrackedCurve`` (Bhat et al. 2013, §4.2 inputs).

Inner-lip and eyelid contours come from what artists already draw:

* **Mask splines** of the Movie Clip editor (``bpy.data.masks``), the
  rotoscoper's tool. One mask layer per curve; the layer name says which
  curve it is (see :func:`curve_name`). A layer's splines are Bezier curves in
  *mask space* and are sampled into a polyline; animation with mask shape
  keys (the Clip editor's "Insert Shape Key") is read from the evaluated mask
  on each frame. Coordinates (``BKE_mask_coord_from_movieclip`` in Blender):
  mask space is the clip frame normalised to ``[0,1]`` along its longer side,
  the shorter side scaled to keep pixels square around the centre, y up.
* **Grease Pencil objects** and the **scene annotation**, drawn in a camera's
  view; read with ``blender/strokes.py`` (its transforms and "View"/3D
  annotation placement rules) and projected through that view's camera.
  ``strokes.read_lip_strokes`` only knows the two lip layers; this module
  wraps its helpers to read any curve layer.

Curve names (``core.solve.contour_loops``): ``mouth_upper``, ``mouth_lower``,
``eyelid_left_upper``, ``eyelid_left_lower``, ``eyelid_right_upper``,
``eyelid_right_lower``. Layer names are matched by words, so "Upper lip",
"mouth_upper", "Lip.Upper", "Eyelid L upper", "left upper lid" and
"eyelid_left_upper" all work; left/right are the *actor's* sides (as in
ICT's ``eyeBlink_L``).

Frames: a Grease Pencil or annotation contour is used on the frames that
have a drawing keyframe on its layer (not held to later frames, unless
``hold=True``); a mask contour on every frame of the mask's frame range
(``mask.frame_start``..``frame_end``) unless its layer is hidden.

Limitation: Blender 5.0 does not expose a mask point's parenting offset
(``MaskParent.parent_orig``) to Python, so mask points parented to a track
cannot be placed; they raise a ``SketchError`` that says how to proceed.
"""

from __future__ import annotations

import re

import numpy as np

from ..core.capture.camera import Camera
from ..core.errors import SketchError
from . import compat
from . import strokes as _st
from .camera import evaluated_depsgraph
from .tracking import clip_size

__all__ = [
    "CURVE_NAMES",
    "curve_name",
    "mask_to_pixels",
    "bezier_polyline",
    "mask_polylines",
    "sketch_polylines",
    "annotation_polylines",
    "chain_polylines",
    "read_curves",
]

CURVE_NAMES = (
    "mouth_upper",
    "mouth_lower",
    "eyelid_left_upper",
    "eyelid_left_lower",
    "eyelid_right_upper",
    "eyelid_right_lower",
)

_MOUTH = {"mouth", "lip", "lips", "lipline"}
_EYE = {"eyelid", "eyelids", "lid", "lids", "eye"}
_LEFT = {"left", "l", "lft"}
_RIGHT = {"right", "r", "rgt"}
_UPPER = {"upper", "up", "top", "hi", "high"}
_LOWER = {"lower", "low", "bottom", "bot", "down"}


def _words(name: str) -> list:
    s = re.sub(r"([a-z])([A-Z])", r"\1 \2", name)  # camelCase
    return [w for w in re.split(r"[^a-z0-9]+", s.lower()) if w]


def curve_name(layer_name: str):
    """The FaceLab curve a layer name stands for, or ``None``.

    >>> curve_name("Upper lip"), curve_name("Eyelid.L upper"), curve_name("lid_R_bottom")
    ('mouth_upper', 'eyelid_left_upper', 'eyelid_right_lower')
    """
    w = set(_words(layer_name))
    up, lo = bool(w & _UPPER), bool(w & _LOWER)
    if up == lo:
        return None
    ul = "upper" if up else "lower"
    if w & _EYE and not w & _MOUTH:
        left, right = bool(w & _LEFT), bool(w & _RIGHT)
        if left == right:
            return None
        return f"eyelid_{'left' if left else 'right'}_{ul}"
    if w & _MOUTH and not w & _EYE:
        return f"mouth_{ul}"
    return None


# --------------------------------------------------------------------------- masks
def _frame_size(clip) -> tuple[int, int, float]:
    W, H = clip_size(clip)
    asp = clip.display_aspect
    aspy = float(asp[1]) / float(asp[0]) / float(clip.tracking.camera.pixel_aspect)
    return W, H, H * aspy


def mask_to_pixels(co, clip) -> np.ndarray:
    """Mask-space points ``(n,2)`` of a mask drawn over ``clip`` -> FaceLab pixels ``(n,2)``.

    The inverse of Blender's ``BKE_mask_coord_from_movieclip``: the frame is
    ``(W, H * aspect)`` with ``aspect`` the clip's display aspect over the
    tracking camera's pixel aspect; the shorter side is unscaled around 0.5;
    then ``x = u W``, ``y = (1 - v) H``.
    """
    W, H, Ha = _frame_size(clip)
    c = np.array(co, dtype=np.float64).reshape(-1, 2)
    if W < Ha:
        c[:, 0] = (c[:, 0] - 0.5) * (Ha / W) + 0.5
    elif W > Ha:
        c[:, 1] = (c[:, 1] - 0.5) * (W / Ha) + 0.5
    return np.c_[c[:, 0] * W, (1.0 - c[:, 1]) * H]


def bezier_polyline(co, left, right, cyclic: bool, resolution: int = 8) -> np.ndarray:
    """Sample a 2D Bezier spline (Blender's handle layout) into a polyline.

    Parameters
    ----------
    co, left, right : (n,2) array_like
        Control points and their left/right handles.
    cyclic : bool
        Close the spline (last point back to the first); the closing point is
        repeated at the end of the polyline.
    resolution : int
        Samples per segment (the segment's end point is the next one's start).

    Returns
    -------
    (k,2) ndarray
        ``resolution`` samples per segment plus the last point.
    """
    co, left, right = (np.asarray(a, dtype=np.float64).reshape(-1, 2) for a in (co, left, right))
    n = len(co)
    if n < 2:
        return co.copy()
    i0 = np.arange(n if cyclic else n - 1)
    i1 = (i0 + 1) % n
    t = np.arange(resolution) / resolution
    b = np.stack([(1 - t) ** 3, 3 * (1 - t) ** 2 * t, 3 * (1 - t) * t**2, t**3], 1)  # (r,4)
    P = np.stack([co[i0], right[i0], left[i1], co[i1]], 1)  # (s,4,2)
    pts = np.einsum("rk,skd->srd", b, P).reshape(-1, 2)
    return np.vstack([pts, co[i1[-1]]])


def _check_parents(mask, layer, spline):
    for p in spline.points:
        par = p.parent
        if par.id is not None and (par.sub_parent or par.parent):
            raise SketchError(
                f"Mask '{mask.name}' layer '{layer.name}' has points parented to track '{par.sub_parent}'; Blender does "
                "not give add-ons the parenting offset, so FaceLab cannot place them. Clear the parent (Mask > "
                "Parent > Clear) and animate the spline with mask shape keys (I in the Clip editor), or draw the "
                "contour with Grease Pencil / annotation strokes instead."
            )


def mask_polylines(mask, clip, *, depsgraph=None, resolution: int = 8) -> dict:
    """The curve polylines of a mask on the depsgraph's (the current) frame.

    Parameters
    ----------
    mask : bpy.types.Mask
    clip : bpy.types.MovieClip
        The clip the mask was drawn over (gives the pixel frame).
    depsgraph : bpy.types.Depsgraph, optional
        The evaluated mask (shape-key animation applied) is read from it.
    resolution : int
        Samples per Bezier segment.

    Returns
    -------
    dict
        ``{curve_name: [(k,2) pixel polylines, one per spline]}`` for the
        visible layers whose names map to a curve; other layers are ignored.

    Raises
    ------
    SketchError
        A curve layer has points parented to a track (see module docstring).
    """
    if depsgraph is not None:
        mask_ev = mask.evaluated_get(depsgraph)
    else:
        mask_ev = mask
    out = {}
    for lay_o, lay in zip(mask.layers, mask_ev.layers):
        name = curve_name(lay_o.name)
        if name is None or lay_o.hide:
            continue
        for sp_o, sp in zip(lay_o.splines, lay.splines):
            n = len(sp.points)
            if n == 0:
                continue
            _check_parents(mask, lay_o, sp_o)
            arr = {}
            for attr in ("co", "handle_left", "handle_right"):
                a = np.empty(2 * n, dtype=np.float32)
                sp.points.foreach_get(attr, a)
                arr[attr] = a.reshape(n, 2)
            poly = bezier_polyline(arr["co"], arr["handle_left"], arr["handle_right"], sp.use_cyclic, resolution)
            out.setdefault(name, []).append(mask_to_pixels(poly, clip))
    return out


# --------------------------------------------------------------------------- grease pencil / annotation
def _layer_frame(frames, frame: int, hold: bool, number):
    if hold:
        best = None
        for f in frames:
            if number(f) <= frame and (best is None or number(f) > number(best)):
                best = f
        return best
    return next((f for f in frames if number(f) == frame), None)


def sketch_polylines(gp_obj, camera: Camera, frame: int, *, depsgraph, hold: bool = False) -> dict:
    """Curve polylines of a Grease Pencil (v3) object drawn in ``camera``'s view.

    Parameters
    ----------
    gp_obj : bpy.types.Object
        A ``GREASEPENCIL`` object; layers named after curves (``curve_name``).
    camera : Camera
        The view's camera; stroke points (world, via the layer transform) are
        projected through it.
    frame : int
        Scene frame.
    depsgraph : bpy.types.Depsgraph
        For the object's and layer parents' evaluated transforms (set the
        scene frame first if they are animated).
    hold : bool
        Use the latest keyframe <= ``frame`` (Blender's display rule) instead
        of a keyframe on exactly ``frame``.

    Returns
    -------
    dict
        ``{curve_name: [(n,2) pixel polylines]}``; layers without a drawing
        on this frame are absent.

    Raises
    ------
    SketchError
        Strokes at or behind the camera, or not a Grease Pencil object.
    """
    if gp_obj is None or gp_obj.type != "GREASEPENCIL":
        raise SketchError(
            f"'{getattr(gp_obj, 'name', None)}' is not a Grease Pencil object; set the view's sketch to the Grease "
            "Pencil object the contours are drawn on (layers named e.g. 'Upper lip', 'Eyelid L upper')."
        )
    out = {}
    for layer in gp_obj.data.layers:
        name = curve_name(layer.name)
        if name is None or layer.hide:
            continue
        fr = _layer_frame(layer.frames, int(frame), hold, lambda f: f.frame_number)
        if fr is None or fr.drawing is None or fr.drawing.type != "DRAWING":
            continue
        M = _st.layer_to_world(layer, gp_obj, depsgraph)
        world = [_st.transform_points(M, P) for P in _st.drawing_polylines(fr.drawing)]
        polys = _st.project_world(camera, world, f"Layer '{layer.name}' of '{gp_obj.name}' on frame {frame}")
        if polys:
            out.setdefault(name, []).extend(polys)
    return out


def annotation_polylines(annotation, camera: Camera, frame: int, *, hold: bool = False) -> dict:
    """Curve polylines of an annotation (``scene.annotation``) drawn in ``camera``'s view.

    "View"-placed strokes (camera-frame percent) and 3D strokes are told apart
    as ``strokes.read_lip_strokes`` does. Returns ``{curve_name: [(n,2)]}``.
    """
    out = {}
    if annotation is None:
        return out
    for layer in annotation.layers:
        name = curve_name(layer.info)
        if name is None or getattr(layer, "hide", False):
            continue
        fr = _layer_frame(layer.frames, int(frame), hold, lambda f: f.frame_number)
        if fr is None:
            continue
        polys = _st.annotation_frame_pixels(fr, camera, f"Annotation layer '{layer.info}' on frame {frame}")
        if polys:
            out.setdefault(name, []).extend(polys)
    return out


def _keyed_frames(layers, name_of):
    fr = set()
    for layer in layers:
        if curve_name(name_of(layer)) is not None:
            fr.update(int(f.frame_number) for f in layer.frames)
    return fr


def chain_polylines(polys) -> np.ndarray:
    """Join several strokes of one curve into one polyline.

    Strokes are taken in drawing order; each is reversed when its end is
    closer to the chain's end than its start is, so strokes drawn in either
    direction continue the curve.
    """
    polys = [np.asarray(p, dtype=np.float64).reshape(-1, 2) for p in polys if len(p)]
    if not polys:
        return np.zeros((0, 2))
    chain = polys[0]
    for p in polys[1:]:
        if len(chain) == 1 and np.linalg.norm(p[-1] - chain[0]) < np.linalg.norm(p[0] - chain[0]):
            p = p[::-1]
        elif np.linalg.norm(p[-1] - chain[-1]) < np.linalg.norm(p[0] - chain[-1]):
            p = p[::-1]
        chain = np.vstack([chain, p])
    return chain


def read_curves(scene, views, cameras, frames, *, annotation_view: int | None = None, hold: bool = False,
                resolution: int = 8, min_points: int = 2):
    """Tracked contours of every view over the scene frames ``frames``.

    Parameters
    ----------
    scene : bpy.types.Scene
    views : sequence of ``tracking.View``
        Each may carry ``mask`` (a Mask over its clip) and ``sketch`` (a Grease
        Pencil object drawn through its camera).
    cameras : list of Camera
        The views' cameras (``tracking.read_views``), same order.
    frames : (T,) array_like of int
    annotation_view : int, optional
        Index of the view whose camera the scene annotation was drawn
        through; ``None`` ignores the annotation.
    hold : bool
        See :func:`sketch_polylines`.
    resolution : int
        Samples per mask Bezier segment.
    min_points : int
        Curves with fewer points are dropped.

    Returns
    -------
    curves : list (T) of list of TrackedCurve
        Per frame, one curve per (view, curve name) found; several strokes of
        one curve are chained (:func:`chain_polylines`).
    stats : dict
        ``{'frames_with_curves': int, 'by_name': {name: count}}``.
    """
    from ..core.solve.contour_loops import TrackedCurve

    frames = [int(f) for f in np.asarray(frames).reshape(-1)]
    fset = set(frames)
    # which frames need the scene evaluated there
    need = set()
    for v in views:
        if getattr(v, "sketch", None) is not None and v.sketch.type == "GREASEPENCIL":
            need |= fset if hold else (_keyed_frames(v.sketch.data.layers, lambda lay: lay.name) & fset)
        m = getattr(v, "mask", None)
        if m is not None:
            need |= {f for f in frames if m.frame_start <= f <= m.frame_end}
    ann = compat.scene_annotation(scene) if annotation_view is not None else None
    if ann is not None:
        need |= fset if hold else (_keyed_frames(ann.layers, lambda lay: lay.info) & fset)

    out = [[] for _ in frames]
    by_name: dict = {}
    keep = scene.frame_current
    try:
        for i, f in enumerate(frames):
            if f not in need:
                continue
            if scene.frame_current != f:
                scene.frame_set(f)
            dg = evaluated_depsgraph(scene)
            for c, v in enumerate(views):
                found: dict = {}
                m = getattr(v, "mask", None)
                if m is not None and m.frame_start <= f <= m.frame_end:
                    for k, p in mask_polylines(m, v.clip, depsgraph=dg, resolution=resolution).items():
                        found.setdefault(k, []).extend(p)
                sk = getattr(v, "sketch", None)
                if sk is not None:
                    for k, p in sketch_polylines(sk, cameras[c], f, depsgraph=dg, hold=hold).items():
                        found.setdefault(k, []).extend(p)
                if ann is not None and c == annotation_view:
                    for k, p in annotation_polylines(ann, cameras[c], f, hold=hold).items():
                        found.setdefault(k, []).extend(p)
                for k in CURVE_NAMES:
                    if k in found:
                        px = chain_polylines(found[k])
                        if len(px) >= min_points:
                            out[i].append(TrackedCurve(name=k, camera=c, pixels=px))
                            by_name[k] = by_name.get(k, 0) + 1
    finally:
        if scene.frame_current != keep:
            scene.frame_set(keep)
    return out, {"frames_with_curves": sum(1 for o in out if o), "by_name": by_name}
