"""Operators of regression propagation: Auto Regions, the training-frame list,
Propagate and Bake. They poll, gather settings, call :mod:`facelab_addon.pipeline` (``regions``,
``propagate``, ``bake``) and report.

Propagate and the PC2/MDD bake run as modal jobs when started from a button (progress in the panel,
Esc cancels between steps) and synchronously from scripts, ``blender -b`` and the CLI: both run the
pipeline's generator of steps.
"""

import sys
import time
import traceback

import bpy
from bpy.props import BoolProperty, EnumProperty, IntProperty, StringProperty

from ..core.errors import FaceLabError
from ..names import LIPS_GROUP, MOUTH_GROUP, file_name_part
from ..pipeline import bake as bake_pipeline
from ..pipeline import wording
from ..pipeline.frames import frame_range
from ..pipeline.propagate import PropagateSettings, propagate, propagate_steps
from ..pipeline.regions import RegionSettings, auto_regions
from ..pipeline.shot_settings import scene_settings
from ..pipeline.steps import StepJob, run_steps
from ..pipeline.training import mark_training_frame, remove_training_frame
from .common import face_object, fill_scene_range, operator_range, poll_face, progress_callback


class FACELAB_OT_auto_regions(bpy.types.Operator):
    """Propose the trusted mouth region (FL_mouth) and the inner-lip region to predict (FL_lips) as geodesic bands around the inner-lip contact loop; refine them by weight painting"""

    bl_idname = "facelab.auto_regions"
    bl_label = "Auto Regions"
    bl_options = {"REGISTER", "UNDO"}

    replace: BoolProperty(name="Replace Existing Groups", default=False,
                          description=f"Overwrite {MOUTH_GROUP} / {LIPS_GROUP} if they exist (otherwise refuse)")
    use_selection: BoolProperty(name="Use Selected Edge Loop", default=False,
                                description="Take the inner-lip loop from the selected vertices instead of finding it")

    @classmethod
    def poll(cls, context):
        return poll_face(cls, context)

    def execute(self, context):
        obj = face_object(context)
        if context.mode == "EDIT_MESH":
            bpy.ops.object.mode_set(mode="OBJECT")
        try:
            r = auto_regions(obj, scene_settings(context.scene, RegionSettings, replace=self.replace,
                                                 use_selection=self.use_selection))
        except FaceLabError as e:
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        self.report({"INFO"}, f"Regions on '{r.object}': {r.mouth_vertices} mouth and {r.lip_vertices} inner-lip "
                              f"vertices (vertex groups {MOUTH_GROUP}, {LIPS_GROUP})")
        return {"FINISHED"}


class FACELAB_OT_mark_training_frame(bpy.types.Operator):
    """Use the current frame's mesh (for example corrected by sculpting a shape key) as a training frame for propagation; on a training frame, it becomes the frame's training shape (the earlier correction's key is kept, off on the frame)"""

    bl_idname = "facelab.mark_training_frame"
    bl_label = "Mark Training Frame"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        return poll_face(cls, context)

    def execute(self, context):
        obj, f = face_object(context), context.scene.frame_current
        if context.mode != "OBJECT":  # a sculpt or edit in progress is flushed to the mesh first
            bpy.ops.object.mode_set(mode="OBJECT")
        earlier = sorted({t.shape_key for t in obj.facelab.training_frames if t.frame == f and t.shape_key})
        was_training = f in {t.frame for t in obj.facelab.training_frames}
        try:
            r = mark_training_frame(context.scene, obj, f)
        except FaceLabError as e:
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        kept = f"; FaceLab's correction it showed is kept in '{r.shape_key}'" if r.shape_key else ""
        if not was_training:
            self.report({"INFO"}, f"Frame {f} marked as a training frame of '{obj.name}'{kept}")
            return {"FINISHED"}
        old = (f"; the earlier correction {', '.join(repr(k) for k in earlier)} is kept, keyed off on the frame"
               if earlier else "")
        self.report({"INFO"}, f"Training frame {f} of '{obj.name}' updated to what it shows now{kept}{old}; "
                              "Propagate again to update the correction")
        return {"FINISHED"}


