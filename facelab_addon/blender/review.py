"""Review of FaceLab's corrections in Blender: capture vs corrected, a heat map of the correction,
sketches of neighbouring frames, the frames to look at next.

* :func:`show_capture` / :func:`show_corrected` mute and restore every correction FaceLab made on a
  face (its recorded corrective shape keys, :func:`~facelab_addon.blender.ownership.owned_keys`, and
  its correction modifiers), keeping the artist's own mutes exactly: they are saved on the object
  (:data:`~facelab_addon.names.REVIEW_SAVED_PROP`, JSON) while the capture is shown.
* :func:`correction_magnitude` is the per-vertex distance (mm of world space) between the corrected
  and the captured evaluated mesh on the current frame; :func:`write_heatmap` stores it as the point
  color attribute :data:`~facelab_addon.names.CORRECTION_ATTR` (Solid mode > Attribute color).
* :func:`set_onion_skin` shows the sketch's strokes of neighbouring keyframes faintly.
* :func:`next_marker_frame` and :func:`most_extrapolated_frame` pick the next frame to look at.
"""

from __future__ import annotations

import contextlib
import json

import numpy as np

from ..names import CORRECTION_ATTR, CORRECTION_RANGE_PROP, EXTRAPOLATION_PROP, PREFIX, REVIEW_SAVED_PROP
from .mesh import evaluated_vertices
from .ownership import owned_keys
from .shapekeys import find_fcurve

__all__ = [
    "CAPTURE_MODIFIER_PREFIX",
    "correction_keys",
    "correction_modifiers",
    "showing_capture",
    "show_capture",
    "show_corrected",
    "corrections_as_set",
    "correction_magnitude",
    "heat_colors",
    "write_heatmap",
    "set_onion_skin",
    "next_marker_frame",
    "keyed_extrapolation",
    "most_extrapolated_frame",
]

#: Modifiers FaceLab adds that hold the capture, not a correction (``FL Capture (PC2)``): never toggled.
CAPTURE_MODIFIER_PREFIX = "FL Capture"


def correction_keys(obj) -> list:
    """Names of the corrective shape keys FaceLab recorded on ``obj`` (``FL_*``), in key order."""
    own = set(owned_keys(obj, PREFIX))
    key = obj.data.shape_keys
    return [kb.name for kb in key.key_blocks if kb.name in own] if key is not None else []


def correction_modifiers(obj) -> list:
    """Names of ``obj``'s modifiers FaceLab added for a correction (``FL ...``/``FL_...``, not the capture)."""
    return [m.name for m in obj.modifiers
            if m.name.startswith(("FL ", PREFIX)) and not m.name.startswith(CAPTURE_MODIFIER_PREFIX)]


def showing_capture(obj) -> bool:
    """Whether :func:`show_capture` is in effect on ``obj`` (its corrections are muted by Review)."""
    return REVIEW_SAVED_PROP in obj


def _state(obj) -> dict:
    kbs = obj.data.shape_keys.key_blocks if obj.data.shape_keys is not None else {}
    return {"keys": {n: bool(kbs[n].mute) for n in correction_keys(obj)},
            "modifiers": {n: [bool(obj.modifiers[n].show_viewport), bool(obj.modifiers[n].show_render)]
                          for n in correction_modifiers(obj)}}


def _apply(obj, state: dict, *, off: bool) -> None:
    """``off``: mute every listed key and modifier; else put back the saved flags of the ones still there."""
    kbs = obj.data.shape_keys.key_blocks if obj.data.shape_keys is not None else {}
    for n, mute in state["keys"].items():
        if n in kbs:
            kbs[n].mute = True if off else mute
    for n, (view, render) in state["modifiers"].items():
        m = obj.modifiers.get(n)
        if m is not None:
            m.show_viewport, m.show_render = (False, False) if off else (view, render)
    obj.data.update()


