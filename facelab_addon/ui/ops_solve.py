"""Operators of the contour-based performance solve and retargeting (Bhat et al. 2013, §4-5).

Add View / Remove View manage the tracking cameras (``Scene.facelab_solve.views``);
Bind Tracks, Solve Performance and Retarget gather their settings
(:mod:`.props_solve`), call the pipelines (:mod:`facelab_addon.pipeline.solve`,
:mod:`facelab_addon.pipeline.retarget`) and report what they did.
"""

import bpy
from bpy.props import IntProperty

from ..core.errors import FaceLabError
from ..names import RETARGET_PREFIX
from ..pipeline.frames import frame_range
from ..pipeline.retarget import retarget
from ..pipeline.shot_settings import bind_settings, retarget_settings, solve_settings
from ..pipeline.solve import DISAGREE_PX, bind_tracks, solve_performance, summarise_skips
from .common import face_object, poll_face, progress_callback


def _first(names, n=8) -> str:
    return f"{', '.join(names[:n])}{'...' if len(names) > n else ''}"


# --------------------------------------------------------------------------- operators
class FACELAB_OT_solve_add_view(bpy.types.Operator):
    """Add a tracking camera: the scene camera and the scene's active Movie Clip (edit them in the list)"""

    bl_idname = "facelab.solve_add_view"
    bl_label = "Add View"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        scene = context.scene
        s = scene.facelab_solve
        used = {v.camera for v in s.views}
        cam = scene.camera if scene.camera not in used else None
        if cam is None:
            cam = next((o for o in scene.objects if o.type == "CAMERA" and o not in used), None)
        v = s.views.add()
        v.camera = cam
        v.clip = scene.active_clip
        s.active_view_index = len(s.views) - 1
        missing = [w for w, x in (("camera", v.camera), ("movie clip", v.clip)) if x is None]
        if missing:
            self.report({"WARNING"}, f"View {len(s.views)} added without a {' and '.join(missing)}; pick them in the list")
        else:
            self.report({"INFO"}, f"View {len(s.views)}: camera '{v.camera.name}', clip '{v.clip.name}'")
        return {"FINISHED"}


class FACELAB_OT_solve_remove_view(bpy.types.Operator):
    """Remove the selected tracking camera from the solve"""

    bl_idname = "facelab.solve_remove_view"
    bl_label = "Remove View"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        if not len(context.scene.facelab_solve.views):
            cls.poll_message_set("No views to remove")
            return False
        return True

    def execute(self, context):
        s = context.scene.facelab_solve
        i = min(s.active_view_index, len(s.views) - 1)
        s.views.remove(i)
        s.active_view_index = max(0, i - 1)
        return {"FINISHED"}


class FACELAB_OT_bind_tracks(bpy.types.Operator):
    """Tie every track (and bundle) to the face surface: on the bind frame, each marker's camera ray is cast onto the mesh; bundles take their nearest surface point"""

    bl_idname = "facelab.bind_tracks"
    bl_label = "Bind Tracks"
    bl_options = {"REGISTER", "UNDO"}

    frame: IntProperty(name="Frame", default=-1, description="Bind frame (-1: FaceLab > Solve > Bind Frame, "
                                                             "or the current frame)")

    @classmethod
    def poll(cls, context):
        if not poll_face(cls, context):
            return False
        if not len(context.scene.facelab_solve.views):
            cls.poll_message_set("Add a view (tracking camera + Movie Clip) first")
            return False
        return True

    def execute(self, context):
        scene = context.scene
        f = self.frame if self.frame >= 0 else scene.facelab_solve.bind_frame
        f = scene.frame_current if f < 0 else f
        obj = face_object(context)
        try:
            r = bind_tracks(scene, obj, f, bind_settings(scene))
        except FaceLabError as e:
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        n_all = len(r.bound) + len(r.missed) + len(r.untracked)
        msg = f"Bound {len(r.bound)} of {n_all} tracks to '{obj.name}' on frame {f}"
        if r.bundles:
            msg += f", {r.bundles} bundles"
        if r.missed:
            msg += f"; missed the face: {_first(r.missed)}"
        if r.untracked:
            msg += f"; no marker on frame {f}: {_first(r.untracked)} (bind on a frame where they are tracked)"
        if r.disagree:
            msg += (f"; the views disagree by more than {DISAGREE_PX:g} px on {_first(r.disagree)} (same name for "
                    "different markers, a tracking slip, or the mesh does not match the footage on this frame)")
        if r.warnings:
            msg += "; " + "; ".join(r.warnings)
        warn = r.missed or r.untracked or r.warnings or r.disagree
        self.report({"WARNING"} if warn else {"INFO"}, msg)
        return {"FINISHED"} if r.bound or r.bundles else {"CANCELLED"}