def poll_training_list(cls, context) -> bool:
    """Shared ``poll`` of the training-list buttons: the face mesh has training frames."""
    obj = face_object(context)
    if obj is None or not len(obj.facelab.training_frames):
        cls.poll_message_set("No training frames on the face mesh")
        return False
    return True


def selected_training_index(obj) -> int:
    """Index of the training frame selected in the panel's list (clamped to the list)."""
    return min(obj.facelab.active_training_index, len(obj.facelab.training_frames) - 1)


class FACELAB_OT_jump_training_frame(bpy.types.Operator):
    """Go to the selected training frame"""

    bl_idname = "facelab.jump_training_frame"
    bl_label = "Jump to Training Frame"

    @classmethod
    def poll(cls, context):
        return poll_training_list(cls, context)

    def execute(self, context):
        obj = face_object(context)
        context.scene.frame_set(obj.facelab.training_frames[selected_training_index(obj)].frame)
        return {"FINISHED"}


class FACELAB_OT_jump_to_frame(bpy.types.Operator):
    """Go to this frame (a suggested frame, or one where the model extrapolates)"""

    bl_idname = "facelab.jump_to_frame"
    bl_label = "Jump to Frame"

    frame: IntProperty(name="Frame", description="The frame to go to")

    def execute(self, context):
        context.scene.frame_set(self.frame)
        return {"FINISHED"}


class FACELAB_OT_remove_training_frame(bpy.types.Operator):
    """Remove the selected training frame from the list (its shape key is kept)"""

    bl_idname = "facelab.remove_training_frame"
    bl_label = "Remove Training Frame"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        return poll_training_list(cls, context)

    def execute(self, context):
        obj = face_object(context)
        i = selected_training_index(obj)
        frame, removed_key = remove_training_frame(context.scene, obj, i)
        obj.facelab.active_training_index = max(0, i - 1)
        kept = f" (its shape key '{removed_key}' is kept)" if removed_key else ""
        self.report({"INFO"}, f"Removed training frame {frame}{kept}; Propagate again to update the correction")
        return {"FINISHED"}


# The job a modal operator (Propagate, Bake) is stepping, for the panel's progress bar and the
# operators' poll (None when idle). The one piece of module state in the UI, and UI-only: it holds
# the live StepJob object (which no bpy property can hold) for the few seconds a modal operator
# runs; it is never a result (pipelines return theirs) and nothing outside ``ui`` reads it.
RUNNING: dict = {"job": None, "label": ""}


class _ModalJob:
    """Mixin: run a StepJob on timer events (progress in the panel and the cursor, Esc cancels).
    The operator defines ``_job_done(context)`` (report, return its set) and ``_job_cancelled()``."""

    def _start_job(self, context, steps, label):
        self._job = StepJob(steps)
        RUNNING.update(job=self._job, label=label)
        wm = context.window_manager
        self._timer = wm.event_timer_add(0.01, window=context.window)
        wm.modal_handler_add(self)
        wm.progress_begin(0, 1000)
        return {"RUNNING_MODAL"}

    def _finish(self, context):
        wm = context.window_manager
        wm.event_timer_remove(self._timer)
        wm.progress_end()
        RUNNING.update(job=None, label="")
        for area in context.screen.areas if context.screen else ():
            area.tag_redraw()

    def modal(self, context, event):
        if event.type == "ESC":
            self._job.cancel()
            self._finish(context)
            self._job_cancelled()
            return {"CANCELLED"}
        if event.type != "TIMER":
            return {"PASS_THROUGH"}
        try:
            t_end = time.perf_counter() + 0.05  # stay responsive: a few steps per timer tick
            running = True
            while running and time.perf_counter() < t_end:
                running = self._job.step()
        except FaceLabError as e:  # the job's generator has put back what it changed
            self._finish(context)
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        except Exception as e:  # a bug: still leave the scene as it was and say so
            self._job.cancel()
            self._finish(context)
            traceback.print_exc()
            self.report({"ERROR"}, f"FaceLab failed while {self._job.stage} ({type(e).__name__}: {e}); what it had "
                                   "changed was put back. Please report this with the console output.")
            return {"CANCELLED"}
        context.window_manager.progress_update(int(1000 * self._job.factor))
        for area in context.screen.areas if context.screen else ():
            if area.type == "VIEW_3D":
                area.tag_redraw()
        if running:
            return {"RUNNING_MODAL"}
        self._finish(context)
        return self._job_done(context)


