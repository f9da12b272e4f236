"""Captured sequences in Blender: which source animates the mesh, and reading it as (T,V,3).

A captured performance reaches Blender in one of three ways:

- **shape keys** animated on the timeline (one key per frame, or a solve);
- a **Mesh Cache** modifier playing a PC2 or MDD file;
- a **Mesh Sequence Cache** modifier playing an Alembic file.

``sequence_source`` tells which. ``read_mesh_cache_frames`` reads a Mesh
Cache's file directly (``core.capture.pointcache``), mapping scene frames to samples
exactly as the modifier does; ``evaluate_frames`` is the generic path (one
``frame_set`` and evaluated mesh per frame) for everything else, with
FaceLab's own corrective keys (the ``FL_*`` keys it recorded) muted so it returns the *capture*.

Corrective shape keys only show on top of a cache when the cache does not
overwrite them: ``cache_integrate.cache_to_shape_key_ready`` switches a Mesh Cache to
``deform_mode='INTEGRATE'`` and, for Alembic (whose modifier always replaces
the positions), bakes the capture to a PC2 file (``bakes``), turns the Mesh Sequence
Cache off (it is kept) and plays the PC2 with an INTEGRATE Mesh Cache in its
place. Note: in INTEGRATE mode Blender carries a key's offset in the local
frame of the cache's surface (rotated with the head, scaled with the face);
``core.capture.integrate.integrate_matrices`` gives that map, and
``integrate_offsets_to_key`` the key offsets that show a wanted correction.

All positions are object-local (shape-key space), float32, scene units.
"""

from __future__ import annotations

import contextlib
import math
import os
import struct

import bpy
import numpy as np

from ..core.capture import meshcache, pointcache
from ..core.errors import CacheFileError, FaceLabError, MeshError
from ..names import PREFIX
from . import compat
from .objects import disabled_modifiers, enabled_modifier_names, evaluated_object, modifier_enabled
from .ownership import (
    as_prefixes,
    correction_cache_prefix,
    is_correction_cache,
    key_matches,
    muted_correction_caches,
    muted_shape_keys,
)
from .shapekeys import shape_key_sequence

__all__ = [
    "sequence_source",
    "mesh_cache_modifier",
    "mesh_cache_direct_read_problem",
    "read_mesh_cache_frames",
    "read_captured_frames",
    "evaluate_frames",
    "alembic_file_problem",
    "check_capture_files",
    "check_alembic_moves",
    "require_mesh_object",
    "scene_fps",
    "input_positions",
    "checked_frames",
    "kept_frame",
    "set_frame",
    "iter_evaluated",
    "cache_path",
    "alembic_still_error",
    "mesh_sequence_cache_modifier",
]

FACELAB_PREFIXES = (PREFIX,)


# --------------------------------------------------------------------------- helpers


def checked_frames(scene_frames) -> np.ndarray:
    """(T,) float64 scene frames (subframes allowed); FaceLabError when empty or not finite."""
    f = np.asarray(list(scene_frames) if not isinstance(scene_frames, np.ndarray) else scene_frames, dtype=np.float64)
    f = f.reshape(-1)
    if len(f) == 0:
        raise FaceLabError("No frames given; pass the scene frames to read (for example range(1, 251)).")
    if not np.isfinite(f).all():
        raise FaceLabError("Scene frames must be finite numbers.")
    return f


def scene_fps(scene=None) -> float:
    """Frames per second of ``scene``: ``render.fps / render.fps_base``."""
    scene = scene or bpy.context.scene
    return float(scene.render.fps) / float(scene.render.fps_base)


def require_mesh_object(obj):
    """Raise ``MeshError`` unless ``obj`` is a mesh object (faces not needed)."""
    if obj is None or obj.type != "MESH":
        raise MeshError("No mesh object: select the captured face mesh.")
    return obj


def _mesh_cache_active(md) -> bool:
    # a correction cache FaceLab added is not a capture
    return md.type == "MESH_CACHE" and modifier_enabled(md) and bool(md.filepath) and md.factor > 0.0 \
        and not is_correction_cache(md.id_data, md)


def _msc_active(md) -> bool:
    return md.type == "MESH_SEQUENCE_CACHE" and modifier_enabled(md) and md.cache_file is not None