def show_capture(obj) -> tuple:
    """Mute every FaceLab correction of ``obj`` (the capture as it came in), saving the artist's mutes.

    Returns
    -------
    (int, int)
        Corrective keys and modifiers muted (already showing the capture: the ones muted then).
    """
    if showing_capture(obj):
        st = json.loads(obj[REVIEW_SAVED_PROP])
    else:
        st = _state(obj)
        obj[REVIEW_SAVED_PROP] = json.dumps(st)
    _apply(obj, st, off=True)
    return len(st["keys"]), len(st["modifiers"])


def show_corrected(obj) -> tuple:
    """Undo :func:`show_capture`: every correction's mute flags exactly as the artist had them.

    Returns
    -------
    (int, int)
        Corrective keys and modifiers restored (0, 0 when the capture was not shown).
    """
    if not showing_capture(obj):
        return 0, 0
    st = json.loads(obj[REVIEW_SAVED_PROP])
    _apply(obj, st, off=False)
    del obj[REVIEW_SAVED_PROP]
    return len(st["keys"]), len(st["modifiers"])


@contextlib.contextmanager
def corrections_as_set(obj):
    """Meanwhile every correction's mute flags are the artist's (Review's *Show Capture* lifted); afterwards
    as before. Reads of the corrected face (Propagate's training frames) see the artist's work, never the
    capture Review shows."""
    saved = json.loads(obj[REVIEW_SAVED_PROP]) if showing_capture(obj) else None
    if saved is not None:
        _apply(obj, saved, off=False)
    try:
        yield
    finally:
        if saved is not None:
            _apply(obj, saved, off=True)


@contextlib.contextmanager
def _capture_shown(obj):
    """Meanwhile the corrections are muted; afterwards every flag is as before."""
    st = _state(obj)
    _apply(obj, st, off=True)
    try:
        yield
    finally:
        _apply(obj, st, off=False)


def correction_magnitude(obj, depsgraph, *, metres_per_unit: float = 1.0) -> np.ndarray:
    """(V,) float64 length of the correction of every vertex on the current frame, in millimetres.

    The corrected mesh is what the artist would see with FaceLab's corrections on (their saved state
    while Review shows the capture); the captured mesh has all of them muted. Both are evaluated in
    world space (object scale and parents count), then scaled by ``metres_per_unit`` (the scene's
    unit scale). A correction cache whose file is missing is refused (``CacheFileError``): the map would
    show no correction where there is one.
    """
    from .correction_files import require_correction_caches

    require_correction_caches(obj, "The correction heat map")
    saved = json.loads(obj[REVIEW_SAVED_PROP]) if showing_capture(obj) else None
    if saved is not None:
        _apply(obj, saved, off=False)
    try:
        depsgraph.update()
        corrected = evaluated_vertices(obj, depsgraph, world=True)
        with _capture_shown(obj):
            depsgraph.update()
            captured = evaluated_vertices(obj, depsgraph, world=True)
    finally:
        if saved is not None:
            _apply(obj, saved, off=True)
        depsgraph.update()
    return np.linalg.norm(corrected - captured, axis=1) * float(metres_per_unit) * 1e3


#: Heat-map colour stops (linear RGB): no correction is light grey, the largest is red.
HEAT_STOPS = np.array([[0.0, 0.80, 0.80, 0.80], [0.35, 1.0, 0.85, 0.25], [0.7, 1.0, 0.35, 0.0],
                       [1.0, 0.75, 0.0, 0.0]])


def heat_colors(values, vmax: float) -> np.ndarray:
    """(V,4) float32 RGBA of ``values`` (V,) on the scale 0..``vmax`` (values above ``vmax`` are red)."""
    t = np.clip(np.asarray(values, np.float64) / max(float(vmax), 1e-12), 0.0, 1.0)
    rgb = np.stack([np.interp(t, HEAT_STOPS[:, 0], HEAT_STOPS[:, c]) for c in (1, 2, 3)], axis=1)
    return np.c_[rgb, np.ones(len(t))].astype(np.float32)


