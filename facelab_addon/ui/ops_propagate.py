"""Operators for regression propagation (Dinev et al. 2018 §4): regions, training
frames, Propagate, bakes. They gather inputs, call core, write, report."""

import sys
import time
from pathlib import Path

import bpy
import numpy as np
from bpy.props import BoolProperty, EnumProperty, IntProperty, StringProperty

from ..blender import caches
from ..blender.mesh import mesh_triangles, require_mesh, vertex_group_mask
from ..blender.shapekeys import add_keys_from_deltas, key_property_bulk, key_values_bulk, remove_keys, rest_vertices
from ..core.capture.cachefile import integrate_matrices, integrate_offsets_to_key
from ..core.errors import FaceLabError, RegionError
from ..core.geometry.compress import compress
from ..core.lips.propagate import LipRegressor, suggest_frames
from ..core.lips.regions import auto_regions, faces_in_region, inner_lip_loop, loop_width, validate_regions
from .ops import face_object, poll_face, progress_callback, record_training_frame
from .prefs import REGION_DEFAULTS

PROP_PREFIX = "FL_Prop_"
SUGGEST_MARKER = "FL suggest"
EXTRAPOLATION_PROP = "FL_extrapolation"
MOUTH_GROUP, LIPS_GROUP = "FL_mouth", "FL_lips"

# Fitted regressors kept between Propagate runs, so adding a frame is incremental.
_REGRESSORS: dict = {}


def region_faces(obj, tris):
    """(mouth_faces, lip_faces) from the FL_mouth / FL_lips vertex groups, validated."""
    mouth = vertex_group_mask(obj, MOUTH_GROUP)
    lips = vertex_group_mask(obj, LIPS_GROUP)
    missing = [g for g, m in ((MOUTH_GROUP, mouth), (LIPS_GROUP, lips)) if m is None]
    if missing:
        raise RegionError(
            f"'{obj.name}' has no vertex group {' or '.join(missing)}; press Auto Regions (or paint the "
            "groups: FL_mouth = trusted mouth area, FL_lips = inner lips to predict)."
        )
    mf, lf = faces_in_region(tris, mouth), faces_in_region(tris, lips)
    validate_regions(tris, mf, lf, len(obj.data.vertices))
    return mf, lf


def training_frames(obj):
    """Sorted unique training frames whose correction still exists."""
    key = obj.data.shape_keys
    names = set(key.key_blocks.keys()) if key else set()
    frames = {t.frame for t in obj.facelab.training_frames if t.source != "sketch" or t.shape_key in names}
    return sorted(frames)




class FACELAB_OT_auto_regions(bpy.types.Operator):
    """Propose the trusted mouth region (FL_mouth) and the inner-lip region to predict (FL_lips) as geodesic bands around the inner-lip contact loop; refine them by weight painting"""

    bl_idname = "facelab.auto_regions"
    bl_label = "Auto Regions"
    bl_options = {"REGISTER", "UNDO"}

    replace: BoolProperty(name="Replace Existing Groups", default=False,
                          description="Overwrite FL_mouth / FL_lips if they exist (otherwise refuse)")
    use_selection: BoolProperty(name="Use Selected Edge Loop", default=False,
                                description="Take the inner-lip loop from the selected vertices instead of finding it")

    @classmethod
    def poll(cls, context):
        return poll_face(cls, context)

    def execute(self, context):
        obj = face_object(context)
        if context.mode == "EDIT_MESH":
            bpy.ops.object.mode_set(mode="OBJECT")
        existing = [g for g in (MOUTH_GROUP, LIPS_GROUP) if obj.vertex_groups.get(g) is not None]
        if existing and not self.replace:
            self.report({"ERROR"}, f"{', '.join(existing)} already exist on '{obj.name}'; enable 'Replace Existing "
                                   "Groups' to overwrite them, or edit them by weight painting.")
            return {"CANCELLED"}
        try:
            require_mesh(obj)
            tris = mesh_triangles(obj.data)
            V = rest_vertices(obj)
            loop = None
            if self.use_selection:
                sel = np.zeros(len(V), bool)
                obj.data.vertices.foreach_get("select", sel)
                loop = np.flatnonzero(sel)
                if len(loop) < 4:
                    raise RegionError("Select the inner-lip edge loop (at least 4 vertices) in Edit Mode first.")
            loop = inner_lip_loop(V, tris, loop)
            width = loop_width(V, loop)  # band widths: fractions of the mouth width (assets/presets/regions.json)
            mouth, lips = auto_regions(V, tris, loop=loop, lip_width=REGION_DEFAULTS["lip_width"] * width,
                                       mouth_width=REGION_DEFAULTS["mouth_width"] * width)
        except FaceLabError as e:
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        for name, mask in ((MOUTH_GROUP, mouth), (LIPS_GROUP, lips)):
            vg = obj.vertex_groups.get(name)
            if vg is not None:
                obj.vertex_groups.remove(vg)
            vg = obj.vertex_groups.new(name=name)
            vg.add(np.flatnonzero(mask).tolist(), 1.0, "REPLACE")
        self.report({"INFO"}, f"Regions on '{obj.name}': {int(mouth.sum())} mouth and {int(lips.sum())} inner-lip "
                              f"vertices (vertex groups {MOUTH_GROUP}, {LIPS_GROUP})")
        return {"FINISHED"}