def cache_path(obj, md) -> str:
    """Absolute path of the file the Mesh Cache modifier ``md`` of ``obj`` plays (library-relative paths resolved)."""
    return bpy.path.abspath(md.filepath, library=obj.library)


def _anim_fcurves(id_data):
    """F-curves and drivers of an ID (layered actions; legacy ``Action.fcurves`` when no channelbag)."""
    ad = getattr(id_data, "animation_data", None)
    if ad is None:
        return []
    out = list(ad.drivers)
    action = ad.action
    if action is not None:
        fcurves = None
        try:
            cb = compat.action_channelbag(action, getattr(ad, "action_slot", None))
            fcurves = cb.fcurves if cb is not None else []
        except Exception:
            fcurves = getattr(action, "fcurves", None) or []
        out.extend(fcurves)
    return out


def _key_name_from_path(path: str):
    if path.startswith('key_blocks["'):
        end = path.find('"]')
        return path[len('key_blocks["') : end].replace('\\"', '"') if end > 0 else None
    return None


def _shape_keys_animated(obj, ignore_prefixes=FACELAB_PREFIXES) -> bool:
    keys = obj.data.shape_keys if obj.type == "MESH" else None
    if keys is None or len(keys.key_blocks) < 2:
        return False
    pref = as_prefixes(ignore_prefixes)
    for fc in _anim_fcurves(keys):
        if fc.data_path == "eval_time":
            return True
        name = _key_name_from_path(fc.data_path)
        if name is not None and not key_matches(keys, name, pref):
            return True
    return False


@contextlib.contextmanager
def kept_frame(scene):
    """Context manager: the scene's current frame and subframe are restored on exit."""
    frame, sub = scene.frame_current, scene.frame_subframe
    try:
        yield
    finally:
        scene.frame_set(frame, subframe=sub)


def set_frame(scene, f: float):
    """Go to scene frame ``f`` (float: the fraction is the subframe)."""
    fi = math.floor(f)
    scene.frame_set(int(fi), subframe=float(f - fi))


def iter_evaluated(obj, frames, *, mute_prefixes=(), progress=None, scene=None):
    """Yield ``(i, co (V,3) float32)`` of the evaluated mesh on each frame.

    Shape keys with ``mute_prefixes`` are muted and the current frame is
    restored when the iteration ends (also on errors or early exit).
    """
    scene = scene or bpy.context.scene
    n = len(obj.data.vertices)
    check_capture_files(obj)
    evaluated_object(obj, bpy.context.evaluated_depsgraph_get())  # refused before anything is muted or read
    T = len(frames)
    buf = np.empty(n * 3, dtype=np.float32)
    # FaceLab's correction caches are muted like its keys
    with kept_frame(scene), muted_shape_keys(obj, mute_prefixes), muted_correction_caches(obj, mute_prefixes):
        for i, f in enumerate(frames):
            set_frame(scene, float(f))
            dg = bpy.context.evaluated_depsgraph_get()
            ev = evaluated_object(obj, dg)
            me = ev.to_mesh()
            try:
                m = len(me.vertices)
                if m != n:
                    raise MeshError(
                        f"On frame {f:g} the evaluated '{obj.name}' has {m} vertices instead of {n}; "
                        "disable the modifier that adds or removes vertices (Subdivision, Decimate...) among "
                        f"its enabled modifiers ({enabled_modifier_names(obj)}) or use a cache with the mesh's "
                        "topology."
                    )
                me.vertices.foreach_get("co", buf)
            finally:
                ev.to_mesh_clear()
            if not np.isfinite(buf).all():
                raise MeshError(
                    f"On frame {f:g} the evaluated '{obj.name}' has NaN or infinite vertex positions; fix the "
                    "cache, modifier or shape key that produces them on that frame."
                )
            if progress is not None:
                progress(i, T)
            yield i, buf.reshape(n, 3)


# --------------------------------------------------------------------------- cache files are checked before use

_OGAWA_DATA = 1 << 63


