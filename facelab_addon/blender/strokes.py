"""Lip sketches drawn in Blender -> polylines in camera pixels (Dinev et al., §5).

The artist sketches the upper and lower lip contours over the plate, in
camera view, on two layers named "Upper lip" and "Lower lip". This module
creates that sketch object, writes strokes at given pixels (tests, demo), and
reads the strokes back as ``(N,2)`` pixel polylines (top-left origin, y down;
see ``facelab_addon/core/capture/camera.py``) for ``core.lips.sketch``.

Sources, in order of preference
-------------------------------
1. A Grease Pencil (v3) object: ``gp_obj`` if given, else the active object if
   it has lip layers, else an object named ``FL_LipSketch``, else the first
   (by name) Grease Pencil object in the scene with lip layers. Points live in
   layer space; ``layer.to_world`` (object ``matrix_world`` @ layer
   ``matrix_local``, or the layer parent) maps them to the world, and the
   camera maps them to pixels. The drawing read is the one *shown* at the
   frame (``layer.get_frame_at(frame)``: the latest keyframe <= frame).
2. The scene annotation (``compat.scene_annotation``: ``scene.annotation`` in
   Blender 5.x, ``scene.grease_pencil`` in 4.5), layers matched the
   same way, frame = the latest annotation frame <= ``frame``. What its
   ``point.co`` means depends on the placement used when drawing in the 3D
   viewport (verified in Blender 5.0.1 by running ``gpencil.annotate`` and
   against the 5.0 source, ``annotate_paint.cc``):

   * "3D Cursor" / "Surface": world coordinates (scene units).
   * "View": screen space, in percent. In camera view, x and y are percent
     (0..100, y up) of the camera frame *without lens shift*
     (``ED_view3d_calc_camera_border(..., no_shift=true)``), i.e. of a
     frame-sized rectangle centred on the principal point; ``z`` is 0.
     Outside camera view they are percent of the viewport region and cannot
     be related to the camera (draw in camera view!).

   Blender 4.5 and 5.0 do not expose the stroke's space flag to Python (5.3
   has ``AnnotationStroke.display_mode``, used when present). Without
   it a stroke is taken as "View" percent space when all its ``z`` are exactly
   0, which a 3D stroke drawn in camera view only shows when the camera looks
   along world Z; for such cameras it is read as world points if those lie in
   front of the camera and near the frame.

Labels: a layer whose name contains "upper" (case-insensitive) is an upper
lip layer, "lower" a lower lip layer. Which layers are read is decided in one
place, :func:`live_lip_layers`, for every reader: only shown layers (a hidden
one is stale to the artist), an exact "upper lip" / "lower lip" name wins over
partial matches, several partial matches are concatenated, and two shown
layers among the exact name and its copies ("Upper lip.001") are refused as
ambiguous. Hidden sketch objects are not read either.

The sketch object (``new_lip_sketch``) is a child of the camera with origin
on the optical axis, ``depth`` in front of the camera (just past the near
clip), rotated so that its X-Z plane is the image plane, and drawn "In Front"
of the face. With the default stroke placement ("Origin") and any drawing
plane "View" or "Front (X-Z)", strokes drawn in camera view land on that plane
and move with the camera; "3D Cursor" / "Surface" placement also keep each
point on the camera ray under the pen, so every placement yields the pixels
the artist drew over, as long as the strokes are drawn in camera view.
"""

from __future__ import annotations

import math

import bpy
import numpy as np
from mathutils import Matrix

from ..core.capture.camera import Camera
from ..core.errors import CameraError, SketchError
from ..names import SKETCH_OBJECT, SNAP_ATTR, SNAP_PROP, SNAP_REPORT_PROP
from . import compat
from .camera import evaluated_depsgraph
from .lip_layers import (
    LOWER_LAYER,
    UPPER_LAYER,
    has_lip_layers,
    hidden_object,
    labelled_lip_layers,
    lip_label,
    live_lip_layers,
    missing_layer_error,
)
from .sketch_snap import snap_to_plate

