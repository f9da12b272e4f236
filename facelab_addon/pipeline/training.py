"""Training frames of Propagate: one definition, one writer, one reader.

A training frame is the corrected shape relative to the frame without FaceLab's lip corrections
(:func:`uncorrected_frame`: Propagate's output and the training keys muted), stored as a key
(``FL_Refine_<frame>``, ``FL_Corrected_<frame>``) keyed 1 on the frame alone. Every writer (Refine Lips,
:func:`add_corrected_frame`, :func:`mark_training_frame`) goes through :func:`store_training_frame`, which also
supersedes FaceLab's earlier correction of the frame (its key keyed 0 there, kept; its record dropped) and keys
Propagate's correction off on the frame, so the frame shows what the viewport showed after Refine (or the
sculpt) now and after every later Propagate, which keeps its own correction zero on training frames. Propagate
reads them through :func:`read_training_frames`, with Review's *Show Capture* lifted. The records live on the
face object (``obj.facelab.training_frames``) and as timeline markers.
"""

from __future__ import annotations

from dataclasses import dataclass

import bpy
import numpy as np

from ..blender import cache_integrate, caches, review
from ..blender.mesh import require_mesh
from ..blender.objects import ModifierState, require_editable
from ..blender.ownership import key_matches, owned_keys
from ..blender.rest_space import to_rest_space
from ..blender.scene_time import require_scene_time
from ..blender.shapekeys import add_corrective_key, key_spike, zero_on_frame
from ..core.errors import FaceLabError, MeshError
from ..names import CORRECTED_PREFIX, PROPAGATE_PREFIX, REFINE_PREFIX, TRAIN_MARKER
from .correctives import silence_correction

__all__ = [
    "TRAINING_KEY_PREFIXES",
    "MARKED",
    "CorrectedFrame",
    "training_frames",
    "record_training_frame",
    "remove_training_frame",
    "uncorrected_frame",
    "store_training_frame",
    "add_corrected_frame",
    "mark_training_frame",
    "read_training_frames",
    "captured_unknown",
    "require_finite",
]

_CACHE_SOURCES = ("mesh_cache", "mesh_sequence_cache")


@dataclass
class CorrectedFrame:
    """A corrected frame added by :func:`add_corrected_frame`: its corrective key and largest offset."""

    frame: int
    shape_key: str
    max_offset: float


# --------------------------------------------------------------------------- training frames
#: Prefixes of the keys that hold a training frame's correction (Refine Lips, Add Corrected Frame, Mark
#: Training Frame): each is keyed 1 on its frame alone.
TRAINING_KEY_PREFIXES = (REFINE_PREFIX, CORRECTED_PREFIX)
#: What a training frame's correction is measured against: the frame with Propagate's output and the training
#: keys muted (the capture as Propagate reads it, plus whatever else the artist animates).
_LOOP_PREFIXES = (PROPAGATE_PREFIX, *TRAINING_KEY_PREFIXES)
#: Source of a frame sculpted in place and marked (Mark Training Frame): its capture is unknown.
MARKED = "marked"


def training_frames(obj) -> list:
    """Sorted unique training frames of ``obj`` whose correction still exists (a sketch's key not deleted)."""
    key = obj.data.shape_keys
    names = set(key.key_blocks.keys()) if key else set()
    frames = {t.frame for t in obj.facelab.training_frames if t.source != "sketch" or t.shape_key in names}
    return sorted(frames)


def record_training_frame(scene, obj, frame: int, shape_key: str, source: str) -> None:
    """Remember ``frame`` as a corrected (training) frame of ``obj`` and mark it on the timeline.

    The low-level record only: a correction is stored by :func:`store_training_frame`.

    Parameters
    ----------
    scene : bpy.types.Scene
    obj : bpy.types.Object
    frame : int
    shape_key : str
        The corrective key holding the correction ("" for a sculpted mesh).
    source : {"sketch", "sculpt", "marked"}
        Refine Lips, Add Corrected Frame, or a frame sculpted in place (Mark Training Frame).
    """
    item = obj.facelab.training_frames.add()
    item.frame, item.shape_key, item.source = frame, shape_key, source
    if not any(m.frame == frame and m.name.startswith(TRAIN_MARKER) for m in scene.timeline_markers):
        scene.timeline_markers.new(f"{TRAIN_MARKER} {frame}", frame=frame)


