"""Operators. Each gathers inputs through the adapters, calls one core function,
writes results through the adapters, and reports. No math here."""

import sys
import time

import bpy
import numpy as np

from ..blender import caches
from ..blender.camera import camera_from_blender
from ..blender.mesh import (
    default_fixed_mask,
    evaluated_vertices,
    mesh_triangles,
    require_mesh,
    world_to_local_deltas,
)
from ..blender.shapekeys import add_corrective_key, key_spike
from ..blender.strokes import new_lip_sketch, read_lip_strokes
from ..core.errors import FaceLabError
from ..core.lips.sketch import refine_lips
from .prefs import get_prefs

TRAIN_MARKER = "FL train"


def progress_callback(context, T, label="FaceLab"):
    """A ``progress(done, n)`` callback (``done`` items of ``n`` finished): the window's progress
    cursor, and in background mode (``blender -b``, the bpy module, the CLI) a line on stderr about
    every 10 %. Callers end it with ``context.window_manager.progress_end()``."""
    wm = context.window_manager
    wm.progress_begin(0, max(T, 1))
    last = [-1]

    def update(done, n=T):
        wm.progress_update(done)
        if bpy.app.background and n:
            pct = int(100 * done / n)
            if pct // 10 != last[0] // 10 or done == n:
                last[0] = pct
                print(f"{label}: {done}/{n} frames ({pct} %)", file=sys.stderr, flush=True)

    return update


def face_object(context):
    """The face to correct: FaceLab > Setup > Face, else the active mesh object."""
    s = context.scene.facelab
    if s.face is not None:
        return s.face
    ob = context.active_object
    return ob if ob is not None and ob.type == "MESH" else None


def poll_face(cls, context) -> bool:
    """Shared ``poll``: a face mesh must be selected (or set in Setup); explains itself otherwise."""
    if face_object(context) is None:
        cls.poll_message_set("Select the captured face mesh (or set it in FaceLab > Setup)")
        return False
    return True


def has_lip_sketch(scene) -> bool:
    """A sketch Refine Lips can read: Setup > Sketch, a Grease Pencil object with lip layers, or
    annotation layers named after the lips (cheap enough for ``poll``)."""
    if scene.facelab.sketch is not None:
        return True
    from ..blender.strokes import _has_lip_layers, _label

    if any(o.type == "GREASEPENCIL" and _has_lip_layers(o.data) for o in scene.objects):
        return True
    ann = getattr(scene, "annotation", None)
    return ann is not None and any(_label(lay.info) for lay in ann.layers)


def record_training_frame(scene, obj, frame: int, shape_key: str, source: str) -> None:
    """Remember ``frame`` as a corrected (training) frame and mark it on the timeline."""
    item = obj.facelab.training_frames.add()
    item.frame, item.shape_key, item.source = frame, shape_key, source
    if not any(m.frame == frame and m.name.startswith(TRAIN_MARKER) for m in scene.timeline_markers):
        scene.timeline_markers.new(f"{TRAIN_MARKER} {frame}", frame=frame)


class FACELAB_OT_new_lip_sketch(bpy.types.Operator):
    """Create a Grease Pencil sketch with 'Upper lip' and 'Lower lip' layers on this frame, attached to the scene camera"""

    bl_idname = "facelab.new_lip_sketch"
    bl_label = "New Lip Sketch"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        if context.scene.camera is None:
            cls.poll_message_set("Set a scene camera first (the camera the backplate belongs to)")
            return False
        return True

    def execute(self, context):
        scene = context.scene
        face = face_object(context)
        try:
            gp = new_lip_sketch(scene, scene.camera)
        except FaceLabError as e:
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        if scene.facelab.face is None and face is not None:
            scene.facelab.face = face
        scene.facelab.sketch = gp
        space = getattr(context, "space_data", None)
        if space is not None and space.type == "VIEW_3D":
            space.region_3d.view_perspective = "CAMERA"
        self.report(
            {"INFO"},
            f"Lip sketch '{gp.name}' ready on frame {scene.frame_current}: draw the inner-lip contours on the "
            "'Upper lip' and 'Lower lip' layers in camera view, then press Refine Lips",
        )
        return {"FINISHED"}


class FACELAB_OT_refine_lips(bpy.types.Operator):
    """Deform the lips of the face so their silhouettes match the sketched contours on this frame (Dinev et al. 2018 §5); the result is a new corrective shape key keyed on this frame"""

    bl_idname = "facelab.refine_lips"
    bl_label = "Refine Lips"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        if not poll_face(cls, context):
            return False
        if context.scene.camera is None:
            cls.poll_message_set("Set a scene camera first (the camera the sketch was drawn in)")
            return False
        if context.mode != "OBJECT":
            cls.poll_message_set("Switch to Object Mode to refine")
            return False
        if not has_lip_sketch(context.scene):
            cls.poll_message_set("No lip sketch yet: press New Lip Sketch and draw the inner lips in camera view")
            return False
        return True

    def execute(self, context):
        scene = context.scene
        frame = scene.frame_current
        t0 = time.perf_counter()
        note = ""
        try:
            obj = require_mesh(face_object(context))
            dg = context.evaluated_depsgraph_get()
            cam = camera_from_blender(scene, scene.camera, dg)
            strokes = read_lip_strokes(scene, cam, frame, gp_obj=scene.facelab.sketch, depsgraph=dg)
            V = evaluated_vertices(obj, dg)
            tris = mesh_triangles(obj.data)
            fixed, fixed_src = default_fixed_mask(obj, tris, scene.facelab.fixed_group)
            X, info = refine_lips(
                V, tris, cam, strokes["upper"], strokes["lower"], fixed=fixed, return_info=True, **get_prefs(context)
            )
            if caches.sequence_source(obj) in ("mesh_cache", "mesh_sequence_cache"):
                note = "; " + caches.cache_to_shape_key_ready(obj)  # so the corrective key shows on the cache
        except FaceLabError as e:
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        d_world = X - V
        d_local = world_to_local_deltas(obj, d_world)
        if note:
            captured = caches.read_captured_frames(obj, [frame])[0]
            d_local = caches.correction_to_key_offsets(obj, captured, d_local)
        kb = add_corrective_key(obj, f"FL_Refine_{frame:04d}", d_local)
        key_spike(kb, frame)
        record_training_frame(scene, obj, frame, kb.name, "sketch")
        moved = np.linalg.norm(d_world, axis=1)
        self.report(
            {"INFO"},
            f"Refined lips on frame {frame} in {time.perf_counter() - t0:.2f} s: shape key '{kb.name}', "
            f"{int((moved > 1e-9).sum())} vertices moved (max {moved.max():.4g} scene units), "
            f"fixed: {fixed_src}{note}",
        )
        return {"FINISHED"}


classes = (FACELAB_OT_new_lip_sketch, FACELAB_OT_refine_lips)


register, unregister = bpy.utils.register_classes_factory(classes)
