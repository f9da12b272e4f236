"""Review operators: compare capture and corrected, the correction heat map, neighbouring sketches,
step to the next suggested / most extrapolated frame; and the Settings sub-panels' Reset / Save as
Defaults. They gather options, call the adapters of :mod:`facelab_addon.blender.review`, report."""

import bpy
import numpy as np
from bpy.props import BoolProperty, FloatProperty, IntProperty, StringProperty

from ..blender import review
from ..blender.strokes import find_sketch_object
from ..core.errors import FaceLabError
from ..names import CORRECTION_ATTR, EXTRAPOLATION_PROP, SUGGEST_MARKER
from ..pipeline import shot_settings, wording
from .common import face_object, poll_face


def _has_corrections(obj) -> bool:
    return bool(review.correction_keys(obj) or review.correction_modifiers(obj))


class FACELAB_OT_review_toggle(bpy.types.Operator):
    """Switch the face between the capture (every FaceLab correction muted) and the corrected result; switching back restores exactly the mutes you had"""

    bl_idname = "facelab.review_toggle"
    bl_label = "Compare Capture / Corrected"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        if not poll_face(cls, context):
            return False
        obj = face_object(context)
        if not review.showing_capture(obj) and not _has_corrections(obj):
            cls.poll_message_set("No FaceLab correction on the face yet (Refine Lips, Propagate, Solve...)")
            return False
        return True

    def execute(self, context):
        obj = face_object(context)
        if review.showing_capture(obj):
            k, m = review.show_corrected(obj)
            self.report({"INFO"}, f"Showing the corrected '{obj.name}': {k} FaceLab keys and {m} modifiers back as "
                                  "you had them")
        else:
            k, m = review.show_capture(obj)
            self.report({"INFO"}, f"Showing the capture of '{obj.name}': {k} FaceLab keys and {m} modifiers muted "
                                  "(press again for the corrected result)")
        return {"FINISHED"}


class FACELAB_OT_correction_heatmap(bpy.types.Operator):
    """Colour the face by how far FaceLab's corrections move each vertex on this frame (mm of world space), as the color attribute FL_correction; view it in Solid mode > Attribute color"""

    bl_idname = "facelab.correction_heatmap"
    bl_label = "Correction Heat Map"
    bl_options = {"REGISTER", "UNDO"}

    max_mm: FloatProperty(name="Scale Max (mm)", default=0.0, min=0.0, soft_max=10.0,
                          description="Correction shown in full red, in mm (0: the largest on this frame)")

    @classmethod
    def poll(cls, context):
        if not poll_face(cls, context):
            return False
        if context.mode != "OBJECT":
            cls.poll_message_set("Switch to Object Mode for the heat map")
            return False
        return True

    def execute(self, context):
        scene, obj = context.scene, face_object(context)
        try:
            mag = review.correction_magnitude(obj, context.evaluated_depsgraph_get(),
                                              metres_per_unit=review.scene_unit_metres(scene))
        except FaceLabError as e:
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        top = float(mag.max()) if len(mag) else 0.0
        vmax = self.max_mm or top
        review.write_heatmap(obj, mag, vmax, scene.frame_current)
        shown = review.show_attribute_color(context)
        moved = int(np.count_nonzero(mag > 0.01))
        if top <= 0.0:
            self.report({"WARNING"}, f"No correction on frame {scene.frame_current}: '{obj.name}' is the capture here "
                                     f"(heat map {CORRECTION_ATTR} all grey)")
            return {"FINISHED"}
        self.report({"INFO"}, f"Heat map '{CORRECTION_ATTR}' on frame {scene.frame_current}: grey 0 mm to red "
                              f"{vmax:.2f} mm; largest correction {top:.2f} mm, {moved:,} vertices move more than "
                              "0.01 mm" + ("" if shown else "; view it in Solid mode > Attribute color"))
        return {"FINISHED"}


def _sketch(context):
    return find_sketch_object(context.scene, context.scene.facelab.sketch)


class FACELAB_OT_sketch_onion_skin(bpy.types.Operator):
    """Show the sketches of neighbouring keyframes faintly (Grease Pencil onion skinning on the lip sketch), to draw consistent contours from frame to frame"""

    bl_idname = "facelab.sketch_onion_skin"
    bl_label = "Neighbouring Sketches"
    bl_options = {"REGISTER", "UNDO"}

    show: BoolProperty(name="Show", default=True, description="Show (on) or hide (off) the neighbouring sketches")
    before: IntProperty(name="Before", default=2, min=0, max=20, description="Sketched keyframes shown before")
    after: IntProperty(name="After", default=2, min=0, max=20, description="Sketched keyframes shown after")
    opacity: FloatProperty(name="Opacity", default=0.3, min=0.0, max=1.0, subtype="FACTOR",
                           description="How strongly the neighbouring sketches show (0: invisible, 1: as drawn)")

    @classmethod
    def poll(cls, context):
        if _sketch(context) is None:
            cls.poll_message_set("No lip sketch yet: press New Lip Sketch")
            return False
        return True

    def execute(self, context):
        gp = _sketch(context)
        review.set_onion_skin(gp, self.show, self.before, self.after, self.opacity)
        if self.show:
            review.show_onion_overlay(context)
        self.report({"INFO"}, f"'{gp.name}': sketches of {self.before} keyframes before and {self.after} after shown "
                              f"at {self.opacity:.0%}" if self.show else f"'{gp.name}': neighbouring sketches hidden")
        return {"FINISHED"}