def alembic_file_problem(path) -> str | None:
    """Why Blender cannot read the Alembic file at ``path``: a short reason, or None when it is whole.

    Blender's Alembic reader aborts the whole program on a truncated Ogawa
    file and plays a missing one as the static mesh, so the file is checked
    first: it must exist, be an Ogawa archive (``b"Ogawa"``, finished writing)
    and every group and data block of its tree must lie inside the file (the
    root group is written last, so a truncated file always fails this).

    Parameters
    ----------
    path : str or os.PathLike
        An absolute path.

    Returns
    -------
    str or None
    """
    path = os.fspath(path)
    if not os.path.isfile(path):
        return "the file does not exist"
    size = os.path.getsize(path)
    with open(path, "rb") as f:
        data = f.read()
    if size < 16:
        return f"it has {size} bytes, too short for an Alembic file (truncated or empty)"
    if data[:4] == b"\x89HDF":
        return "it is an HDF5 Alembic, which Blender cannot read (re-export it as Ogawa)"
    if data[:5] != b"Ogawa":
        return f"it is not an Alembic (Ogawa) file: it starts with {data[:8]!r}"
    if data[5] != 0xFF:
        return "its writer did not finish it (the archive is not frozen): the export was interrupted"
    root = struct.unpack_from("<Q", data, 8)[0]
    stack, seen = [root], set()
    while stack:
        pos = stack.pop()
        if pos in seen:
            continue
        seen.add(pos)
        if pos + 8 > size:
            return f"it is truncated ({size} bytes; a block starts at byte {pos})"
        k = struct.unpack_from("<Q", data, pos)[0]
        if pos + 8 + 8 * k > size:
            return f"it is truncated ({size} bytes; a group at byte {pos} lists {k} children past the end)"
        for c in struct.unpack_from(f"<{k}Q", data, pos + 8):
            if c & _OGAWA_DATA:
                q = c & ~_OGAWA_DATA
                if q and (q + 8 > size or q + 8 + struct.unpack_from("<Q", data, q)[0] > size):
                    return f"it is truncated ({size} bytes; a data block at byte {q} ends past the end)"
            elif c:
                stack.append(c)
    return None


def check_capture_files(obj) -> None:
    """Refuse a cache modifier of ``obj`` whose file Blender would silently fail to play.

    Every enabled Mesh Cache with a file must be a whole PC2/MDD file of the
    modifier's format with one point per vertex; every enabled Mesh Sequence
    Cache must play a whole Alembic file that holds the modifier's object
    path. Without this, Blender's modifiers fail quietly and the static mesh
    is read as if it were the capture.

    Parameters
    ----------
    obj : bpy.types.Object

    Raises
    ------
    CacheFileError
        Naming the object, the modifier, the file, the problem and the fix.
    """
    for md in obj.modifiers:
        if _mesh_cache_active(md):
            try:
                info = pointcache.cache_info(cache_path(obj, md), md.cache_format)
                pointcache.check_vertex_count(info, len(obj.data.vertices), name=f"'{obj.name}'")
            except CacheFileError as e:
                raise type(e)(f"Mesh Cache '{md.name}' of '{obj.name}': {e}") from None
        elif _msc_active(md):
            cf = md.cache_file
            path = bpy.path.abspath(cf.filepath, library=cf.library)
            why = alembic_file_problem(path)
            if why is None and not len(cf.object_paths):
                why = "Blender found no object in it (it could not read the file when it was opened)"
            if why is None and md.object_path and md.object_path not in {o.path for o in cf.object_paths}:
                why = f"it has no object '{md.object_path}'"
            if why is not None:
                raise CacheFileError(
                    f"Mesh Sequence Cache '{md.name}' of '{obj.name}' plays '{path}', but {why}, so Blender would "
                    "show the static mesh instead of the capture. Re-export or re-copy the Alembic file (then "
                    "reload it in the Cache File properties), or point the modifier at the right file and object."
                )


def check_alembic_moves(obj, frames, positions) -> None:
    """Refuse an Alembic capture that gives the same positions on every one of several frames.

    Parameters
    ----------
    obj : bpy.types.Object
    frames : (T,) float ndarray
        Scene frames.
    positions : (T,V,3) float ndarray
        The evaluated capture on ``frames``.

    Raises
    ------
    CacheFileError
        When ``T > 1`` and no vertex moves between the frames.
    """
    if len(frames) > 1 and not np.any(positions != positions[:1]):
        raise alembic_still_error(obj, frames)