class FACELAB_OT_mark_training_frame(bpy.types.Operator):
    """Use the current frame's mesh (for example corrected by sculpting a shape key) as a training frame for propagation"""

    bl_idname = "facelab.mark_training_frame"
    bl_label = "Mark Training Frame"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        if not poll_face(cls, context):
            return False
        f = context.scene.frame_current
        if f in {t.frame for t in face_object(context).facelab.training_frames}:
            cls.poll_message_set(f"Frame {f} is already a training frame")
            return False
        return True

    def execute(self, context):
        obj, f = face_object(context), context.scene.frame_current
        record_training_frame(context.scene, obj, f, "", "sculpt")
        self.report({"INFO"}, f"Frame {f} marked as a training frame of '{obj.name}'")
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

    frame: IntProperty(name="Frame")

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
        tf = obj.facelab.training_frames
        i = selected_training_index(obj)
        frame, removed_key = tf[i].frame, tf[i].shape_key
        tf.remove(i)
        obj.facelab.active_training_index = max(0, i - 1)
        if frame not in {t.frame for t in tf}:
            for m in list(context.scene.timeline_markers):
                if m.frame == frame and m.name.startswith("FL train"):
                    context.scene.timeline_markers.remove(m)
        kept = f" (its shape key '{removed_key}' is kept)" if removed_key else ""
        self.report({"INFO"}, f"Removed training frame {frame}{kept}; Propagate again to update the correction")
        return {"FINISHED"}


class StepJob:
    """Drives a long job written as a generator of ``(stage, done, total)`` steps, one step per call,
    so a modal operator can run it on timer events (progress in the panel, Esc cancels between
    steps) while scripts, ``blender -b`` and the CLI run the same generator to the end at once.
    Nothing but plain Python: testable headless, where timers and modal handlers never run."""

    def __init__(self, steps):
        self._steps = steps
        self.stage, self.done, self.total = "starting", 0, 1
        self.result = None
        self.finished = False

    @property
    def factor(self) -> float:
        return min(1.0, self.done / self.total) if self.total else 0.0

    def step(self) -> bool:
        """Run one step; False once the job has finished (``result`` holds its return value)."""
        try:
            self.stage, self.done, self.total = next(self._steps)
            return True
        except StopIteration as stop:
            self.result, self.finished = stop.value, True
            return False

    def run(self, progress=None):
        """Run every remaining step; ``progress(done, total)`` after each. Returns the result."""
        while self.step():
            if progress is not None:
                progress(self.done, self.total)
        return self.result

    def cancel(self) -> None:
        """Stop between two steps (the generator's ``finally`` blocks run)."""
        self._steps.close()


# The job a modal operator (Propagate, Bake) is running, for the panel's progress bar (None when idle).
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
        except FaceLabError as e:
            self._finish(context)
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        context.window_manager.progress_update(int(1000 * self._job.factor))
        for area in context.screen.areas if context.screen else ():
            if area.type == "VIEW_3D":
                area.tag_redraw()
        if running:
            return {"RUNNING_MODAL"}
        self._finish(context)
        return self._job_done(context)