__all__ = [
    "stroke_snap_choices",
    "set_stroke_snap",
    "selected_strokes",
    "SKETCH_CAMERA_PROP",
    "sketch_camera",
    "sketch_name_for",
    "layer_to_world",
    "transform_points",
    "drawing_polylines",
    "project_world",
    "new_lip_sketch",
    "write_stroke_pixels",
    "find_sketch_object",
    "has_lip_sketch",
    "sketch_keyframes",
    "require_sketch_keyed_on",
    "read_lip_strokes",
    "set_lip_layer",
]

DEFAULT_SKETCH_NAME = SKETCH_OBJECT
_LAYER_TINT = {UPPER_LAYER: (1.0, 0.15, 0.1), LOWER_LAYER: (0.1, 0.35, 1.0)}
_DEFAULT_GP_RADIUS = 0.01  # Blender's implicit point radius when no "radius" attribute exists
_HOWTO = (
    "press New Lip Sketch, then in camera view (Numpad 0) draw the upper lip contour on the "
    f"'{UPPER_LAYER}' layer and the lower lip contour on the '{LOWER_LAYER}' layer"
)


# --------------------------------------------------------------------------- helpers
def _find_layer(gp_data, name):
    for layer in gp_data.layers:
        if layer.name.lower() == name.lower():
            return layer
    return None


def _matrix(m) -> np.ndarray:
    return np.array(m, dtype=np.float64).reshape(4, 4)


def layer_to_world(layer, obj, depsgraph) -> np.ndarray:
    """(4,4) layer space -> world (scene units), as ``Layer::to_world_space`` in Blender.

    ``obj`` and the layer's parent are read evaluated (current frame).
    """
    local = _matrix(layer.matrix_local)
    parent = layer.parent
    if parent is None:
        return _matrix(obj.evaluated_get(depsgraph).matrix_world) @ local
    parent = parent.evaluated_get(depsgraph)
    parent_to_world = _matrix(parent.matrix_world)
    if parent.type == "ARMATURE" and layer.parent_bone and parent.pose is not None:
        bone = parent.pose.bones.get(layer.parent_bone)
        if bone is not None:
            parent_to_world = parent_to_world @ _matrix(bone.matrix)
    return parent_to_world @ _matrix(layer.matrix_parent_inverse) @ local


def transform_points(M, P) -> np.ndarray:
    """(n,3) points ``P`` mapped by the (4,4) affine matrix ``M``."""
    return P @ M[:3, :3].T + M[:3, 3]


def _curve_offsets(drawing) -> np.ndarray:
    """(C+1,) int32 first point of each curve of a GP v3 drawing, then the number of points (empty: no curve)."""
    n_off = len(drawing.curve_offsets)
    if n_off < 2:
        return np.zeros(0, np.int32)
    offsets = np.empty(n_off, dtype=np.int32)
    drawing.curve_offsets.foreach_get("value", offsets)
    return offsets


def drawing_polylines(drawing) -> list:
    """Layer-space polylines of a GP v3 drawing: list of (n,3) float64 arrays."""
    offsets = _curve_offsets(drawing)
    if len(offsets) < 2:
        return []
    n_pts = int(offsets[-1])
    if n_pts == 0:
        return []
    pos = np.empty(n_pts * 3, dtype=np.float32)
    drawing.attributes["position"].data.foreach_get("vector", pos)
    pos = pos.reshape(-1, 3).astype(np.float64)
    return [p for p in np.split(pos, offsets[1:-1]) if len(p)]


def _check_in_front(camera: Camera, P, where: str):
    z = camera.depth(P)
    if not np.all(z > 1e-9):
        raise SketchError(
            f"{where} has {int(np.sum(~(z > 1e-9)))} point(s) at or behind the camera; "
            "delete those strokes and draw them again in camera view (Numpad 0) over the plate."
        )


def project_world(camera: Camera, polylines, where: str) -> list:
    """World polylines (list of (n,3), scene units) -> (n,2) pixels; SketchError naming ``where`` when
    a point is at or behind the camera."""
    out = []
    for P in polylines:
        _check_in_front(camera, P, where)
        out.append(camera.project(P))
    return out


# --------------------------------------------------------------------------- sketch cameras
#: Custom property of a sketch object pointing to the camera object it is drawn through.
SKETCH_CAMERA_PROP = "facelab_camera"