def alembic_still_error(obj, frames) -> CacheFileError:
    """The error for an Alembic capture of ``obj`` that does not move over ``frames`` (T,) (to raise)."""
    md = mesh_sequence_cache_modifier(obj)
    what = f"'{md.cache_file.filepath}'" if md is not None else "its Alembic file"
    return CacheFileError(
        f"The Alembic capture of '{obj.name}' ({what}) does not move on frames {frames[0]:g}-{frames[-1]:g}: "
        "every frame has the same positions, so the file holds no animation there or Blender cannot read "
        "it. Check the frame range (and the Cache File's frame offset), re-export the Alembic file, or "
        "reload it in the Cache File properties."
    )


# --------------------------------------------------------------------------- what animates the mesh


def sequence_source(obj, *, ignore_prefixes=FACELAB_PREFIXES) -> str:
    """How the captured performance animates ``obj``.

    Parameters
    ----------
    obj : bpy.types.Object
    ignore_prefixes : tuple of str
        Shape keys with these name prefixes (FaceLab's correctives) do not
        count as captured animation.

    Returns
    -------
    str
        ``"mesh_sequence_cache"`` or ``"mesh_cache"`` when the last enabled
        (viewport) cache modifier of the stack is an Alembic Mesh Sequence
        Cache or a PC2/MDD Mesh Cache (with a file and factor > 0);
        ``"shape_keys"`` when shape keys other than the ignored ones are
        animated (F-curves or drivers on their values, or on ``eval_time``);
        otherwise ``"static"`` (nothing FaceLab recognises; other animation,
        an armature for instance, still works with ``evaluate_frames``).
    """
    require_mesh_object(obj)
    for md in reversed(obj.modifiers):
        if _msc_active(md):
            return "mesh_sequence_cache"
        if _mesh_cache_active(md):
            return "mesh_cache"
    if _shape_keys_animated(obj, ignore_prefixes):
        return "shape_keys"
    return "static"


def mesh_cache_modifier(obj):
    """The last enabled Mesh Cache modifier of ``obj`` (with a file), or None."""
    for md in reversed(obj.modifiers):
        if _mesh_cache_active(md):
            return md
    return None


def mesh_sequence_cache_modifier(obj):
    """The last enabled Mesh Sequence Cache modifier of ``obj`` (with a Cache File), or None."""
    for md in reversed(obj.modifiers):
        if _msc_active(md):
            return md
    return None


def mesh_cache_direct_read_problem(obj, md=None, *, mute_prefixes=FACELAB_PREFIXES):
    """Why the Mesh Cache of ``obj`` cannot be read straight from its file (None if it can).

    The direct read reproduces the modifier's output, which is the final mesh
    when: the modifier is the last enabled one; in ``'OVERWRITE'`` mode
    (earlier modifiers and shape keys are overwritten) or in ``'INTEGRATE'``
    mode with no enabled modifier before it and no unmuted shape keys other
    than the Basis and the muted ``mute_prefixes`` ones; with factor 1 and
    no vertex group.

    Returns
    -------
    str or None
        A short reason, used to explain the fall back to ``evaluate_frames``.
    """
    md = md or mesh_cache_modifier(obj)
    if md is None:
        return "no enabled Mesh Cache modifier with a file"
    mods = list(obj.modifiers)
    k = mods.index(md)
    pref = as_prefixes(mute_prefixes)

    def counts(m):  # FaceLab's correction caches of muted prefixes are off while the capture is read
        p = correction_cache_prefix(obj, m)
        return modifier_enabled(m) and not (p is not None and pref and p.startswith(pref))

    after = [m.name for m in mods[k + 1 :] if counts(m)]
    if after:
        return f"enabled modifiers after it ({', '.join(after)})"
    if md.factor != 1.0:
        return f"influence {md.factor:g} (not 1)"
    if md.vertex_group:
        return f"vertex group '{md.vertex_group}'"
    if md.deform_mode == "INTEGRATE":
        before = [m.name for m in mods[:k] if counts(m)]
        if before:
            return f"Integrate mode with enabled modifiers before it ({', '.join(before)})"
        keys = obj.data.shape_keys
        if keys is not None:
            if not keys.use_relative:
                return "Integrate mode with absolute shape keys"
            live = [
                kb.name
                for kb in keys.key_blocks
                if kb != keys.reference_key and not kb.mute and not kb.name.startswith(pref)
            ]
            if live:
                return f"Integrate mode with other shape keys ({', '.join(live[:3])})"
    return None


