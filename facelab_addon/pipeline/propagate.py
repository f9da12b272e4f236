"""Propagate: learn how the inner lips follow the mouth from the corrected frames and correct every frame
(Dinev et al. 2018 §4).

Training data is scene data: every corrected frame is recorded on the face object
(``obj.facelab.training_frames``) and marked on the timeline (:mod:`.training`). A training frame is one definition,
written by one function (:func:`store_training_frame`, for Refine Lips, :func:`add_corrected_frame`
and :func:`.training.mark_training_frame`) and read by one (:func:`.training.read_training_frames`): the corrected shape
relative to the frame without FaceLab's lip corrections (:func:`.training.uncorrected_frame`), as a key keyed
on the frame alone, with Propagate's correction off there; so a frame keeps what the viewport
showed after Refine (or the sculpt) through every later Propagate. :func:`propagate_steps`
reads the captured sequence, fits a :class:`~facelab_addon.core.lips.regressor.LipRegressor`
on the training frames, corrects the inner lips of every frame a chunk at a time
(:class:`~facelab_addon.core.lips.shot.ShotCorrector`) and writes the per-frame
correction as a few compressed corrective keys ``FL_Prop_NN``
(:data:`~facelab_addon.names.PROPAGATE_PREFIX`), plus the extrapolation score keyed on the
object and suggested frames as timeline markers. Over a capture cache, where the key offsets
(carried by the cache surface) need more shapes than keys can hold, the correction is instead
written as a point cache of the corrected vertices, added after the capture
(:class:`~facelab_addon.pipeline.correctives.CorrectionWriter` ``after_capture``).

The regressor is fitted afresh on every run (the fit is a small part of a Propagate; see
``docs/benchmarks.md``), so no fitted model is kept between runs and a changed mesh, region or
training set can never be served stale.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ..blender import bakes, cache_integrate, caches
from ..blender.capture_stream import CaptureReader
from ..blender.mesh import face_topology, require_mesh, spread_key_offsets
from ..blender.objects import ModifierState, local_length, require_editable, tolerance_length
from ..blender.scene_time import require_scene_time
from ..blender.shapekeys import key_property_bulk, rest_vertices
from ..core.errors import FaceLabError, FrameError
from ..core.geometry.compress import StorageOutcome
from ..core.lips.regressor import LipRegressor
from ..core.lips.shot import ShotCorrector, expected_worse, key_shapes_over_cache
from ..names import EXTRAPOLATION_ACTION, EXTRAPOLATION_PROP, PROPAGATE_PREFIX, STORE_SETTINGS_ATTR, SUGGEST_MARKER
from .correctives import CorrectionWriter, StorageSettings, StoredKeys
from .frames import check_frames
from .regions import region_faces
from .settings import setting, stored
from .steps import run_steps
from .training import captured_unknown, read_training_frames, require_finite, training_frames

__all__ = ["PropagateSettings", "PropagateResult", "propagate_steps", "propagate", "training_input", "model_summary"]

_CACHE_SOURCES = ("mesh_cache", "mesh_sequence_cache")
#: Fewest training frames for the leave-one-out ridge (``PropagateSettings.ridge``): from fewer, leaving one out
#: says too little, and the shrunk maps undercorrect.
LOO_MIN_FRAMES = 5
#: A frame is reported as expected worse than its capture past this expected RMS increase, world mm.
WORSE_MM = 0.01
_CHUNK = 256  # frames per streamed chunk: working memory ~ chunk x (mouth + lip vertices), not the shot
_SHOT_SAMPLE = 64  # frames of the shot read before the fit for the "auto" model choice
_WELD_SAMPLE = 16  # frames of the shot (besides the training frames) on which split-seam twins must coincide


@dataclass
class PropagateSettings:
    """How :func:`propagate` runs.

    Attributes
    ----------
    suggestions : int
        How many frames to suggest correcting next (timeline markers).
    model : {"auto", "whole", "correction"}
        What the regression learns (``LipRegressor`` ``model``): the lips' whole motion (the paper), only
        the correction of the captured lips, or ("auto") the blend of the two with the smallest error
        expected on the shot, estimated from the training frames and the shot itself
        (:mod:`~facelab_addon.core.lips.regressor.model_choice`).
    damping : bool
        Scale each frame's predicted correction by ``|c|² / (|c|² + S)``, ``S`` the error the fitted model is
        expected to make on that frame by extrapolating beyond the training frames (``LipRegressor``
        ``damping``): a frame where the prediction is no more certain than it is large keeps most of its
        capture. On (default); off: every frame gets the full prediction (the paper).
    ridge : {"loo", "none"}
        ``LipRegressor`` ``ridge``: ``"loo"`` (each local map's ridge weight by leave-one-out over the training
        frames, from :data:`LOO_MIN_FRAMES` training frames on; 0 with fewer) or ``"none"`` (0, the paper).
    """

    suggestions: int = setting(3, label="Suggestions", min=0, max=50,
                               description="How many frames to suggest correcting next (timeline markers)")
    model: str = setting("auto", label="Model", choices=(
        ("auto", "Auto", "Blend the two models by the error each is expected to make on this shot "
                         "(from the training frames and the shot)"),
        ("whole", "Whole Motion", "Learn the lips' whole motion from the mouth; needs training "
                                  "frames that span the shot's expressions"),
        ("correction", "Correction", "Learn only the correction and add it to the captured lips; works from "
                                     "few frames, keeps capture errors that do not follow the mouth")),
        description="What Propagate learns from the training frames: the lips' whole motion, only the "
                    "correction, or an automatic blend")
    ridge: str = setting("loo", label="Regularization", choices=(
        ("loo", "Leave-One-Out", "From 5 training frames on, shrink each local map toward zero by the ridge weight "
                                 "whose leave-one-out error over the training frames is smallest: near-duplicate "
                                 "training poses with different corrections no longer make the model extrapolate "
                                 "wildly"),
        ("none", "None", "The least-squares maps of the paper")),
        description="How the regression is regularized (LipRegressor ridge)")
    damping: bool = setting(True, label="Damp Uncertain Frames",
                            description="Shrink each frame's correction toward the capture by how uncertain the "
                                        "model is there (its expected error, from the training frames and the "
                                        "frame's distance from them): well-captured frames far from the training "
                                        "poses are damaged less")


@dataclass
class PropagateResult:
    """What :func:`propagate` did.

    Attributes
    ----------
    object : str
        The face object's name.
    frames : (T,) int ndarray
        The frames corrected.
    keys : list of str
        The ``FL_Prop_*`` corrective keys written (empty when no frame needed a correction).
    training : list of int
        The training frames the regressor learnt from (their own correction is kept: zero there).
    suggested : list of int
        Frames suggested for correction next (also timeline markers), best first.
    extrapolation : (T,) float ndarray
        How far each frame's mouth lies outside the training poses (also keyed on the object).
    expected_worse : list of int
        Frames whose inner lips the correction is expected to leave worse than captured by more than
        :data:`WORSE_MM` (``LipRegressor.expected_change``), the worst first: the frames to check, or to
        correct next.
    note : str
        What was changed so the keys show over a cache (empty for shape-key animation).
    model : str
        The model used, e.g. ``"auto: 9% whole motion + 91% correction"`` (see :class:`PropagateSettings`).
    whole_weight : float
        Weight of the whole-motion model in the blend (1: whole motion, 0: correction).
    seconds : float
        From the call to the last step.
    """

    object: str
    frames: np.ndarray
    keys: list = field(default_factory=list)
    training: list = field(default_factory=list)
    suggested: list = field(default_factory=list)
    extrapolation: np.ndarray = None
    expected_worse: list = field(default_factory=list)
    note: str = ""
    model: str = ""
    whole_weight: float = 1.0
    seconds: float = 0.0

    @property
    def rank(self) -> int:
        """Number of corrective shapes written."""
        return len(self.keys)


# --------------------------------------------------------------------------- propagate
def propagate(scene, obj, frames, settings: PropagateSettings | None = None, progress=None, *,
              chunk: int | None = None) -> PropagateResult:
    """Fit the regressor on the training frames, predict every frame, write the corrective keys.

    Runs :func:`propagate_steps` to the end at once.

    Parameters
    ----------
    scene : bpy.types.Scene
    obj : bpy.types.Object
        The face mesh, with region groups and training frames.
    frames : (T,) int array_like
        Consecutive scene frames to correct; every training frame must be among them.
    settings : PropagateSettings, optional
    progress : callable(label, done, total), optional
        Called after each step.
    chunk : int, optional
        Frames read, corrected and compressed at a time (memory is bounded by the chunk, not
        the shot; the result does not depend on it). Default: a 40th of the shot (a step of
        the progress bar), at least 4 and at most 256 frames.

    Returns
    -------
    PropagateResult
    """
    return run_steps(propagate_steps(scene, obj, frames, settings, chunk=chunk), progress)


def propagate_steps(scene, obj, frames, settings: PropagateSettings | None = None, *, chunk: int | None = None):
    """Propagate as a generator: yields ``(stage, done, total)`` between steps and returns a :class:`PropagateResult`.

    The input is checked by this call (errors are raised before any step);
    the steps then fit on the training frames and stream the shot a chunk of
    frames at a time: read only the mouth and lip vertices
    (:class:`~facelab_addon.blender.capture_stream.CaptureReader`), predict the
    interior lip correction, (over a cache: map it onto the cache surface), add it to
    a :class:`~facelab_addon.core.lips.regressor.reduced.StreamingBasis` and score the
    mouth; then write the few shapes and their weights. Memory is bounded by
    the chunk, not the shot. Nothing in the scene changes before the last step,
    except that a Mesh Cache is switched to Integrate (or an Alembic baked to
    a PC2) first; closing the generator between steps (a cancel) or an error
    in a step puts the modifiers back as they were (and deletes such a PC2)
    and leaves the corrective keys as they were.

    Parameters
    ----------
    scene, obj, frames, settings, chunk
        As :func:`propagate`.

    Returns
    -------
    generator

    Raises
    ------
    RegionError
        Region groups missing or unusable.
    FaceLabError
        No frames, frames not one increasing range, no training frame, or
        training frames outside ``frames``; ``NotEditableError`` when ``obj``
        is linked from a library.
    MeshError
        ``obj`` is not a mesh with faces; (in a step) a captured or corrected
        frame with NaN coordinates, named by its scene frame.
    """
    settings = settings or PropagateSettings()
    t0 = time.perf_counter()
    frames = check_frames(frames, "Propagate", consecutive=True)
    require_mesh(obj)
    require_editable(obj, "Propagate")
    require_scene_time(scene, "Propagate", obj)
    train = training_frames(obj)
    # a mesh split along its UV seams is one surface: twins that coincide at rest, in every key and on the training
    # frames and a sample of the shot (read only when the mesh has coincident vertices) are welded
    topo = face_topology(obj, _weld_poses(obj, frames, train))
    tris = topo.tris
    mouth_faces, lip_faces = region_faces(obj, tris)
    if len(train) < 1:
        raise FaceLabError("No training frame: correct at least one frame (Refine Lips, or sculpt and Mark Training Frame).")
    outside = [f for f in train if f < frames[0] or f > frames[-1]]
    if outside:
        raise FaceLabError(f"Training frames {outside} lie outside the range {frames[0]}-{frames[-1]}; widen the range.")
    unknown = captured_unknown(obj, train) if settings.model == "correction" else []
    if unknown:
        raise FaceLabError(
            f"Model 'Correction' learns corrected minus captured lips, but training frame(s) {unknown[:5]} were "
            "sculpted in place (Mark Training Frame), so their capture is unknown. Use Model 'Auto' or 'Whole "
            "Motion', or correct those frames with Refine Lips or Add Corrected Frame.")
    chunk = min(_CHUNK, max(4, len(frames) // 40)) if chunk is None else chunk
    if int(chunk) < 1:
        raise FaceLabError(f"Propagate: chunk must be at least 1 frame, got {chunk}; use the default {_CHUNK}.")
    return _propagate_steps(_Job(scene, obj, frames, settings, topo, mouth_faces, lip_faces, train, int(chunk), t0))


def _chunks(n, size):
    return [(i, min(n, i + size)) for i in range(0, n, size)]


def _weld_poses(obj, frames, train):
    """The captured frames twins must coincide on to be welded: the training frames and an even sample of
    ``frames`` (object-local, FaceLab's keys muted), evaluated one at a time when asked for."""
    pick = frames[np.unique(np.linspace(0, len(frames) - 1, min(len(frames), _WELD_SAMPLE)).round().astype(int))]
    for f in np.union1d(pick, np.asarray(train, dtype=frames.dtype)):
        yield caches.evaluate_frames(obj, [f])[0]


@dataclass
class _Job:
    """One checked Propagate call (:func:`propagate_steps`): what its steps work on.

    ``frames`` (T,) int the consecutive scene frames; ``topo`` the mesh's ``face_topology`` (triangles, split-seam
    weld); ``mouth_faces``/``lip_faces`` triangle ids of the regions; ``train`` the training frames (scene frames);
    ``chunk`` frames read and corrected at a time; ``t0`` the call's ``perf_counter``.
    """

    scene: object
    obj: object
    frames: np.ndarray
    settings: PropagateSettings
    topo: object
    mouth_faces: np.ndarray
    lip_faces: np.ndarray
    train: list
    chunk: int
    t0: float


def _propagate_steps(job: _Job):
    state = ModifierState(job.obj)
    done = False
    try:
        result = yield from _propagate_work(job)
        done = True
        return result
    finally:
        if not done:  # cancelled (the generator closed) or failed: put the modifiers back
            state.restore()


def _propagate_work(job: _Job):
    scene, obj, frames, settings, topo, train = job.scene, job.obj, job.frames, job.settings, job.topo, job.train
    T = len(frames)
    total = T + 2  # progress units: fit, T frames corrected, write
    on_cache = caches.sequence_source(obj) in _CACHE_SOURCES
    storage = stored(scene, STORE_SETTINGS_ATTR, StorageSettings)
    if on_cache and T > key_shapes_over_cache(storage.key_budget):
        # over a captured cache a long shot's correction goes to a point cache: refuse an unsaved .blend without a
        # cache folder now, before the scene changes, not after every frame was corrected
        bakes.correction_cache_path(obj, PROPAGATE_PREFIX, str(storage.cache_format).upper(),
                                    storage.cache_directory or None)
    note = cache_integrate.cache_to_shape_key_ready(obj, scene_frames=frames) if on_cache else ""
    yield "fitting", 0, total
    rest = rest_vertices(obj)
    # a mesh split along seams: the regression sees the welded surface alone (no duplicates), ``kept`` its vertices
    kept = topo.weld.kept if topo.n_duplicates else None
    rest_w, tris_w = (rest, topo.tris) if kept is None else topo.weld.compact(rest)
    corrected = read_training_frames(obj, train)
    require_finite(corrected, train, "corrected (training)")
    unknown = captured_unknown(obj, train)
    model = "whole" if unknown and settings.model == "auto" else settings.model
    reg = LipRegressor(rest_w, tris_w, job.mouth_faces, job.lip_faces, model=model, damping=bool(settings.damping),
                       ridge="loo" if settings.ridge == "loo" and len(train) >= LOO_MIN_FRAMES else 0.0)
    captured_train = caches.read_captured_frames(obj, list(train)).astype(np.float64)  # FaceLab keys muted
    require_finite(captured_train, train, "captured (training)")
    if kept is not None:
        corrected, captured_train = corrected[:, kept], captured_train[:, kept]
    corrected = training_input(captured_train, corrected, reg.interior_vertices)
    # Only the mouth and lip vertices are read (plus, over a cache, the polygons around the interior lips).
    iv, used = reg.interior_vertices, reg.used_vertices
    if kept is not None:  # the mesh's own vertex ids
        iv, used = kept[iv], kept[used]
    # the vertices written: the interior lips and their split-seam twins (each takes its representative's correction)
    out_v, take = topo.weld.expand(iv)
    read_v, ring = used, None
    if on_cache:
        ring = cache_integrate.IntegrateMap(cache_integrate.polygon_corners(obj.data), out_v, rest)
        read_v = np.union1d(read_v, ring.vertices)
    reader = CaptureReader(obj, read_v)
    at_used = np.searchsorted(read_v, used)
    at_ring = None if ring is None else np.searchsorted(read_v, ring.vertices)
    shot = None
    if model == "auto" or (model == "correction" and settings.damping):  # an even sample of the shot (model_choice)
        pick = frames[np.unique(np.linspace(0, T - 1, min(T, _SHOT_SAMPLE)).round().astype(int))]
        shot = reader.read(pick)[:, at_used]
        require_finite(shot, pick, "captured")
    try:
        reg.fit(corrected, captured=None if unknown else captured_train, shot=shot, used_only=True)
    except FrameError as e:  # the core names positions in the training list; the artist reads scene frames
        raise e.for_frames(list(train)) from None
    del corrected, captured_train, shot
    # half the storage tolerance here, half for the writer's own compression (the shot's setting, world mm)
    tol = tolerance_length(scene, obj, 0.5e-3 * storage.tolerance_mm)
    # Over a cache the keys ride on its surface, so a correction that is a few shapes on the mesh is, as key
    # offsets, a new shape on every frame. The shown correction is spooled as it comes (the patch cache after the
    # capture, blender.bakes.add_correction_patch); the key offsets are compressed only until they clearly need
    # more shapes than the key budget, then no longer mapped (the corrector's outcome turns PATCH_CACHE).
    is_train = np.isin(frames, train)
    corrector = ShotCorrector(reg, is_train, tol, take=take if on_cache else None, patch_cache=on_cache,
                              max_key_shapes=key_shapes_over_cache(storage.key_budget) if on_cache else 1024,
                              suggest=bool(settings.suggestions))
    spool = CorrectionWriter(scene, obj, PROPAGATE_PREFIX, vertices=out_v, after_capture=True) if on_cache else None
    try:
        for i, j in _chunks(T, job.chunk):
            yield "correcting the frames", 1 + i, total
            X = reader.read(frames[i:j])  # FaceLab keys muted
            require_finite(X, frames[i:j], "captured")
            # over a cache the keys ride on its surface: the offsets are mapped through it
            to_key = None if ring is None else (lambda corr, X=X: ring.to_key(X[:, at_ring], corr))
            try:  # (t, n, 3) correction shown, object local
                corr = corrector.add_chunk(X[:, at_used], to_key)
            except FrameError as e:  # positions in the shot -> scene frames
                raise e.for_frames([int(f) for f in frames]) from None
            if spool is not None:
                spool.add(frames[i:j], corr)
        yield "writing the corrective keys", total - 1, total
        result = corrector.finish()
        if result.outcome is StorageOutcome.PATCH_CACHE:
            names = StoredKeys.of(spool.finish())  # the patch cache: no keys
        else:
            names = _write_keys(job, result, iv, out_v, None if on_cache else take)
    finally:
        if spool is not None:
            spool.close()
    if names.storage.outcome.reported:  # say where it went
        note = f"{note} {names.storage.note}".strip()
    score = result.extrapolation
    worse = [int(frames[i]) for i in expected_worse(result.expected_change, local_length(scene, obj, 1e-3 * WORSE_MM))]
    obj[EXTRAPOLATION_PROP] = 0.0
    key_property_bulk(obj, f'["{EXTRAPOLATION_PROP}"]', frames, score, action_name=EXTRAPOLATION_ACTION)
    for m in [m for m in scene.timeline_markers if m.name.startswith(SUGGEST_MARKER)]:
        scene.timeline_markers.remove(m)
    suggested = []
    if settings.suggestions:
        idx = _suggest(corrector, reader, frames, at_used, settings.suggestions)
        suggested = [int(frames[i]) for i in idx]
        for f in suggested:
            scene.timeline_markers.new(f"{SUGGEST_MARKER} {f}", frame=f)
    obj.data.update()
    return PropagateResult(object=obj.name, frames=frames, keys=names, training=list(train), suggested=suggested,
                           extrapolation=score, expected_worse=worse, note=note, model=model_summary(reg, unknown),
                           whole_weight=reg.whole_weight, seconds=time.perf_counter() - job.t0)


def _write_keys(job: _Job, result, iv, out_v, welded) -> StoredKeys:
    """Store a ``KEYS`` :class:`ShotCorrection`: its shapes cover ``out_v`` (the written vertices), or, with
    ``welded`` (the ``take`` of the split-seam twins, off a cache), the welded interior lips ``iv``."""
    scene, obj, frames = job.scene, job.obj, job.frames
    basis, weights = result.basis, result.weights
    if welded is None:
        return _store_corrections(scene, obj, frames, basis, weights, out_v)
    # stored as on the welded surface, then each twin given its representative's offsets
    names = _store_corrections(scene, obj, frames, basis, weights, iv)
    if names.storage.mode == "keys":
        spread_key_offsets(obj, list(names), job.topo)
    elif names.storage.mode == "cache":  # a point cache of the vertices written: every twin in it
        names = _store_corrections(scene, obj, frames, basis[:, welded], weights, out_v)
    return names


def model_summary(reg, unknown=()) -> str:
    """What a fitted ``LipRegressor`` learnt, for reports: its model and, for "auto", the blend chosen
    (``unknown``: training frames without a captured version, which leave "auto" the whole motion)."""
    a = reg.whole_weight
    if unknown:
        return (f"whole motion: training frame{'s' if len(unknown) > 1 else ''} {', '.join(map(str, unknown[:5]))} "
                "sculpted in place, so the correction alone is unknown")
    if reg.model != "auto":
        return {"whole": "whole motion", "correction": "correction"}[reg.model]
    return f"auto: {100 * a:.0f}% whole motion + {100 * (1 - a):.0f}% correction"


def training_input(captured, corrected, interior) -> np.ndarray:
    """The training frames as the regression learns them: the captured frames with the corrected inner lips.

    The mouth input of a training frame is read from the capture, exactly as on every other frame, so
    the extrapolation score is 0 on training frames and a correction that also moved the trusted mouth
    (or the lip border, which the Poisson solve holds at its captured position) never teaches the
    regression a mouth pose the capture does not have. Only the interior lip vertices, the ones the
    regression predicts, take the corrected positions.

    Parameters
    ----------
    captured : (k,V,3) float array
        The training frames as captured (FaceLab's keys muted), object-local scene units.
    corrected : (k,V,3) float array
        The same frames with the artist's correction.
    interior : (nI,) int array
        ``LipRegressor.interior_vertices``.

    Returns
    -------
    (k,V,3) float64 ndarray
    """
    out = np.array(captured, dtype=np.float64)
    out[:, interior] = np.asarray(corrected)[:, interior]
    return out


def _store_corrections(scene, obj, frames, basis, weights, vertices) -> StoredKeys:
    """Replace FaceLab's ``FL_Prop_*`` output with the correction ``weights @ basis``, by the storage policy.

    The one place Propagate writes its result: ``basis`` (r, n, 3) offsets of ``vertices`` (object
    local, measured on the evaluated mesh; over a cache already mapped through its surface),
    ``weights`` (T, r) the value of each shape on each of ``frames``. The correction writer
    (:class:`~facelab_addon.pipeline.correctives.CorrectionWriter`) maps it to rest space under
    deforming modifiers and stores it as at most the shot's key budget of keys, or as a point cache.
    Returns the key names, with the storage result as ``.storage``.
    """
    with CorrectionWriter(scene, obj, PROPAGATE_PREFIX, vertices=vertices, measured_on="evaluated") as w:
        w.add_low_rank(frames, basis, weights)
        return StoredKeys.of(w.finish())


def _suggest(corrector, reader, frames, at_used, count):
    """Frame indices to correct next (``ShotCorrector.suggest``): the screened candidates re-read once."""
    return corrector.suggest(count, lambda idx: reader.read(frames[idx])[:, at_used])