class FACELAB_OT_solve_performance(bpy.types.Operator):
    """Solve blendshape weights for every frame from the bound tracks, bundles and lip/eyelid contours, keyed as ordinary F-curves, plus a per-frame corrective as FL_Solve_ shape keys"""

    bl_idname = "facelab.solve_performance"
    bl_label = "Solve Performance"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        if not poll_face(cls, context):
            return False
        if not len(context.scene.facelab_solve.views):
            cls.poll_message_set("Add a view (tracking camera + Movie Clip) first")
            return False
        if context.mode != "OBJECT":
            cls.poll_message_set("Switch to Object Mode to solve")
            return False
        return True

    def execute(self, context):
        scene = context.scene
        obj = face_object(context)
        try:
            settings = solve_settings(scene)
            frames = frame_range(scene, settings.frame_start, settings.frame_end)
            r = solve_performance(scene, obj, settings,
                                  progress=progress_callback(context, len(frames), "FaceLab Solve"))
        except FaceLabError as e:
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        finally:
            context.window_manager.progress_end()
        msg = f"Solved {len(r.solved)} frames in {r.time_s:.1f} s"
        if r.skipped:
            msg += f" ({summarise_skips(r.skipped)})"
        msg += f", {len(r.keys)} corrective shapes" if settings.use_corrective else ""
        if r.curve_stats and r.curve_stats["frames_with_curves"]:
            msg += f", contours on {r.curve_stats['frames_with_curves']} frames"
        if r.missing:
            fr = sorted(r.missing)
            msg += (f"; markers missing or off-screen on {len(fr)} frames (those markers skipped: "
                    f"{', '.join(map(str, fr[:6]))}{'...' if len(fr) > 6 else ''})")
        for n in [r.action_note] + r.notes:
            if n:
                msg += f"; {n}"
        warn = bool(r.skipped or r.missing or r.notes)
        self.report({"WARNING"} if warn else {"INFO"}, msg)
        return {"FINISHED"}


class FACELAB_OT_retarget(bpy.types.Operator):
    """Carry the solved performance to the creature: transfer the blendshapes by deformation transfer, copy the weights, transfer the correctives, and keep the lips talking (lip-sync heuristic)"""

    bl_idname = "facelab.retarget"
    bl_label = "Retarget"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        if not poll_face(cls, context):
            return False
        if context.scene.facelab_solve.creature is None:
            cls.poll_message_set("Pick the creature mesh in FaceLab > Retarget")
            return False
        return True

    def execute(self, context):
        scene = context.scene
        obj = face_object(context)
        creature = scene.facelab_solve.creature
        try:
            settings = retarget_settings(scene)
            frames = frame_range(scene, settings.frame_start, settings.frame_end)
            r = retarget(scene, obj, creature, settings,
                         progress=progress_callback(context, len(frames), "FaceLab Retarget"))
        except FaceLabError as e:
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        finally:
            context.window_manager.progress_end()
        msg = (f"Retargeted {len(r.frames)} frames to '{creature.name}' in {r.time_s:.1f} s ({r.correspondence}): "
               f"{len(r.created)} shape keys transferred, {len(r.keys)} corrective shapes ({RETARGET_PREFIX}*)")
        if r.kept:
            msg += f"; kept the creature's own keys {_first(r.kept, 5)}"
        if r.action_note:
            msg += f"; {r.action_note}"
        self.report({"WARNING"} if r.kept else {"INFO"}, msg)
        return {"FINISHED"}


classes = (FACELAB_OT_solve_add_view, FACELAB_OT_solve_remove_view, FACELAB_OT_bind_tracks,
           FACELAB_OT_solve_performance, FACELAB_OT_retarget)
register, unregister = bpy.utils.register_classes_factory(classes)