def stage_progress(context, label):
    """A ``progress(stage, done, total)`` callback for a synchronous job: the window's progress cursor
    (begun here, out of 1000; callers end it), and in background mode a line on stderr per stage and
    about every 10 %."""
    wm = context.window_manager
    wm.progress_begin(0, 1000)
    shown = [None, -1]

    def update(stage, done, total):
        factor = min(1.0, done / total) if total else 0.0
        wm.progress_update(int(999 * factor))
        tenth = int(10 * factor)
        if bpy.app.background and (stage, tenth) != tuple(shown) and (stage != shown[0] or tenth > shown[1]):
            shown[:] = stage, tenth
            print(f"{label}: {stage} ({int(100 * factor)} %)", file=sys.stderr, flush=True)

    return update


class FACELAB_OT_propagate(_ModalJob, bpy.types.Operator):
    """Learn how the inner lips follow the mouth from the training frames and correct every frame; the result is a small set of corrective shape keys keyed on the timeline. Esc cancels while it reads the frames"""

    bl_idname = "facelab.propagate"
    bl_label = "Propagate"
    bl_options = {"REGISTER", "UNDO"}

    frame_start: IntProperty(name="Start", default=1, options={"SKIP_SAVE"},
                             description="First frame to correct (starts at the scene's start; negative frames "
                                         "are allowed)")
    frame_end: IntProperty(name="End", default=250, options={"SKIP_SAVE"},
                           description="Last frame to correct (starts at the scene's end)")
    suggestions: IntProperty(name="Suggestions", default=3, min=0, max=50, options={"SKIP_SAVE"},
                             description="How many frames to suggest correcting next (starts at the shot's "
                                         "setting, FaceLab > Train & Propagate > Propagate Settings)")

    @classmethod
    def poll(cls, context):
        if RUNNING["job"] is not None:
            cls.poll_message_set("Propagate is already running (Esc cancels it)")
            return False
        if not poll_face(cls, context):
            return False
        if not len(face_object(context).facelab.training_frames):
            cls.poll_message_set("Correct at least one frame first (Refine Lips, or sculpt and Mark Training Frame)")
            return False
        return True

    def _settings(self, context):
        over = {"suggestions": self.suggestions} if self.properties.is_property_set("suggestions") else {}
        settings = scene_settings(context.scene, PropagateSettings, **over)
        self.suggestions = settings.suggestions  # the redo panel shows what was used
        return settings

    def _frames(self, context):
        frames = frame_range(context.scene, *operator_range(self), "Propagate")
        fill_scene_range(self, context.scene)
        return frames

    def _report_done(self, r, seconds):
        self.report({"INFO"}, wording.join([
            wording.propagate_headline(len(r.frames), seconds, r.rank, len(r.training), r.whole_weight,
                                       wording.forced_whole_reason(r.model)),
            r.note,
            f"correct next (suggested): frames {', '.join(map(str, r.suggested))}" if r.suggested else "",
            wording.expected_worse(r.expected_worse),
        ]))

    def execute(self, context):
        """Synchronous: scripts, ``blender -b``, the CLI (timers and modal handlers never run there)."""
        t0 = time.perf_counter()
        try:
            frames = self._frames(context)
            r = propagate(context.scene, face_object(context), frames,
                          self._settings(context),
                          progress=stage_progress(context, "FaceLab Propagate"))
        except FaceLabError as e:
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        finally:
            context.window_manager.progress_end()
        self._report_done(r, time.perf_counter() - t0)
        return {"FINISHED"}

    def invoke(self, context, event):
        """From a button: step through the job on a timer, progress in the panel, Esc cancels."""
        if bpy.app.background or context.window is None:
            return self.execute(context)
        self._t0 = time.perf_counter()
        try:
            frames = self._frames(context)
            steps = propagate_steps(context.scene, face_object(context), frames,
                                    self._settings(context))
        except FaceLabError as e:
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        return self._start_job(context, steps, f"Propagate {len(frames):,} frames")

    def _job_cancelled(self):
        self.report({"WARNING"}, f"Propagate cancelled while {self._job.stage} ({self._job.done:,}/"
                                 f"{self._job.total:,}); no corrective key or modifier was changed")

    def _job_done(self, context):
        self._report_done(self._job.result, time.perf_counter() - self._t0)
        return {"FINISHED"}