class FACELAB_OT_propagate(_ModalJob, bpy.types.Operator):
    """Learn how the inner lips follow the mouth from the training frames (Dinev et al. 2018 §4) and correct every frame; the result is a small set of corrective shape keys keyed on the timeline. Esc cancels while it reads the frames"""

    bl_idname = "facelab.propagate"
    bl_label = "Propagate"
    bl_options = {"REGISTER", "UNDO"}

    frame_start: IntProperty(name="Start", default=-1, description="First frame (-1: the scene's start)")
    frame_end: IntProperty(name="End", default=-1, description="Last frame (-1: the scene's end)")
    suggestions: IntProperty(name="Suggestions", default=3, min=0, max=20,
                             description="How many frames to suggest correcting next")

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

    def _frames(self, context):
        scene = context.scene
        f0 = scene.frame_start if self.frame_start < 0 else self.frame_start
        f1 = scene.frame_end if self.frame_end < 0 else self.frame_end
        return np.arange(f0, f1 + 1)

    def _report_done(self, frames, summary, seconds):
        self.report(
            {"INFO"},
            f"Propagated to {len(frames):,} frames in {seconds:.1f} s, {summary['rank']} corrective "
            f"shapes from {summary['training']} training frames"
            + (f"; {summary['note']}" if summary["note"] else "")
            + (f"; suggested next: {', '.join(map(str, summary['suggested']))}" if summary["suggested"] else ""),
        )

    def execute(self, context):
        """Synchronous: scripts, ``blender -b``, the CLI (timers and modal handlers never run there)."""
        obj = face_object(context)
        t0 = time.perf_counter()
        frames = self._frames(context)
        try:
            summary = propagate(context, obj, frames, self.suggestions)
        except FaceLabError as e:
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        finally:
            context.window_manager.progress_end()
        self._report_done(frames, summary, time.perf_counter() - t0)
        return {"FINISHED"}

    def invoke(self, context, event):
        """From a button: step through the job on a timer, progress in the panel, Esc cancels."""
        if bpy.app.background or context.window is None:
            return self.execute(context)
        self._frames_run, self._t0 = self._frames(context), time.perf_counter()
        steps = propagate_steps(context, face_object(context), self._frames_run, self.suggestions)
        return self._start_job(context, steps, f"Propagate {len(self._frames_run):,} frames")

    def _job_cancelled(self):
        self.report({"WARNING"}, f"Propagate cancelled while {self._job.stage} ({self._job.done:,}/"
                                 f"{self._job.total:,}); no corrective key was changed")

    def _job_done(self, context):
        self._report_done(self._frames_run, self._job.result, time.perf_counter() - self._t0)
        return {"FINISHED"}


def propagate(context, obj, frames, n_suggest=3) -> dict:
    """Fit (or update) the regressor, predict every frame, write corrective keys. Returns a summary.

    Runs :func:`propagate_steps` to the end at once, with the window's progress (and a line on
    stderr per stage and every 10 % in background mode)."""
    wm = context.window_manager
    wm.progress_begin(0, 1000)
    job = StepJob(propagate_steps(context, obj, frames, n_suggest))
    shown = (None, -1)
    while job.step():
        wm.progress_update(int(999 * job.factor))
        tenth = int(10 * job.factor)
        if bpy.app.background and (job.stage, tenth) != shown and (job.stage != shown[0] or tenth > shown[1]):
            shown = (job.stage, tenth)
            print(f"FaceLab Propagate: {job.stage} ({int(100 * job.factor)} %)", file=sys.stderr, flush=True)
    return job.result


def _chunks(n, size):
    return [(i, min(n, i + size)) for i in range(0, n, size)]