def sketch_camera(gp_obj):
    """The camera object a sketch is drawn through, or None when it does not say.

    Its :data:`SKETCH_CAMERA_PROP` custom property (set by :func:`new_lip_sketch`), else its
    parent when that is a camera.
    """
    cam = gp_obj.get(SKETCH_CAMERA_PROP) if hasattr(gp_obj, "get") else None
    if cam is not None and getattr(cam, "type", None) == "CAMERA":
        return cam
    par = gp_obj.parent
    return par if par is not None and par.type == "CAMERA" else None


def sketch_name_for(scene, cam) -> str:
    """The name of ``cam``'s sketch: an existing one drawn through it, else a new name."""
    for o in scene.objects:
        if o.type == "GREASEPENCIL" and has_lip_layers(o.data) and sketch_camera(o) == cam:
            return o.name
    default = bpy.data.objects.get(DEFAULT_SKETCH_NAME)
    if default is None or default.type != "GREASEPENCIL" or sketch_camera(default) in (None, cam):
        return DEFAULT_SKETCH_NAME
    return f"{DEFAULT_SKETCH_NAME}.{cam.name}"



# --------------------------------------------------------------------------- create
def _sketch_material():
    """The lip sketch's Grease Pencil material, styled by ``assets/presets/sketch_material.json``."""
    from ..assets import AssetError, load_preset

    mat = bpy.data.materials.get(DEFAULT_SKETCH_NAME)
    if mat is None or not mat.is_grease_pencil:
        style = load_preset("sketch_material", {"color": tuple, "show_fill": bool})
        if len(style["color"]) != 4:
            raise AssetError(f"assets/presets/sketch_material.json: 'color' must be RGBA (4 numbers in 0..1), "
                             f"got {style['color']}; fix the file.")
        mat = bpy.data.materials.new(DEFAULT_SKETCH_NAME)
        bpy.data.materials.create_gpencil_data(mat)
        mat.grease_pencil.color = style["color"]
        compat.set_gp_material_fill(mat.grease_pencil, style["show_fill"])
    return mat


def new_lip_sketch(scene, camera_obj=None, name: str | None = None, depth: float | None = None):
    """Create, or complete, the Grease Pencil object the artist sketches the lips on through one camera.

    Idempotent: an existing object ``name`` is reused as it is (transform and
    strokes untouched); only missing pieces are added: the lip layers, a
    keyframe (empty drawing) on ``scene.frame_current`` on each lip layer, a
    stroke material, and the link to the scene.

    Every camera has its own sketch (a stereo pair or a witness camera sketches
    the same frame from several views): without ``name``, the sketch of this
    camera is reused (:func:`sketch_camera`), else ``FL_LipSketch``
    is created for the first camera and ``FL_LipSketch.<camera name>`` for the
    others. The sketch records its camera in the custom property
    :data:`SKETCH_CAMERA_PROP`.

    Parameters
    ----------
    scene : bpy.types.Scene
    camera_obj : bpy.types.Object, optional
        The camera the sketch is drawn through; defaults to ``scene.camera``.
    name : str, optional
        Object and data name (default: this camera's sketch, see above).
    depth : float, optional
        Distance of the drawing plane in front of the camera, scene units;
        default ``1.5 * clip_start``. Only used when creating the object.

    Returns
    -------
    bpy.types.Object
        The ``GREASEPENCIL`` object with layers "Upper lip" (active) and
        "Lower lip".

    Raises
    ------
    CameraError
        No camera given and the scene has none.
    SketchError
        ``name`` is taken by an object that is not Grease Pencil.
    """
    cam = camera_obj if camera_obj is not None else scene.camera
    if cam is None:
        raise CameraError(
            f"Scene '{scene.name}' has no camera to sketch through; "
            "add a camera and make it the scene camera."
        )
    if name is None:
        name = sketch_name_for(scene, cam)
    obj = bpy.data.objects.get(name)
    if obj is not None and obj.type != "GREASEPENCIL":
        raise SketchError(
            f"Object '{name}' exists but is a {obj.type.lower()}, not Grease Pencil; rename or delete it "
            "and press New Lip Sketch again."
        )
    if obj is None:
        gp = compat.grease_pencil_data().new(name)
        obj = bpy.data.objects.new(name, gp)
        if depth is None:
            clip = cam.data.clip_start if cam.type == "CAMERA" else 0.1
            depth = 1.5 * clip
        scale = float(np.linalg.norm(_matrix(cam.matrix_world)[:3, 2])) or 1.0
        obj.parent = cam
        obj.matrix_parent_inverse = Matrix.Identity(4)
        # Origin on the optical axis (camera -Z); rotate +90 deg about X so the
        # object's X-Z plane ("Front" drawing plane) is the image plane.
        offset = Matrix.Translation((0.0, 0.0, -depth / scale))
        obj.matrix_basis = offset @ Matrix.Rotation(math.pi / 2, 4, "X")
        obj.show_in_front = True
        obj.hide_render = True  # a drawing aid: never in the renders
        obj[SKETCH_CAMERA_PROP] = cam
    if scene.objects.get(obj.name) is None:
        scene.collection.objects.link(obj)
    gp = obj.data
    if len(gp.materials) == 0:
        gp.materials.append(_sketch_material())

    frame = scene.frame_current
    lips = labelled_lip_layers(gp.layers, lambda lay: lay.name)
    for lab, layer_name in (("upper", UPPER_LAYER), ("lower", LOWER_LAYER)):
        layer = lips[lab][0] if lips[lab] else None
        if layer is None:
            layer = gp.layers.new(layer_name, set_active=False)
            layer.tint_color = _LAYER_TINT[layer_name]
            layer.tint_factor = 1.0
        if not any(f.frame_number == frame for f in layer.frames):
            layer.frames.new(frame)
    upper = labelled_lip_layers(gp.layers, lambda lay: lay.name)["upper"]
    if upper:
        gp.layers.active = upper[0]
    return obj