def read_mesh_cache_frames(obj, scene_frames, *, modifier=None, mute_shape_keys_prefix=FACELAB_PREFIXES, progress=None):
    """Positions a Mesh Cache (PC2/MDD) modifier gives ``obj`` on scene frames, read from its file.

    Maps every scene frame to cache samples exactly as the modifier does
    (``play_mode``, ``time_mode`` FRAME/TIME/FACTOR, ``frame_start``,
    ``frame_scale``, ``interpolation``, scene fps and time remapping, the
    axis matrix) and reads only the samples needed. Equals the evaluated
    mesh with FaceLab's keys muted to float32 rounding (verified in
    ``tests/blender/test_caches.py``). When the stack is one the direct
    read cannot reproduce (see ``mesh_cache_direct_read_problem``), falls
    back to ``evaluate_frames``, after the file was checked.

    Parameters
    ----------
    obj : bpy.types.Object
        Mesh object with a Mesh Cache modifier.
    scene_frames : (T,) array_like of float
        Scene frames (a fractional part is a subframe).
    modifier : bpy.types.MeshCacheModifier, optional
        Default: the last enabled Mesh Cache of the stack.
    mute_shape_keys_prefix : tuple of str
        Keys muted by the evaluation fallback (FaceLab's correctives).
    progress : callable(i, T), optional
        Called by the evaluation fallback.

    Returns
    -------
    (T,V,3) float32 ndarray
        Object-local positions, scene units.

    Raises
    ------
    MeshError
        No Mesh Cache modifier.
    pointcache.CacheFileError
        Missing/bad file, NaN positions or a vertex count that does not match
        the mesh (checked before the evaluation fallback too: see
        :func:`check_capture_files`).
    """
    require_mesh_object(obj)
    frames = checked_frames(scene_frames)
    md = modifier or mesh_cache_modifier(obj)
    if md is None:
        raise MeshError(
            f"'{obj.name}' has no enabled Mesh Cache modifier with a file; add one (PC2 or MDD) or "
            "read the animation with evaluate_frames."
        )
    check_capture_files(obj)  # a broken file is refused, never evaluated as the static mesh
    if mesh_cache_direct_read_problem(obj, md, mute_prefixes=mute_shape_keys_prefix) is not None:
        return evaluate_frames(obj, frames, mute_shape_keys_prefix=mute_shape_keys_prefix, progress=progress)
    scene = bpy.context.scene
    path = cache_path(obj, md)
    info = pointcache.cache_info(path, md.cache_format)
    r = scene.render
    i0, i1, w = meshcache.mesh_cache_samples(
        frames,
        info,
        fps=scene_fps(scene),
        time_mode=md.time_mode,
        play_mode=md.play_mode,
        frame_start=md.frame_start,
        frame_scale=md.frame_scale,
        interpolation=md.interpolation,
        eval_frame=md.eval_frame,
        eval_time=md.eval_time,
        eval_factor=md.eval_factor,
        frame_length=np.float32(r.frame_map_old) / np.float32(r.frame_map_new),  # measured: old/new
    )
    mm = pointcache.read_cache(path, fmt=md.cache_format, mmap=True)
    out = meshcache.blend_samples(mm, i0, i1, w)
    del mm
    pointcache.check_finite_samples(info, out, i0)
    M = meshcache.axis_conversion_matrix(md.forward_axis, md.up_axis, tuple(md.flip_axis))
    if not np.array_equal(M, np.eye(3)):
        Mf = M.astype(np.float32)
        for t in range(len(out)):
            out[t] = out[t] @ Mf.T
    return out