def remove_training_frame(scene, obj, index: int) -> tuple:
    """Forget the training record ``index`` of ``obj`` (its shape key is kept).

    The frame's timeline marker goes too once no record is left on that frame.

    Returns
    -------
    frame : int
    shape_key : str
        The kept key of the record ("" for a sculpted mesh).
    """
    tf = obj.facelab.training_frames
    frame, shape_key = tf[index].frame, tf[index].shape_key
    tf.remove(index)
    if frame not in {t.frame for t in tf}:
        for m in list(scene.timeline_markers):
            if m.frame == frame and m.name.startswith(TRAIN_MARKER):
                scene.timeline_markers.remove(m)
    return frame, shape_key


def uncorrected_frame(obj, frame: int) -> np.ndarray:
    """(V,3) float64 evaluated ``obj`` on ``frame`` with Propagate's output and the training keys muted.

    A training frame's correction is this frame's shape subtracted from what the artist made (the
    corrected shape relative to the capture), so it is the same whatever Propagate showed on the frame
    when the artist refined or sculpted it, and whether Review shows the capture or not (its *Show Capture* is
    lifted meanwhile). Object-local scene units, after the modifiers (as
    :func:`facelab_addon.blender.caches.evaluate_frames`).
    """
    with review.corrections_as_set(obj):  # the same whether Review shows the capture or not
        return caches.evaluate_frames(obj, [frame], mute_shape_keys_prefix=_LOOP_PREFIXES)[0].astype(np.float64)


def _supersede(scene, obj, frame: int) -> list:
    """Make room for a new correction of ``frame``: FaceLab's earlier training keys of the frame are keyed 0
    there (kept, never deleted) and their records dropped; Propagate's correction is keyed off on the frame.
    Review's *Show Capture* ends first (the artist's mutes back), so the face shows the new correction with every
    other one, never the capture with FaceLab's newest keys alone. Returns the superseded keys."""
    review.show_corrected(obj)
    key = obj.data.shape_keys
    owned = set(owned_keys(obj)) if key is not None else set()
    gone = []
    tf = obj.facelab.training_frames
    for i in reversed(range(len(tf))):
        t = tf[i]
        if t.frame != frame:
            continue
        if t.shape_key and t.shape_key in owned and t.shape_key in key.key_blocks:
            zero_on_frame(key, f'key_blocks["{bpy.utils.escape_identifier(t.shape_key)}"].value', frame)
            key.key_blocks[t.shape_key].value = 0.0
            gone.append(t.shape_key)
        remove_training_frame(scene, obj, i)
    silence_correction(obj, PROPAGATE_PREFIX, frame)
    return gone


def store_training_frame(scene, obj, frame: int, offsets, prefix: str, source: str):
    """Write ``frame``'s correction as a new key ``<prefix><frame>`` keyed 1 on the frame (0 on its neighbours),
    make it the frame's one training record and turn Propagate's correction off on the frame.

    The one writer of training frames (Refine Lips, Add Corrected Frame, Mark Training Frame): afterwards the
    frame shows :func:`uncorrected_frame` + ``offsets``, now and after any later Propagate (which keeps its
    correction zero on training frames). An earlier correction of the frame by FaceLab is superseded (its key
    keyed 0 on the frame, its record dropped), so it no longer adds.

    Parameters
    ----------
    scene, obj
    frame : int
    offsets : (V,3) float array_like
        Shape-key offsets (rest space, object-local scene units) relative to :func:`uncorrected_frame`.
    prefix : str
        :data:`~facelab_addon.names.REFINE_PREFIX` or :data:`~facelab_addon.names.CORRECTED_PREFIX`.
    source : {"sketch", "sculpt", "marked"}

    Returns
    -------
    bpy.types.ShapeKey
    """
    kb = add_corrective_key(obj, f"{prefix}{frame:04d}", offsets)
    key_spike(kb, frame)
    _supersede(scene, obj, frame)
    record_training_frame(scene, obj, frame, kb.name, source)
    if scene.frame_current == frame:
        scene.frame_set(frame)  # the keys' animated values on this frame as they are now keyed
    obj.data.update()
    return kb