def set_lip_layer(gp_obj, lip: str) -> str:
    """Make the sketch's ``lip`` layer (``"upper"`` / ``"lower"``) the one drawn on; returns its name."""
    layers = labelled_lip_layers(gp_obj.data.layers, lambda lay: lay.name)[lip]
    if not layers:
        nice = UPPER_LAYER if lip == "upper" else LOWER_LAYER
        raise SketchError(f"Sketch '{gp_obj.name}' has no '{nice}' layer; press New Lip Sketch to add it.")
    gp_obj.data.layers.active = layers[0]
    return layers[0].name


# --------------------------------------------------------------------------- write
def write_stroke_pixels(gp_obj, layer_name: str, frame: int, polylines_px, camera: Camera,
                        depth: float | None = None, radius_px: float = 1.5, depsgraph=None) -> None:
    """Add strokes that project exactly onto given pixels.

    Points are put on the camera rays through the pixels at ``depth`` in
    front of the camera, then converted to the layer's space. Existing
    strokes are kept; a layer named ``layer_name`` and a keyframe at
    ``frame`` are created if missing.

    Parameters
    ----------
    gp_obj : bpy.types.Object
        A ``GREASEPENCIL`` object.
    layer_name : str
        Matched case-insensitively.
    frame : int
        Keyframe to write to.
    polylines_px : list of (N,2) array_like
        Pixel polylines (top-left origin, y down), ``N >= 1``.
    camera : Camera
        The camera the pixels refer to.
    depth : float, optional
        Depth along the viewing axis, scene units; default: the depth of the
        object's origin if it is in front of the camera, else 1.
    radius_px : float
        Stroke radius written to the ``radius`` attribute, in pixels at ``depth``.
    depsgraph : bpy.types.Depsgraph, optional
        For the object's evaluated transform at the current scene frame;
        default: the context's evaluated depsgraph.
    """
    if gp_obj is None or gp_obj.type != "GREASEPENCIL":
        raise SketchError("write_stroke_pixels needs a Grease Pencil object; press New Lip Sketch first.")
    polys = [np.asarray(p, dtype=np.float64).reshape(-1, 2) for p in polylines_px]
    if any(len(p) == 0 for p in polys):
        raise ValueError("every polyline needs at least one point")
    if not polys:
        return
    gp = gp_obj.data
    layer = _find_layer(gp, layer_name) or gp.layers.new(layer_name, set_active=False)
    fr = next((f for f in layer.frames if f.frame_number == frame), None) or layer.frames.new(frame)
    drawing = fr.drawing
    if depsgraph is None:
        scenes = gp_obj.users_scene
        depsgraph = evaluated_depsgraph(scenes[0]) if scenes else bpy.context.evaluated_depsgraph_get()
    to_world = layer_to_world(layer, gp_obj, depsgraph)

    if depth is None:
        depth = float(camera.depth(to_world[:3, 3][None])[0])
        if not depth > 0:
            depth = 1.0
    px = np.vstack(polys)
    h = np.c_[px, np.ones(len(px))]
    x_cam = np.linalg.solve(camera.K, h.T).T * depth  # camera coordinates, z == depth
    X = (x_cam - camera.t) @ camera.R  # world: R^T (x_c - t)
    to_layer = np.linalg.inv(to_world)
    P = transform_points(to_layer, X)

    n_old = len(drawing.attributes["position"].data)
    had_radius = drawing.attributes.get("radius") is not None
    drawing.add_strokes([len(p) for p in polys])
    n_all = n_old + len(P)
    pos = np.empty(n_all * 3, dtype=np.float32)
    attr = drawing.attributes["position"]
    attr.data.foreach_get("vector", pos)
    pos = pos.reshape(-1, 3)
    pos[n_old:] = P
    attr.data.foreach_set("vector", pos.ravel())

    rad_attr = drawing.attributes.get("radius") or drawing.attributes.new("radius", "FLOAT", "POINT")
    rad = np.empty(n_all, dtype=np.float32)
    if had_radius:
        rad_attr.data.foreach_get("value", rad)
    else:
        rad[:] = _DEFAULT_GP_RADIUS
    layer_scale = float(np.cbrt(abs(np.linalg.det(to_layer[:3, :3])))) or 1.0
    rad[n_old:] = radius_px * depth / camera.K[0, 0] * layer_scale
    rad_attr.data.foreach_set("value", rad)
    drawing.tag_positions_changed()
    gp_obj.data.update_tag()


