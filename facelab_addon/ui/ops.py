"""Operators of the sketch step (New Lip Sketch, Refine Lips). The work is in
:mod:`facelab_addon.pipeline.refine`; the helpers every operator shares are in :mod:`.common`."""

import bpy

from ..blender.strokes import has_lip_sketch, new_lip_sketch
from ..core.errors import FaceLabError
from ..pipeline import shot_settings
from ..pipeline.propagate import record_training_frame  # noqa: F401  (re-exported for scripts)
from ..pipeline.refine import RefineSettings, refine
from .common import face_object, operator_range, poll_face, progress_callback  # noqa: F401  (re-exported)


def refine_settings(context) -> RefineSettings:
    """The Refine Lips settings saved with the shot (FaceLab > Sketch & Refine > Settings; the fixed group
    from Setup)."""
    return shot_settings.refine_settings(context.scene)


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
        if not has_lip_sketch(context.scene, context.scene.facelab.sketch):
            cls.poll_message_set("No lip sketch yet: press New Lip Sketch and draw the inner lips in camera view")
            return False
        return True

    def execute(self, context):
        scene = context.scene
        try:
            r = refine(scene, face_object(context), scene.frame_current, refine_settings(context),
                       sketch=scene.facelab.sketch)
        except FaceLabError as e:
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        self.report(
            {"INFO"},
            f"Refined lips on frame {r.frame} in {r.seconds:.2f} s: shape key '{r.shape_key}', "
            f"{r.moved_vertices} vertices moved (max {r.max_move:.4g} scene units), "
            f"fixed: {r.fixed_source}" + (f"; {r.note}" if r.note else "")
            + (f"; head turned {r.head_turn_deg:.0f}° from the Basis: its depth taken from there"
               if r.head_turn_deg is not None and r.head_turn_deg >= 2 else ""),
        )
        return {"FINISHED"}


classes = (FACELAB_OT_new_lip_sketch, FACELAB_OT_refine_lips)


register, unregister = bpy.utils.register_classes_factory(classes)
