"""Corrective shape keys on top of a captured cache (Mesh Cache in Integrate mode).

A Mesh Cache in ``'OVERWRITE'`` mode, and a Mesh Sequence Cache (Alembic) always, replace the
positions the shape keys produce. :func:`cache_to_shape_key_ready` makes the keys show: it
switches a Mesh Cache to ``'INTEGRATE'``, or bakes an Alembic capture to PC2 and plays it with
an Integrate Mesh Cache. In Integrate mode Blender carries a key's offset in the local frame of
the cache surface; :func:`correction_to_key_offsets` maps a wanted correction back through that
frame (:func:`facelab_addon.core.capture.integrate.integrate_matrices`).
"""

from __future__ import annotations

import os
from pathlib import Path

import bpy
import numpy as np

from ..core.capture import pointcache, pointcache_writer
from ..core.errors import FaceLabError, MeshError
from .bakes import _bake_steps, _run, _uniform_step
from .caches import (
    _alembic_still_error,
    _disabled_modifiers,
    _enabled,
    _frames,
    _msc_modifier,
    check_capture_files,
    mesh_cache_modifier,
    require_mesh_object,
    sequence_source,
)

__all__ = ["cache_to_shape_key_ready", "polygon_corners", "correction_to_key_offsets"]


def _unique_file(path: Path) -> Path:
    if not path.exists():
        return path
    i = 1
    while True:
        p = path.with_name(f"{path.stem}.{i:03d}{path.suffix}")
        if not p.exists():
            return p
        i += 1


def _unique_modifier_name(obj, base):
    from .shapekeys import unique_name

    return unique_name(base, (m.name for m in obj.modifiers))


def cache_to_shape_key_ready(obj, *, directory=None, scene_frames=None, progress=None) -> str:
    """Make shape keys (FaceLab's correctives) show on top of ``obj``'s captured cache.

    - Mesh Cache (PC2/MDD): sets its ``deform_mode`` to ``'INTEGRATE'``
      (in ``'OVERWRITE'`` the cache replaces the keyed positions).
    - Mesh Sequence Cache (Alembic), which always replaces the positions:
      bakes the captured sequence (the modifier's output, later modifiers
      off) to ``<object>_capture.pc2`` in ``directory`` (default: the
      .blend's folder; never overwriting a file), turns the Alembic modifier
      off in viewport and render (it is kept) and adds, right after it, a
      Mesh Cache playing that PC2 in ``'INTEGRATE'`` mode (sample 0 on
      ``scene_frames[0]``), so the mesh looks the same and keys add on top.
    - Shape-key animation or a static mesh: nothing to change.

    Nothing is deleted. Keys show *in the local frame* of the cache surface
    (``core.capture.integrate.integrate_matrices``).

    Parameters
    ----------
    obj : bpy.types.Object
    directory : str or os.PathLike, optional
        Where to write the PC2 for an Alembic cache.
    scene_frames : array_like of float, optional
        Frames to bake for an Alembic cache, evenly spaced. Default: the
        scene's frame range.
    progress : callable(i, T), optional

    Returns
    -------
    str
        What was changed, one sentence, for the operator's report.

    Raises
    ------
    MeshError
        The mesh has no faces (Integrate needs them) or the cache changes the
        vertex count.
    FaceLabError
        Unsaved .blend and no ``directory``.
    CacheFileError
        The cache file is missing or broken
        (:func:`~facelab_addon.blender.caches.check_capture_files`), or the
        Alembic capture does not move over ``scene_frames`` (the baked file is
        removed, the modifiers are left as they were).
    OutputError
        The PC2 cannot be written in ``directory``.
    """
    require_mesh_object(obj)
    src = sequence_source(obj)
    if src in ("mesh_cache", "mesh_sequence_cache") and len(obj.data.polygons) == 0:
        raise MeshError(f"'{obj.name}' has no faces; the Mesh Cache 'Integrate' mode needs faces to carry shape keys.")
    check_capture_files(obj)  # a broken file is refused before anything changes
    if src == "mesh_cache":
        md = mesh_cache_modifier(obj)
        if md.deform_mode == "INTEGRATE":
            return f"Mesh Cache '{md.name}' already integrates shape keys; nothing changed."
        md.deform_mode = "INTEGRATE"
        return f"Mesh Cache '{md.name}': deform mode Overwrite -> Integrate, so shape keys now add on top of the cache."
    if src == "shape_keys":
        return f"'{obj.name}' is animated by shape keys; corrective keys already add on top. Nothing changed."
    if src == "static":
        return f"'{obj.name}' has no captured cache; corrective keys already show. Nothing changed."

    # Alembic
    msc = _msc_modifier(obj)
    scene = bpy.context.scene
    frames = _frames(range(scene.frame_start, scene.frame_end + 1) if scene_frames is None else scene_frames)
    step = _uniform_step(frames, "Baking the Alembic cache")
    if directory is None:
        if not bpy.data.filepath:
            raise FaceLabError(
                "Save the .blend first (the capture is baked to a PC2 file next to it), or give a directory."
            )
        directory = os.path.dirname(bpy.data.filepath)
    directory = Path(bpy.path.abspath(os.fspath(directory)))
    base = bpy.path.clean_name(obj.name) or "capture"
    path = _unique_file(directory / f"{base}_capture.pc2")

    mods = list(obj.modifiers)
    k = mods.index(msc)
    later = [m for m in mods[k + 1 :] if _enabled(m)]
    n = len(obj.data.vertices)
    with _disabled_modifiers(later):
        _run(_bake_steps(obj, frames, lambda: pointcache_writer.PointCacheWriter(
            path, "PC2", n, len(frames), start_frame=float(frames[0]), sample_rate=step), progress=progress))
    try:  # a capture that never moves is a file Blender could not read: keep the artist's modifier on
        baked = pointcache.read_pc2(path, mmap=True)[0]
        moved = len(frames) == 1 or any(np.any(baked[t] != baked[0]) for t in range(1, len(frames)))
        del baked
        if not moved:
            raise _alembic_still_error(obj, frames)
    except FaceLabError:
        path.unlink(missing_ok=True)
        raise

    msc.show_viewport = False
    msc.show_render = False
    mc = obj.modifiers.new(_unique_modifier_name(obj, "FL Capture (PC2)"), "MESH_CACHE")
    mc.cache_format = "PC2"
    fp = str(path)
    if bpy.data.filepath:
        try:
            fp = bpy.path.relpath(fp)
        except ValueError:  # another drive on Windows
            pass
    mc.filepath = fp
    mc.play_mode = "SCENE"
    mc.time_mode = "FRAME"
    mc.frame_scale = 1.0 / step
    mc.frame_start = float(frames[0]) / step  # sample = f/step - f0/step
    mc.interpolation = "LINEAR"
    mc.deform_mode = "INTEGRATE"
    mc.forward_axis, mc.up_axis = "POS_Y", "POS_Z"
    obj.modifiers.move(len(obj.modifiers) - 1, k + 1)
    return (
        f"Baked Alembic modifier '{msc.name}' ({len(frames)} frames, {frames[0]:g}-{frames[-1]:g}) to '{path}', "
        f"turned it off (kept) and added Mesh Cache '{mc.name}' (PC2, Integrate) after it, "
        "so shape keys now add on top of the capture."
    )