# --------------------------------------------------------------------------- read
def find_sketch_object(scene, gp_obj=None):
    """The Grease Pencil lip sketch of ``scene``, or None (the scene annotation may still hold one).

    ``gp_obj`` if given (it must be Grease Pencil), else, among the shown objects with lip layers
    (hidden ones only when no other has lip layers), the active object, else the one named ``FL_LipSketch``
    (:data:`facelab_addon.names.SKETCH_OBJECT`), else the first by name with
    lip layers; without lip layers anywhere, an object of the default name.

    Raises
    ------
    SketchError
        ``gp_obj`` is not a Grease Pencil object.
    """
    if gp_obj is not None:
        if gp_obj.type != "GREASEPENCIL":
            raise SketchError(
                f"Object '{gp_obj.name}' is a {gp_obj.type.lower()}, not a Grease Pencil sketch; {_HOWTO}."
            )
        return gp_obj
    candidates = [o for o in scene.objects if o.type == "GREASEPENCIL" and has_lip_layers(o.data)]
    shown = [o for o in candidates if not hidden_object(o)]
    candidates = shown or candidates  # only hidden sketches: read one, its layers' messages say what is hidden
    if not candidates:
        named = scene.objects.get(DEFAULT_SKETCH_NAME)
        return named if named is not None and named.type == "GREASEPENCIL" else None
    active = getattr(bpy.context, "active_object", None)
    for o in candidates:
        if o == active:
            return o
    for o in candidates:
        if o.name == DEFAULT_SKETCH_NAME:
            return o
    return sorted(candidates, key=lambda o: o.name)[0]


def has_lip_sketch(scene, gp_obj=None) -> bool:
    """Whether :func:`read_lip_strokes` has a sketch to read: ``gp_obj``, a Grease Pencil object
    with lip layers, or annotation layers named after the lips (cheap enough for ``poll``)."""
    if gp_obj is not None:
        return True
    if any(o.type == "GREASEPENCIL" and has_lip_layers(o.data) for o in scene.objects):
        return True
    ann = compat.scene_annotation(scene)
    return ann is not None and any(lip_label(lay.info) for lay in ann.layers)