def write_heatmap(obj, magnitude_mm, vmax_mm: float, frame: int):
    """Store ``magnitude_mm`` (V,) as the point color attribute :data:`CORRECTION_ATTR` (made active for the
    viewport) and the legend range on the mesh (:data:`CORRECTION_RANGE_PROP`). Returns the attribute."""
    me = obj.data
    attr = me.color_attributes.get(CORRECTION_ATTR)
    if attr is not None and (attr.domain != "POINT" or attr.data_type != "FLOAT_COLOR"):
        me.color_attributes.remove(attr)
        attr = None
    if attr is None:
        attr = me.color_attributes.new(CORRECTION_ATTR, "FLOAT_COLOR", "POINT")
    attr.data.foreach_set("color", heat_colors(magnitude_mm, vmax_mm).ravel())
    me.color_attributes.active_color = attr
    me[CORRECTION_RANGE_PROP] = [0.0, float(vmax_mm), float(frame)]
    me.update()
    return attr


def set_onion_skin(gp_obj, on: bool, before: int = 2, after: int = 2, factor: float = 0.3) -> None:
    """Show (``on``) the strokes of ``before`` / ``after`` neighbouring keyframes of a Grease Pencil
    object faintly (``factor`` opacity), on every layer; ``on=False`` hides them."""
    gp = gp_obj.data
    gp.onion_mode = "RELATIVE"  # counted in keyframes, not frames
    gp.ghost_before_range, gp.ghost_after_range = int(before), int(after)
    gp.onion_factor = float(factor)
    gp.use_onion_fade = True
    for layer in gp.layers:
        layer.use_onion_skinning = bool(on)


def next_marker_frame(scene, prefix: str, current: int):
    """The first frame after ``current`` with a timeline marker named ``prefix...`` (wrapping to the
    first one), or None without such markers."""
    frames = sorted({m.frame for m in scene.timeline_markers if m.name.startswith(prefix)})
    if not frames:
        return None
    later = [f for f in frames if f > current]
    return later[0] if later else frames[0]


def keyed_extrapolation(obj):
    """``(frames (T,) int, scores (T,) float32)`` keyed by Propagate on ``obj``'s
    :data:`~facelab_addon.names.EXTRAPOLATION_PROP`, or None."""
    fc = find_fcurve(obj, f'["{EXTRAPOLATION_PROP}"]')
    if fc is None or not len(fc.keyframe_points):
        return None
    co = np.empty(2 * len(fc.keyframe_points), np.float32)
    fc.keyframe_points.foreach_get("co", co)
    co = co.reshape(-1, 2)
    return co[:, 0].round().astype(int), co[:, 1]


def most_extrapolated_frame(frames, scores, exclude=()):
    """``(frame, score)`` with the highest extrapolation score, skipping ``exclude`` (the training frames);
    None when every frame is excluded."""
    frames = np.asarray(frames)
    scores = np.asarray(scores, np.float64)
    keep = ~np.isin(frames, np.asarray(list(exclude), dtype=frames.dtype))
    if not keep.any():
        return None
    i = int(np.argmax(np.where(keep, scores, -np.inf)))
    return int(frames[i]), float(scores[i])


def active_viewports(context) -> list:
    """The 3D viewport spaces of the window's screen (none headless)."""
    screen = getattr(context, "screen", None)
    return [a.spaces.active for a in screen.areas if a.type == "VIEW_3D"] if screen is not None else []


def show_attribute_color(context) -> int:
    """Set every 3D viewport to Solid shading with Attribute colours; returns how many were set."""
    spaces = active_viewports(context)
    for sp in spaces:
        sp.shading.type = "SOLID"
        sp.shading.color_type = "VERTEX"
    return len(spaces)


def show_onion_overlay(context) -> int:
    """Turn on the Grease Pencil onion-skin overlay in every 3D viewport; returns how many."""
    spaces = active_viewports(context)
    for sp in spaces:
        sp.overlay.use_gpencil_onion_skin = True
    return len(spaces)


def scene_unit_metres(scene) -> float:
    """Metres per scene unit (the scene's unit scale, 1 when unset)."""
    return float(scene.unit_settings.scale_length or 1.0)