def propagate_steps(context, obj, frames, n_suggest=3):
    """Propagate as a generator: yields ``(stage, done, total)`` between steps and returns the summary.

    Steps: read the capture in chunks of frames; fit; predict in chunks; (a cache: map every frame's
    correction onto the cache surface); compress and write. Nothing in the scene changes before the
    last step, except that a Mesh Cache is switched to Integrate (or an Alembic baked to a PC2) first,
    so cancelling between steps leaves the corrective keys as they were."""
    scene = context.scene
    require_mesh(obj)
    tris = mesh_triangles(obj.data)
    mouth_faces, lip_faces = region_faces(obj, tris)
    train = training_frames(obj)
    if len(train) < 1:
        raise FaceLabError("No training frame: correct at least one frame (Refine Lips, or sculpt and Mark Training Frame).")
    outside = [f for f in train if f < frames[0] or f > frames[-1]]
    if outside:
        raise FaceLabError(f"Training frames {outside} lie outside the range {frames[0]}-{frames[-1]}; widen the range.")
    T = len(frames)
    # progress units: T frames read + T predicted (+ T mapped onto a cache) + 2 (fit, write)
    source = caches.sequence_source(obj)
    on_cache = source in ("mesh_cache", "mesh_sequence_cache")
    total = 2 * T + 2 + (T if on_cache else 0)
    note = ""
    if on_cache:
        note = caches.cache_to_shape_key_ready(obj, scene_frames=frames)
    rest = rest_vertices(obj)
    chunk = max(4, T // 40)
    captured = np.empty((T, len(rest), 3), np.float32)
    for i, j in _chunks(T, chunk):
        yield "reading the capture", i, total
        captured[i:j] = caches.read_captured_frames(obj, frames[i:j])  # FaceLab keys muted
    yield "fitting", T, total
    corrected = caches.evaluate_frames(obj, train, mute_shape_keys_prefix=(PROP_PREFIX,))
    reg = _regressor(obj, rest, tris, mouth_faces, lip_faces, train, corrected)

    lipv = np.unique(tris[lip_faces])
    before = captured[:, lipv].astype(np.float64)
    for i, j in _chunks(T, max(chunk, 16)):
        yield "predicting", T + 1 + i, total
        reg.predict(captured[i:j], out=captured[i:j])  # in place: 1000 frames stay within memory
    pred = captured
    corr = (pred[:, lipv] - before).astype(np.float64)  # (T, n_lip, 3) correction, object local
    corr[np.isin(frames, train)] = 0.0  # training frames keep the artist's own correction
    if on_cache:  # keys ride on the cache surface (INTEGRATE): map each frame's offsets through it
        sub_off, sub_cv = _polygons_around(caches.polygon_corners(obj.data), lipv)
        for t in range(T):
            if t % 4 == 0:
                yield "mapping onto the cache", 2 * T + 1 + t, total
            if np.any(corr[t]):
                M = integrate_matrices(rest, before_full(pred[t], lipv, before[t]), sub_off, sub_cv)[lipv]
                corr[t] = integrate_offsets_to_key(M, corr[t])
    yield "writing the corrective keys", total - 1, total
    basis_lip, weights = compress(corr, metres_per_unit=scene.unit_settings.scale_length or 1.0)
    remove_keys(obj, PROP_PREFIX)
    names = []
    if len(basis_lip):
        basis = np.zeros((len(basis_lip), len(rest), 3))
        basis[:, lipv] = basis_lip
        names = add_keys_from_deltas(obj, PROP_PREFIX, basis)
        key_values_bulk(obj, names, frames, weights)
    # where the model guesses: the extrapolation score keyed on the object, suggestions as markers.
    # Mouth features are computed once (mouth triangles never touch the predicted interior lip vertices).
    feats = reg.mouth_features(pred)
    score = reg.extrapolation(features=feats)
    obj[EXTRAPOLATION_PROP] = 0.0
    key_property_bulk(obj, f'["{EXTRAPOLATION_PROP}"]', frames, score)
    for m in [m for m in scene.timeline_markers if m.name.startswith(SUGGEST_MARKER)]:
        scene.timeline_markers.remove(m)
    suggested = []
    if n_suggest:
        idx = suggest_frames(None, n_suggest, regressor=reg, exclude=np.flatnonzero(np.isin(frames, train)),
                             features=feats, overwrite_features=True)
        suggested = [int(frames[i]) for i in idx]
        for f in suggested:
            scene.timeline_markers.new(f"{SUGGEST_MARKER} {f}", frame=f)
    obj.data.update()
    return dict(rank=len(names), training=len(train), suggested=suggested, note=note,
                extrapolation=score, keys=names)


def _polygons_around(corners, verts):
    """``(face_offsets, corner_verts)`` of only the polygons touching ``verts``.

    The Integrate map of a vertex averages over its own corners, all in polygons that touch it, so
    on this subset it is exactly the whole mesh's (``core.capture.cachefile.integrate_matrices``), at a
    fraction of the cost: the lips are ~4 % of a face."""
    offs, cv = corners
    sizes = np.diff(offs)
    face_of = np.repeat(np.arange(len(sizes)), sizes)
    touch = np.zeros(len(sizes), bool)
    touch[face_of[np.isin(cv, verts)]] = True
    return np.r_[0, np.cumsum(sizes[touch])], cv[touch[face_of]]


def before_full(pred_t, lipv, before_t):
    """The captured frame: the prediction with the lip vertices put back."""
    out = np.array(pred_t, dtype=np.float64)
    out[lipv] = before_t
    return out


def _regressor(obj, rest, tris, mouth_faces, lip_faces, train, corrected):
    """The fitted regressor for these regions and training frames, updated incrementally when
    the previous fit's frames (same corrections) are a subset of ``train``."""
    key = (obj.name, len(rest), hash(tris.tobytes()), hash(mouth_faces.tobytes()), hash(lip_faces.tobytes()),
           hash(rest.tobytes()))
    cached = _REGRESSORS.get(key)
    if cached is not None:
        reg, fit_frames, fit_data = cached
        row = {f: i for i, f in enumerate(train)}
        same = all(f in row and np.array_equal(fit_data[j], corrected[row[f]]) for j, f in enumerate(fit_frames))
        if same:
            new = [row[f] for f in train if f not in set(fit_frames)]
            if new:
                reg.add(corrected[new])  # incremental: only the new frames
                order = list(fit_frames) + [train[i] for i in new]
                _REGRESSORS[key] = (reg, order, np.concatenate([fit_data, corrected[new]]))
            return reg
    reg = LipRegressor(rest, tris, mouth_faces, lip_faces)
    reg.fit(corrected)
    _REGRESSORS.clear()  # keep one model in memory
    _REGRESSORS[key] = (reg, list(train), corrected)
    return reg


def bake_steps(obj, frames, path, fmt):
    """A PC2 or MDD bake of the evaluated mesh as a generator, one frame a step; returns the path.

    Same file as ``blender.caches.bake_pc2`` / ``bake_mdd`` (header, object-local positions). The
    writer writes beside the destination and moves the file in place at the end, so cancelling
    (closing the generator) leaves an existing file untouched; the scene frame is restored."""
    from ..core.capture import cachefile

    frames = np.asarray(frames, dtype=np.float64)
    n = len(obj.data.vertices)
    if fmt == "PC2":
        step = caches._uniform_step(frames, "A PC2 bake")
        w = cachefile.PointCacheWriter(str(path), "PC2", n, len(frames), start_frame=float(frames[0]),
                                       sample_rate=step)
    else:
        if len(frames) > 1 and not (np.diff(frames) > 0).all():
            raise FaceLabError("An MDD bake needs increasing scene frames.")
        w = cachefile.PointCacheWriter(str(path), "MDD", n, len(frames), times=frames / caches.scene_fps())
    it = caches._iter_evaluated(obj, frames)
    ok = False
    try:
        for i, co in it:
            w.write(co)
            yield f"baking frame {int(frames[i])}", i + 1, len(frames)
        ok = True
    finally:
        it.close()  # restores the scene frame
        if not ok:
            w.abort()
    return w.close()


class FACELAB_OT_bake(_ModalJob, bpy.types.Operator):
    """Bake the corrected performance to a PC2, MDD or Alembic file for other packages (PC2/MDD: Esc cancels)"""

    bl_idname = "facelab.bake"
    bl_label = "Bake Corrected Sequence"
    bl_options = {"REGISTER"}

    filepath: StringProperty(subtype="FILE_PATH")
    format: EnumProperty(items=[("PC2", "PC2", ""), ("MDD", "MDD", ""), ("ABC", "Alembic", "")], default="PC2")
    overwrite: BoolProperty(name="Overwrite", default=False)

    @classmethod
    def poll(cls, context):
        if RUNNING["job"] is not None:
            cls.poll_message_set("A FaceLab job is running (Esc cancels it)")
            return False
        return poll_face(cls, context)

    def invoke(self, context, event):
        if not self.filepath:
            ext = {"PC2": ".pc2", "MDD": ".mdd", "ABC": ".abc"}[self.format]
            self.filepath = bpy.path.abspath("//") + face_object(context).name + "_corrected" + ext
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def execute(self, context):
        obj, scene = face_object(context), context.scene
        path = Path(bpy.path.abspath(self.filepath))
        if not self.filepath:
            self.report({"ERROR"}, "Choose a file to bake to.")
            return {"CANCELLED"}
        if path.exists() and not self.overwrite:
            self.report({"ERROR"}, f"{path} exists; enable Overwrite or choose another file.")
            return {"CANCELLED"}
        self._frames_run = np.arange(scene.frame_start, scene.frame_end + 1)
        self._obj, self._t0 = obj, time.perf_counter()
        try:
            if self.format == "ABC":  # one call of Blender's exporter: not steppable
                out = caches.bake_alembic(obj, self._frames_run, path)
                return self._report_baked(out)
            caches._require_mesh_object(obj)
            steps = bake_steps(obj, self._frames_run, path, self.format)
            if not bpy.app.background and context.window is not None:  # after the file browser
                return self._start_job(context, steps, f"Bake {self.format}")
            job = StepJob(steps)
            prog = progress_callback(context, len(self._frames_run), f"FaceLab Bake {self.format}")
            out = job.run(prog)
        except FaceLabError as e:
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        finally:
            if RUNNING["job"] is None:
                context.window_manager.progress_end()
        return self._report_baked(out)

    def _report_baked(self, out):
        self.report({"INFO"}, f"Baked {len(self._frames_run):,} frames of '{self._obj.name}' to {out} in "
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