def evaluate_frames(obj, scene_frames, *, mute_shape_keys_prefix=FACELAB_PREFIXES, progress=None) -> np.ndarray:
    """Evaluated positions of ``obj`` on scene frames (the generic path: Alembic, rigs, anything).

    Sets every frame (``scene.frame_set``), takes the evaluated mesh (shape
    keys and modifiers) and reads its vertex positions. Shape keys whose
    names start with ``mute_shape_keys_prefix`` are muted meanwhile, so the
    result is the capture without FaceLab's corrections; their mute state
    and the scene's current frame are restored afterwards, also on errors.

    Parameters
    ----------
    obj : bpy.types.Object
        Mesh object in the active view layer.
    scene_frames : (T,) array_like of float
        Scene frames (a fractional part is a subframe).
    mute_shape_keys_prefix : str or tuple of str
        Default ``("FL_",)``; ``()`` evaluates the final, corrected mesh.
    progress : callable(i, T), optional
        Called after each frame.

    Returns
    -------
    (T,V,3) float32 ndarray
        Object-local positions, scene units.

    Raises
    ------
    MeshError
        When the evaluated vertex count differs from the mesh's on some frame,
        a position is NaN or infinite, or the object is not in the view layer.
    CacheFileError
        A cache modifier's file is missing or broken (:func:`check_capture_files`).
    """
    require_mesh_object(obj)
    frames = checked_frames(scene_frames)
    out = np.empty((len(frames), len(obj.data.vertices), 3), dtype=np.float32)
    for i, co in iter_evaluated(obj, frames, mute_prefixes=mute_shape_keys_prefix, progress=progress):
        out[i] = co
    return out


def read_captured_frames(obj, scene_frames, *, mute_shape_keys_prefix=FACELAB_PREFIXES, progress=None):
    """The captured sequence of ``obj`` (without FaceLab's keys), by the fastest exact path.

    A Mesh Cache is read from its file when possible, shape-key animation is
    mixed from its F-curves directly (``shapekeys.shape_key_sequence``);
    everything else is evaluated frame by frame.

    Parameters
    ----------
    obj : bpy.types.Object
    scene_frames : (T,) array_like of float
    mute_shape_keys_prefix : tuple of str
    progress : callable(i, T), optional

    Returns
    -------
    (T,V,3) float32 ndarray
        Object-local positions, scene units.

    Raises
    ------
    CacheFileError
        A cache file is missing or broken (:func:`check_capture_files`).
    """
    from .scene_time import require_scene_time

    require_scene_time(None, "Reading the capture", obj)  # the F-curves below are read at the frames' own time
    source = sequence_source(obj, ignore_prefixes=mute_shape_keys_prefix)
    check_capture_files(obj)
    if source == "mesh_cache":
        return read_mesh_cache_frames(
            obj, scene_frames, mute_shape_keys_prefix=mute_shape_keys_prefix, progress=progress
        )
    if source in ("shape_keys", "static"):
        seq = shape_key_sequence(obj, checked_frames(scene_frames), skip_prefixes=as_prefixes(mute_shape_keys_prefix))
        if seq is not None:  # F-curves mixed directly, no frame_set per frame
            return seq
    return evaluate_frames(obj, scene_frames, mute_shape_keys_prefix=mute_shape_keys_prefix, progress=progress)


def input_positions(obj, frames, *, upto=None, skip_prefixes=()) -> np.ndarray:
    """(T,V,3) float32 object-local positions entering the modifier ``upto`` (default: the first).

    The shape-key mix on each frame (every key, FaceLab's included) when ``upto`` is the first
    modifier; otherwise the evaluated mesh with ``upto`` and every later modifier turned off.

    Parameters
    ----------
    obj : bpy.types.Object
    frames : (T,) array_like of float
    upto : int, optional
        Index in ``obj.modifiers`` (default 0).
    skip_prefixes : tuple of str
        Shape keys to leave out (:func:`.ownership.key_matches`: under ``FL_`` only FaceLab's recorded keys).
    """
    k = 0 if upto is None else int(upto)
    if k == 0:
        seq = shape_key_sequence(obj, frames, skip_prefixes=tuple(skip_prefixes), ignore_modifiers=True)
        if seq is not None:
            return seq
    with disabled_modifiers([m for m in list(obj.modifiers)[k:] if m.show_viewport]):
        return evaluate_frames(obj, frames, mute_shape_keys_prefix=tuple(skip_prefixes))