class FACELAB_OT_next_suggested_frame(bpy.types.Operator):
    """Go to the next frame FaceLab suggests correcting (timeline markers 'FL suggest', left by Propagate)"""

    bl_idname = "facelab.next_suggested_frame"
    bl_label = "Next Suggested Frame"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        if review.next_marker_frame(context.scene, SUGGEST_MARKER, context.scene.frame_current) is None:
            cls.poll_message_set(f"No '{SUGGEST_MARKER}' markers: Propagate suggests frames to correct next")
            return False
        return True

    def execute(self, context):
        scene = context.scene
        f = review.next_marker_frame(scene, SUGGEST_MARKER, scene.frame_current)
        scene.frame_set(f)
        self.report({"INFO"}, f"Frame {f}: suggested for correction (sketch it and Refine Lips)")
        return {"FINISHED"}


class FACELAB_OT_most_extrapolated_frame(bpy.types.Operator):
    """Go to the frame where Propagate's model extrapolates most (the mouth furthest from every training pose), training frames excluded"""

    bl_idname = "facelab.most_extrapolated_frame"
    bl_label = "Most Extrapolated Frame"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def description(cls, context, properties):
        """The current frame's extrapolation score and its bands, then what the button does."""
        obj = face_object(context)
        score = obj.get(EXTRAPOLATION_PROP) if obj is not None else None
        return cls.__doc__ if score is None else f"{wording.extrapolation_tooltip(float(score))}.\n{cls.__doc__}"

    @classmethod
    def poll(cls, context):
        if not poll_face(cls, context):
            return False
        if review.keyed_extrapolation(face_object(context)) is None:
            cls.poll_message_set("Propagate first: it keys how far each frame is from the training frames")
            return False
        return True

    def execute(self, context):
        obj = face_object(context)
        frames, score = review.keyed_extrapolation(obj)
        best = review.most_extrapolated_frame(frames, score, {t.frame for t in obj.facelab.training_frames})
        if best is None:
            self.report({"ERROR"}, "Every propagated frame is a training frame; nothing extrapolates")
            return {"CANCELLED"}
        context.scene.frame_set(best[0])
        word = wording.extrapolation_word(best[1])
        self.report({"INFO"}, f"Frame {best[0]}: prediction {word} (extrapolation {best[1]:.2f})"
                              + ("; correct this frame and Propagate again" if word != "reliable" else ""))
        return {"FINISHED"}


def _entry(op):
    e = shot_settings.entry_for(op.target)
    if e is None:
        op.report({"ERROR"}, f"No FaceLab settings called {op.target!r}: one of "
                             f"{[x.attr for x in shot_settings.SCENE_SETTINGS]}")
    return e


class FACELAB_OT_reset_settings(bpy.types.Operator):
    """Set this step's settings of the shot back to the defaults of the add-on preferences"""

    bl_idname = "facelab.reset_settings"
    bl_label = "Reset Settings"
    bl_options = {"REGISTER", "UNDO"}

    target: StringProperty(name="Settings", description="Scene attribute of the settings (e.g. facelab_refine)")

    def execute(self, context):
        e = _entry(self)
        if e is None:
            return {"CANCELLED"}
        grp = getattr(context.scene, e.attr)
        for k, v in shot_settings.preference_defaults(e, context).items():
            setattr(grp, k, v)
        self.report({"INFO"}, f"{e.cls.__name__}: the defaults of the preferences")
        return {"FINISHED"}


class FACELAB_OT_save_settings_defaults(bpy.types.Operator):
    """Make this shot's settings of the step the defaults of new scenes (add-on preferences)"""

    bl_idname = "facelab.save_settings_defaults"
    bl_label = "Save Settings as Defaults"
    bl_options = {"REGISTER"}

    target: StringProperty(name="Settings", description="Scene attribute of the settings (e.g. facelab_refine)")

    @classmethod
    def poll(cls, context):
        if shot_settings.preferences(context) is None:
            cls.poll_message_set("FaceLab is not enabled as an add-on here: no preferences to save to")
            return False
        return True

    def execute(self, context):
        e = _entry(self)
        if e is None:
            return {"CANCELLED"}
        shot_settings.copy_values(getattr(context.scene, e.attr), getattr(shot_settings.preferences(context), e.attr), e)
        context.preferences.is_dirty = True
        self.report({"INFO"}, f"{e.cls.__name__}: this shot's values are the defaults of new scenes")
        return {"FINISHED"}


classes = (FACELAB_OT_review_toggle, FACELAB_OT_correction_heatmap, FACELAB_OT_sketch_onion_skin,
           FACELAB_OT_next_suggested_frame, FACELAB_OT_most_extrapolated_frame, FACELAB_OT_reset_settings,
           FACELAB_OT_save_settings_defaults)


register, unregister = bpy.utils.register_classes_factory(classes)
