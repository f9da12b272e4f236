"""Operators of the sketch step (New Lip Sketch, Refine Lips). The work is in
:mod:`facelab_addon.pipeline.refine`; the helpers every operator shares are in :mod:`.common`."""

import bpy

from ..blender.sketch_mode import DRAW_MODE, SKETCH_MODES, start_drawing
from ..blender.strokes import new_lip_sketch, set_lip_layer
from ..core.errors import FaceLabError
from ..pipeline import shot_settings, wording
from ..pipeline.refine import RefineSettings, refine
from .common import face_object, poll_sketch


def refine_settings(context) -> RefineSettings:
    """The Refine Lips settings saved with the shot (FaceLab > Sketch & Refine > Settings and its Advanced;
    the fixed group from Setup)."""
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
        try:
            ready = start_drawing(context, gp, "upper")
        except (RuntimeError, FaceLabError) as e:  # no Draw mode here (a locked object, no view layer)
            self.report({"WARNING"}, f"Lip sketch '{gp.name}' made, but Draw mode could not start ({e}); select "
                                     "it and press Tab / Ctrl+Tab to draw")
            return {"FINISHED"}
        self.report(
            {"INFO"},
            f"Lip sketch '{gp.name}' ready on frame {scene.frame_current}: drawing on '{ready['layer']}' in "
            "camera view" + ("" if ready["plate"] else " (the camera shows no plate: Load Plate first)")
            + "; draw the upper inner-lip contour, switch to Lower Lip, draw it, then press Refine Lips",
        )
        return {"FINISHED"}


class FACELAB_OT_sketch_lip_layer(bpy.types.Operator):
    """Draw on the sketch's Upper lip or Lower lip layer (in Draw mode)"""

    bl_idname = "facelab.sketch_lip_layer"
    bl_label = "Lip Layer"
    bl_options = {"REGISTER", "UNDO"}

    lip: bpy.props.EnumProperty(name="Lip", items=(("upper", "Upper Lip", "Draw the upper inner-lip contour"),
                                                   ("lower", "Lower Lip", "Draw the lower inner-lip contour")),
                                description="Which inner-lip contour to draw: its layer of the lip sketch")

    @classmethod
    def poll(cls, context):
        if context.scene.facelab.sketch is None:
            cls.poll_message_set("No lip sketch yet: press New Lip Sketch")
            return False
        return True

    def execute(self, context):
        gp = context.scene.facelab.sketch
        try:
            if context.view_layer.objects.active == gp and gp.mode == DRAW_MODE:
                name = set_lip_layer(gp, self.lip)
            else:
                name = start_drawing(context, gp, self.lip)["layer"]
        except (RuntimeError, FaceLabError) as e:
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        self.report({"INFO"}, f"Drawing on '{name}'")
        return {"FINISHED"}


class FACELAB_OT_refine_lips(bpy.types.Operator):
    """Deform the lips of the face so their silhouettes match the sketched contours on this frame; the result is a new corrective shape key keyed on this frame"""

    bl_idname = "facelab.refine_lips"
    bl_label = "Refine Lips"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        why = poll_sketch(context)
        if why is not None:
            cls.poll_message_set(why)
            return False
        if context.mode not in SKETCH_MODES:
            cls.poll_message_set("Switch to Object Mode (or the sketch's Draw mode) to refine")
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
        metres = r.max_move * float(scene.unit_settings.scale_length or 1.0)  # world scene units -> m
        self.report({"INFO"}, wording.join([
            f"Refined lips on frame {r.frame} in {r.seconds:.2f} s: shape key '{r.shape_key}', "
            f"{r.moved_vertices} vertices moved by up to {wording.mm(metres)}",
            wording.held_fixed(r.fixed_source, scene.facelab.fixed_group),
            r.note,
            f"head turned {r.head_turn_deg:.0f}° from the Basis: its depth taken from there"
            if r.head_turn_deg is not None and r.head_turn_deg >= 2 else "",
        ]))
        for w in r.warnings:
            self.report({"WARNING"}, w)
        return {"FINISHED"}


classes = (FACELAB_OT_new_lip_sketch, FACELAB_OT_sketch_lip_layer, FACELAB_OT_refine_lips)


register, unregister = bpy.utils.register_classes_factory(classes)