class FACELAB_OT_bake(_ModalJob, bpy.types.Operator):
    """Bake the corrected performance to a PC2, MDD or Alembic file for other packages (PC2/MDD: Esc cancels)"""

    bl_idname = "facelab.bake"
    bl_label = "Bake Corrected Sequence"
    bl_options = {"REGISTER"}

    filepath: StringProperty(subtype="FILE_PATH", description="The file to write")
    format: EnumProperty(name="Format", items=[("PC2", "PC2", "Point cache 2 (Mesh Cache modifier)"),
                                               ("MDD", "MDD", "Lightwave MDD (Mesh Cache modifier)"),
                                               ("ABC", "Alembic", "Alembic (Mesh Sequence Cache modifier)")],
                         default="PC2", description="File format of the baked sequence")
    overwrite: BoolProperty(name="Overwrite", default=False,
                            description="Replace an existing file (not set: the shot's setting, Bake > Settings)")

    @classmethod
    def poll(cls, context):
        if RUNNING["job"] is not None:
            cls.poll_message_set("A FaceLab job is running (Esc cancels it)")
            return False
        return poll_face(cls, context)

    def invoke(self, context, event):
        if not self.filepath:
            fmt = self.format if self.properties.is_property_set("format") else \
                scene_settings(context.scene, bake_pipeline.BakeSettings).format
            ext = bake_pipeline.FORMATS[fmt]
            self.filepath = bpy.path.abspath("//") + file_name_part(face_object(context).name) + "_corrected" + ext
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def execute(self, context):
        scene = context.scene
        path = bpy.path.abspath(self.filepath) if self.filepath.startswith("//") and bpy.data.filepath \
            else self.filepath  # an unsaved .blend keeps '//', which the bake refuses with its reason
        over = {k: getattr(self, k) for k in ("format", "overwrite") if self.properties.is_property_set(k)}
        settings = scene_settings(scene, bake_pipeline.BakeSettings, **over)
        self._t0 = time.perf_counter()
        try:
            frames = frame_range(scene, None, None, "Bake")
            steps = bake_pipeline.bake_steps(face_object(context), frames, path, settings)
            if settings.format != "ABC" and not bpy.app.background and context.window is not None:
                return self._start_job(context, steps, f"Bake {settings.format}")  # after the file browser
            frame_done = None
            if settings.format != "ABC":  # one call of Blender's exporter: no progress to show
                frame_done = progress_callback(context, len(frames), f"FaceLab Bake {settings.format}")
            r = run_steps(steps, frame_done and (lambda stage, done, total: frame_done(done, total)))
        except FaceLabError as e:
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        finally:
            if RUNNING["job"] is None:
                context.window_manager.progress_end()
        return self._report_baked(r)

    def _report_baked(self, r):
        self.report({"INFO"}, f"Baked {r.frames:,} frames of '{r.object}' to {r.path} in "
                              f"{time.perf_counter() - self._t0:.1f} s")
        return {"FINISHED"}

    def _job_cancelled(self):
        self.report({"WARNING"}, f"Bake cancelled after {self._job.done:,} of {self._job.total:,} frames; "
                                 "no file was written")

    def _job_done(self, context):
        return self._report_baked(self._job.result)


classes = (
    FACELAB_OT_auto_regions,
    FACELAB_OT_mark_training_frame,
    FACELAB_OT_remove_training_frame,
    FACELAB_OT_jump_training_frame,
    FACELAB_OT_jump_to_frame,
    FACELAB_OT_propagate,
    FACELAB_OT_bake,
)


register, unregister = bpy.utils.register_classes_factory(classes)