def sketch_keyframes(gp_obj) -> list:
    """Sorted scene frames holding a keyframe on the lip layers of the Grease Pencil sketch ``gp_obj``."""
    frames = set()
    lips = live_lip_layers(gp_obj.data.layers, lambda lay: lay.name, f"The lip sketch '{gp_obj.name}'")
    for layer in lips["upper"] + lips["lower"]:
        frames.update(int(fr.frame_number) for fr in layer.frames)
    return sorted(frames)


def require_sketch_keyed_on(scene, frame: int, gp_obj=None) -> None:
    """Refuse to refine ``frame`` when the lip sketch has no keyframe on it.

    A drawing is shown on every frame until the next keyframe, so the strokes
    read on a frame without a keyframe of its own were drawn for an earlier
    frame, over another pose of the face. Both lip layers (of the Grease
    Pencil sketch, else of the scene annotation) must be keyed on ``frame``.

    Parameters
    ----------
    scene : bpy.types.Scene
    frame : int
    gp_obj : bpy.types.Object, optional
        The sketch; default found as in :func:`read_lip_strokes`.

    Raises
    ------
    SketchError
        Naming the frame, the keyframe the strokes are held from, the sketched
        frames and the fix. (No sketch, or nothing shown on the frame, is
        left to :func:`read_lip_strokes`.)
    """
    frame = int(frame)
    obj = find_sketch_object(scene, gp_obj)
    if obj is not None:
        layers, name_of, what = obj.data.layers, (lambda lay: lay.name), f"The lip sketch '{obj.name}'"
    else:
        ann = compat.scene_annotation(scene)
        if ann is None:
            return
        layers, name_of, what = ann.layers, (lambda lay: lay.info), f"The lip annotation '{ann.name}'"
    lips = live_lip_layers(layers, name_of, what)
    keyed = {lab: sorted({int(fr.frame_number) for lay in lips[lab] for fr in lay.frames}) for lab in lips}
    for lab, nice in (("upper", UPPER_LAYER), ("lower", LOWER_LAYER)):
        if not lips[lab] or frame in keyed[lab]:
            continue  # a missing layer is reported by read_lip_strokes
        held = [f for f in keyed[lab] if f < frame]
        if not held:
            continue  # nothing shown on the frame: read_lip_strokes says there are no strokes
        both = sorted(set(keyed["upper"]) & set(keyed["lower"]))
        raise SketchError(
            f"{what} has no '{nice}' keyframe on frame {frame}: the strokes shown there are held from frame "
            f"{held[-1]}, drawn over another pose of the face. "
            f"Go to frame {frame}, add a keyframe on the lip layers and draw both lips there, or refine a "
            f"sketched frame ({', '.join(map(str, both[:12])) or 'none yet'})."
        )


def _read_gp_object(obj, camera: Camera, frame: int, depsgraph, snap=None) -> dict:
    name_of = (lambda lay: lay.name)
    lips = live_lip_layers(obj.data.layers, name_of, f"Sketch '{obj.name}'")
    out, choice = {}, {"upper": [], "lower": []}
    for lab, nice in (("upper", UPPER_LAYER), ("lower", LOWER_LAYER)):
        if not lips[lab]:
            raise missing_layer_error(
                obj.data.layers, name_of, lab, f"Sketch '{obj.name}'",
                f"add a layer named '{nice}' (or press New Lip Sketch) and draw the {nice.lower()} on it in camera "
                "view.")
        polys = []
        for layer in lips[lab]:
            fr = layer.get_frame_at(frame)
            if fr is None or fr.drawing is None or fr.drawing.type != "DRAWING":
                continue
            M = layer_to_world(layer, obj, depsgraph)
            world = [transform_points(M, P) for P in drawing_polylines(fr.drawing)]
            polys += project_world(camera, world, f"Layer '{layer.name}' of '{obj.name}' on frame {frame}")
            choice[lab] += _snap_choices(fr.drawing)
        if not polys:
            raise SketchError(
                f"The '{nice}' layer of '{obj.name}' has no strokes on frame {frame}; "
                f"draw the {nice.lower()} contour on it in camera view on this frame (keyed on it)."
            )
        out[lab] = polys
    # which strokes are read snapped: all or none when asked (``snap``), else each stroke's own choice
    # (SNAP_ATTR), or the sketch's option for a stroke without one
    on = bool(obj.get(SNAP_PROP, False))
    only = {lab: [bool(snap) if snap is not None else (c > 0 or (c == 0 and on)) for c in choice[lab]]
            for lab in choice}
    if any(any(v) for v in only.values()):
        cam_obj = sketch_camera(obj) or getattr(bpy.context.scene, "camera", None)
        out, report = snap_to_plate(cam_obj, camera, frame, out, only=only)
        obj[SNAP_REPORT_PROP] = report
    elif snap is None and SNAP_REPORT_PROP in obj:
        del obj[SNAP_REPORT_PROP]  # nothing snapped now: no report of an earlier snapping
    return out