def add_corrected_frame(scene, obj, frame: int, vertices) -> CorrectedFrame:
    """Make the face corrected by hand on ``frame`` a training frame.

    The difference to the frame without FaceLab's lip corrections (:func:`uncorrected_frame`) becomes a
    corrective key ``FL_Corrected_<frame>`` (:data:`~facelab_addon.names.CORRECTED_PREFIX`) stored by
    :func:`store_training_frame` (source "sculpt"). Over a cache, the cache is first made ready to carry keys
    (:func:`facelab_addon.blender.cache_integrate.cache_to_shape_key_ready`) and the offsets are mapped through
    its surface so the frame shows ``vertices`` exactly.

    Parameters
    ----------
    scene : bpy.types.Scene
    obj : bpy.types.Object
    frame : int
    vertices : (V,3) float array_like
        The corrected face, object-local scene units, the mesh's vertex order.

    Returns
    -------
    CorrectedFrame

    Raises
    ------
    MeshError
        ``vertices`` does not have the mesh's vertex count.
    """
    require_mesh(obj)
    require_editable(obj, "Mark Corrected Frame")
    require_scene_time(scene, "Mark Corrected Frame", obj)
    V = np.asarray(vertices, dtype=np.float64)
    n = len(obj.data.vertices)
    if V.shape != (n, 3):
        raise MeshError(f"The corrected face has {len(V)} vertices, '{obj.name}' has {n}; export it with the "
                        "same topology.")
    if not np.all(np.isfinite(V)):
        raise MeshError(f"The corrected face for frame {frame} has NaN or infinite coordinates; fix the file and "
                        "export it again.")
    d = _frame_offsets(obj, frame, V)
    kb = store_training_frame(scene, obj, frame, d, CORRECTED_PREFIX, "sculpt")
    return CorrectedFrame(frame=frame, shape_key=kb.name, max_offset=float(np.linalg.norm(d, axis=1).max()))


def mark_training_frame(scene, obj, frame: int) -> CorrectedFrame:
    """Make ``frame`` as the viewport shows it (for example sculpted in place) a training frame.

    What FaceLab's lip corrections add on the frame (Propagate's output, an earlier Refine) is kept as a key
    ``FL_Corrected_<frame>`` stored by :func:`store_training_frame`, so the frame keeps the shape the artist
    marked through later Propagate runs; without such a correction only the record is written. Either way
    the record's source is "marked": the frame was sculpted in place, so its capture is unknown
    (:func:`captured_unknown`). On a frame that is already a training frame (a sculpt on top of a refined one)
    the new shape supersedes the earlier correction (:func:`store_training_frame`: its key kept, keyed 0 there).

    Returns
    -------
    CorrectedFrame
        ``shape_key`` "" when the frame showed no correction of FaceLab's.
    """
    require_mesh(obj)
    require_editable(obj, "Mark Training Frame")
    require_scene_time(scene, "Mark Training Frame", obj)
    shown = caches.evaluate_frames(obj, [frame], mute_shape_keys_prefix=())[0].astype(np.float64)
    shown_rel = shown - uncorrected_frame(obj, frame)
    if float(np.abs(shown_rel).max(initial=0.0)) <= 1e-7 * max(1.0, float(np.abs(shown).max(initial=0.0))):
        _supersede(scene, obj, frame)
        record_training_frame(scene, obj, frame, "", MARKED)
        return CorrectedFrame(frame=frame, shape_key="", max_offset=0.0)
    d = _frame_offsets(obj, frame, shown)
    kb = store_training_frame(scene, obj, frame, d, CORRECTED_PREFIX, MARKED)
    return CorrectedFrame(frame=frame, shape_key=kb.name, max_offset=float(np.linalg.norm(d, axis=1).max()))