def polygon_corners(mesh):
    """``(face_offsets (P+1,), corner_verts (C,))`` int arrays of a Blender mesh's polygons."""
    offs = np.empty(len(mesh.polygons), np.int32)
    mesh.polygons.foreach_get("loop_start", offs)
    cv = np.empty(len(mesh.loops), np.int32)
    mesh.loops.foreach_get("vertex_index", cv)
    return np.r_[offs, len(cv)].astype(np.int64), cv.astype(np.int64)


def correction_to_key_offsets(obj, cache_positions, deltas, corners=None):
    """Shape-key offsets that show as ``deltas`` (V,3) on a frame whose cache output is ``cache_positions``.

    Without a cache (shape keys, static mesh) this is ``deltas`` itself. Over a
    Mesh Cache in ``'INTEGRATE'`` mode Blender carries key offsets in the
    local frame of the cache surface (``core.capture.integrate.integrate_matrices``),
    so the offsets are mapped back through those matrices.

    Parameters
    ----------
    obj : bpy.types.Object
    cache_positions : (V,3) float
        The captured positions on that frame (FaceLab keys muted), object-local.
    deltas : (V,3) float
        Wanted displacement of the evaluated mesh, object-local scene units.
    corners : tuple, optional
        Precomputed ``polygon_corners(obj.data)``.
    """
    if sequence_source(obj) not in ("mesh_cache", "mesh_sequence_cache"):
        return np.asarray(deltas, dtype=np.float64)
    from ..core.capture.integrate import integrate_matrices, integrate_offsets_to_key
    from .shapekeys import rest_vertices

    offs, cv = polygon_corners(obj.data) if corners is None else corners
    M = integrate_matrices(rest_vertices(obj), cache_positions, offs, cv)
    return integrate_offsets_to_key(M, deltas)