def stroke_snap_choices(drawing) -> np.ndarray:
    """(C,) int8 per stroke (curve) of a GP v3 drawing: +1 snap it, -1 never, 0 as the sketch's option says
    (all 0 when the drawing has no :data:`~facelab_addon.names.SNAP_ATTR`)."""
    n = max(len(_curve_offsets(drawing)) - 1, 0)
    attr = drawing.attributes.get(SNAP_ATTR)
    out = np.zeros(n, np.int32)
    if attr is not None and attr.domain == "CURVE" and len(attr.data) == n and n:
        attr.data.foreach_get("value", out)
    return np.sign(out).astype(np.int8)


def set_stroke_snap(drawing, strokes, choice: int) -> int:
    """Set the snap choice (+1 snap, -1 never, 0 as the sketch says) of the strokes ``strokes`` ((C,) bool mask
    or indices) of a GP v3 drawing; creates the per-curve attribute (0 elsewhere). Returns how many strokes."""
    n = max(len(_curve_offsets(drawing)) - 1, 0)
    idx = np.flatnonzero(np.asarray(strokes, dtype=bool)) if np.asarray(strokes).dtype == bool \
        else np.asarray(strokes, dtype=np.int64)
    if n == 0 or len(idx) == 0:
        return 0
    attr = drawing.attributes.get(SNAP_ATTR)
    if attr is not None and (attr.domain != "CURVE" or attr.data_type != "INT8"):
        drawing.attributes.remove(attr)
        attr = None
    if attr is None:
        attr = drawing.attributes.new(SNAP_ATTR, "INT8", "CURVE")
    vals = np.zeros(n, np.int32)
    attr.data.foreach_get("value", vals)
    vals[idx] = int(np.sign(choice))
    attr.data.foreach_set("value", vals)
    return len(idx)


def selected_strokes(drawing) -> np.ndarray:
    """(C,) bool: the strokes of a GP v3 drawing with a selected point (or selected, in stroke selection)."""
    offsets = _curve_offsets(drawing)
    n = max(len(offsets) - 1, 0)
    sel = drawing.attributes.get(".selection")
    if sel is None or n == 0:
        return np.zeros(n, bool)
    vals = np.zeros(len(sel.data), bool)
    sel.data.foreach_get("value", vals)
    if sel.domain == "CURVE":
        return vals
    return np.logical_or.reduceat(vals, offsets[:-1]) & (np.diff(offsets) > 0) if len(vals) else np.zeros(n, bool)


def _snap_choices(drawing) -> list:
    """The snap choice of each polyline :func:`drawing_polylines` returns (strokes without points dropped)."""
    sizes = np.diff(_curve_offsets(drawing))
    return [int(c) for c, k in zip(stroke_snap_choices(drawing), sizes) if k > 0]


def _annotation_frame_at(layer, frame: int):
    best = None
    for f in layer.frames:
        if f.frame_number <= frame and (best is None or f.frame_number > best.frame_number):
            best = f
    return best


def _view_percent_to_px(P, camera: Camera) -> np.ndarray:
    """Camera-view screen-space annotation points (percent of the unshifted frame, y up) to pixels."""
    W, H = camera.width, camera.height
    cx, cy = camera.K[0, 2], camera.K[1, 2]
    return np.c_[P[:, 0] / 100.0 * W + (cx - W / 2.0), (1.0 - P[:, 1] / 100.0) * H + (cy - H / 2.0)]