def _frame_offsets(obj, frame, target) -> np.ndarray:
    """(V,3) key offsets (rest space) that make ``frame`` show ``target`` (V,3) (object-local, evaluated) over
    :func:`uncorrected_frame`; over a cache mapped through its surface."""
    on_cache = caches.sequence_source(obj) in _CACHE_SOURCES
    state = ModifierState(obj)
    try:
        if on_cache:
            cache_integrate.cache_to_shape_key_ready(obj)
        base = uncorrected_frame(obj, frame)
        require_finite(base[None], [frame], "captured")
        d = np.asarray(target, dtype=np.float64) - base
        if on_cache:
            captured = caches.read_captured_frames(obj, [frame])[0].astype(np.float64)
            d = cache_integrate.correction_to_key_offsets(obj, captured, d)
    except BaseException:
        state.restore()
        raise
    return to_rest_space(obj, [frame], d[None])[0]


def read_training_frames(obj, train) -> np.ndarray:
    """(k,V,3) float32 training frames as Propagate learns them: each frame with its training correction and
    without Propagate's, object-local, as the artist set the mutes (Review's *Show Capture* lifted).

    Raises
    ------
    FaceLabError
        A training frame's key is muted (by hand): the frame would train as its capture.
    """
    key = obj.data.shape_keys
    with review.corrections_as_set(obj):
        if key is not None:
            muted = sorted({(t.frame, t.shape_key) for t in obj.facelab.training_frames
                            if t.frame in set(train) and t.shape_key in key.key_blocks
                            and key.key_blocks[t.shape_key].mute})
            if muted:
                named = ", ".join(f"{k} (frame {f})" for f, k in muted[:5])
                raise FaceLabError(f"The training key{'s' if len(muted) > 1 else ''} {named} "
                                   f"{'are' if len(muted) > 1 else 'is'} muted, so Propagate would learn the "
                                   "capture there; unmute it in the Shape Keys panel, or remove the frame from "
                                   "the training frames (Remove Training Frame).")
        return caches.evaluate_frames(obj, train, mute_shape_keys_prefix=(PROPAGATE_PREFIX,))


def require_finite(X, frames, what):
    """Raise naming the scene frames (not list indices) whose vertices of ``X`` (T,V,3) are not finite."""
    bad = ~np.isfinite(X).reshape(len(X), -1).all(axis=1)
    if np.any(bad):
        named = [int(f) for f in np.asarray(frames)[bad][:5]]
        raise MeshError(f"The {what} face has NaN or infinite coordinates on frame{'s' if len(named) > 1 else ''} "
                        f"{', '.join(map(str, named))}; fix or re-import those frames (or leave them out of the "
                        "range).")


def captured_unknown(obj, train) -> list:
    """Training frames whose capture Propagate cannot read apart from the correction.

    The correction model learns corrected minus captured lips, so it needs each training frame as
    captured: the frame with its correction's key muted. Refine Lips and Add Corrected Frame record
    FaceLab's own keys, which the capture reads leave out; a frame sculpted in place and marked with
    Mark Training Frame (source "marked") is its capture plus the sculpt, so its capture is unknown.

    Returns
    -------
    list of int
        Those frames of ``train`` (sorted); empty when every training frame's capture is known.
    """
    key = obj.data.shape_keys
    owned = set(owned_keys(obj)) if key else set()
    known = {t.frame for t in obj.facelab.training_frames
             if t.source != MARKED and t.shape_key and key is not None and t.shape_key in key.key_blocks
             and key_matches(key, t.shape_key, caches.FACELAB_PREFIXES, owned)}
    return [int(f) for f in train if f not in known]