def _is_view_space(stroke, P, camera: Camera) -> bool:
    """Whether annotation points are camera-view percent coordinates (else world points)."""
    mode = getattr(stroke, "display_mode", None)  # not in Blender 4.5 / 5.0; in 5.3
    if mode is not None:
        return mode != "3DSPACE"
    if not np.all(P[:, 2] == 0.0):
        return False
    # z == 0 everywhere: "View" placement, unless the camera looks along world Z,
    # where 3D strokes drawn at the 3D cursor on z = 0 also have z == 0.
    if abs(camera.forward[2]) < 0.9:
        return True
    z = camera.depth(P)
    if not np.all(z > 1e-9):
        return True
    big = max(camera.width, camera.height)
    return not bool(np.all(camera.in_frame(camera.project(P), margin=-big)))


def annotation_frame_pixels(annotation_frame, camera: Camera, where: str) -> list:
    """Pixel polylines ``[(n,2), ...]`` of the strokes of one annotation frame.

    "View"-placed strokes are in percent of the camera frame; 3D strokes are
    projected through ``camera`` (they must lie in front of it; ``where`` names
    the layer and frame in the error otherwise). Empty strokes are skipped.
    """
    polys = []
    for stroke in annotation_frame.strokes:
        n = len(stroke.points)
        if n == 0:
            continue
        co = np.empty(n * 3, dtype=np.float32)
        stroke.points.foreach_get("co", co)
        P = co.reshape(-1, 3).astype(np.float64)
        if _is_view_space(stroke, P, camera):
            polys.append(_view_percent_to_px(P, camera))
        else:
            polys += project_world(camera, [P], where)
    return polys


def _read_annotation(ann, camera: Camera, frame: int) -> dict:
    name_of = (lambda lay: lay.info)
    lips = live_lip_layers(ann.layers, name_of, f"Annotation '{ann.name}'")
    out = {}
    for lab, nice in (("upper", UPPER_LAYER), ("lower", LOWER_LAYER)):
        if not lips[lab]:
            raise missing_layer_error(
                ann.layers, name_of, lab, f"Annotation '{ann.name}'",
                f"add an annotation layer named '{nice}' and draw the {nice.lower()} on it in camera view, or "
                f"{_HOWTO}.")
        polys = []
        for layer in lips[lab]:
            fr = _annotation_frame_at(layer, frame)
            if fr is None:
                continue
            polys += annotation_frame_pixels(fr, camera, f"Annotation layer '{layer.info}' on frame {frame}")
        if not polys:
            raise SketchError(
                f"The '{nice}' annotation layer has no strokes on frame {frame}; "
                f"draw the {nice.lower()} contour on it in camera view on this frame (keyed on it)."
            )
        out[lab] = polys
    return out


def read_lip_strokes(scene, camera: Camera, frame: int, gp_obj=None, depsgraph=None, snap=None) -> dict:
    """Read the upper and lower lip sketch as pixel polylines.

    Parameters
    ----------
    scene : bpy.types.Scene
    camera : Camera
        The camera the sketch was drawn through (``camera_from_blender``).
    frame : int
        Scene frame; the drawing shown at that frame is read.
    gp_obj : bpy.types.Object, optional
        The Grease Pencil sketch; found in the scene if omitted (see module
        docstring), with the scene annotation as fallback.
    depsgraph : bpy.types.Depsgraph, optional
        For the sketch object's evaluated transform; default: the context's
        evaluated depsgraph. Transforms are those of the current scene
        frame, so set the scene frame to ``frame`` first when the camera
        (and the sketch parented to it) is animated.

    Returns
    -------
    dict
        ``{"upper": [(N,2) ndarray, ...], "lower": [...]}``, pixels
        (top-left origin, y down), one array per stroke, in drawing order.
        Out-of-frame points are returned as they are.

    Raises
    ------
    SketchError
        No sketch at all, a lip layer missing or empty on this frame, or
        points at or behind the camera.
    """
    obj = find_sketch_object(scene, gp_obj)
    if obj is not None:
        if depsgraph is None:
            depsgraph = evaluated_depsgraph(scene)
        return _read_gp_object(obj, camera, int(frame), depsgraph, snap)
    ann = compat.scene_annotation(scene)
    if ann is not None and any(lip_label(lay.info) for lay in ann.layers):
        return _read_annotation(ann, camera, int(frame))
    raise SketchError(f"No lip sketch found in scene '{scene.name}': {_HOWTO}.")
