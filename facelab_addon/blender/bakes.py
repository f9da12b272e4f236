"""Bake the evaluated mesh of an object to point-cache files (PC2, MDD) or Alembic.

A bake is a generator of one step per frame (:func:`bake_point_cache_steps`), so a modal
operator can show progress and cancel; :func:`bake_pc2`, :func:`bake_mdd` and
:func:`bake_alembic` run to the end. Files are written by
:class:`facelab_addon.core.capture.pointcache_writer.PointCacheWriter`, which never leaves a
half-written file at the destination. Positions are object-local scene units.

Correction caches: a dense per-frame correction that does not fit FaceLab's key budget is
written as a point cache (:func:`correction_cache_path`, never over an existing file) and
played by a Mesh Cache modifier FaceLab adds (:func:`add_correction_cache`). Both are recorded
on the object (:data:`facelab_addon.names.CORRECTION_CACHES_PROP`), so a re-run replaces
(:func:`remove_correction_cache`) only what FaceLab wrote.
"""

from __future__ import annotations

import contextlib
import math
import os
from pathlib import Path

import bpy
import numpy as np

from ..core.capture import pointcache_writer
from ..core.errors import FaceLabError, OutputError
from ..names import CORRECTION_CACHE_MODIFIER, CORRECTION_CACHES_PROP, file_name_part
from .caches import checked_frames, iter_evaluated, kept_frame, require_mesh_object, scene_fps
from .ownership import (
    as_prefixes,
    correction_cache,
    correction_cache_record,
)
from .shapekeys import key_property_bulk, remove_fcurve, unique_name

__all__ = ["bake_point_cache_steps", "bake_pc2", "bake_mdd", "bake_alembic", "bake_destination",
           "correction_cache_path", "add_correction_cache", "add_correction_patch", "remove_correction_cache"]


def bake_destination(path) -> Path:
    """The absolute destination of a bake, checked writable before any frame is evaluated.

    Parameters
    ----------
    path : str or os.PathLike
        Absolute, or ``//``-relative to the saved .blend.

    Returns
    -------
    pathlib.Path

    Raises
    ------
    OutputError
        A ``//`` path in an unsaved .blend, a relative path (it would land in
        whatever folder Blender was started from), or a destination that
        cannot be written (``pointcache_writer.check_writable``).
    """
    text = os.fspath(path)
    if not text:
        raise OutputError("Choose a file to bake to.")
    if text.startswith("//") and not bpy.data.filepath:
        raise OutputError(
            f"'{text}' is relative to the .blend, but the .blend is not saved yet; save it first, or choose "
            "an absolute path."
        )
    out = Path(bpy.path.abspath(text))
    if not out.is_absolute():
        raise OutputError(
            f"'{text}' is a relative path, which would be written into the folder Blender was started from; "
            "choose an absolute path (or save the .blend and use a '//' path relative to it)."
        )
    return pointcache_writer.check_writable(out)


def uniform_step(frames, what) -> float:
    """The constant step (scene frames) of increasing ``frames`` (T,); FaceLabError naming ``what`` otherwise."""
    if len(frames) == 1:
        return 1.0
    steps = np.diff(frames)
    if not (steps > 0).all() or not np.allclose(steps, steps[0], rtol=0, atol=1e-6):
        raise FaceLabError(
            f"{what} needs increasing, evenly spaced frames (got steps {np.unique(np.round(steps, 6))[:5].tolist()}); "
            "bake a range such as range(start, end + 1)."
        )
    return float(steps[0])


def _point_cache_header(frames, fmt) -> dict:
    """Header keywords of a ``PointCacheWriter`` for ``frames``; raises when the frames do not fit ``fmt``."""
    if fmt == "PC2":
        return dict(start_frame=float(frames[0]), sample_rate=uniform_step(frames, "A PC2 bake"))
    if fmt == "MDD":
        if len(frames) > 1 and not (np.diff(frames) > 0).all():
            raise FaceLabError("An MDD bake needs increasing scene frames.")
        return dict(times=frames / scene_fps())
    raise FaceLabError(f"Unknown point-cache format {fmt!r}; bake to 'PC2' or 'MDD'.")


def bake_steps(obj, frames, new_writer, *, mute_prefixes=(), progress=None):
    """Write the evaluated mesh of every frame; yields ``("baking frame F", i + 1, T)``, returns the path.

    ``new_writer()`` opens the ``PointCacheWriter`` on the first step. Closing
    the generator early, or an error, aborts the writer (an existing file at
    the destination stays untouched) and restores the scene frame.
    """
    writer = new_writer()
    it = iter_evaluated(obj, frames, mute_prefixes=mute_prefixes, progress=progress)
    ok = False
    try:
        for i, co in it:
            writer.write(co)
            yield f"baking frame {int(frames[i])}", i + 1, len(frames)
        ok = True
    finally:
        it.close()  # restores the scene frame
        if not ok:
            writer.abort()
    return writer.close()


def run_steps(steps):
    """Run a generator of steps to the end; its return value."""
    while True:
        try:
            next(steps)
        except StopIteration as stop:
            return stop.value


def bake_point_cache_steps(obj, scene_frames, path, fmt, *, mute_shape_keys_prefix=(), progress=None):
    """A PC2 or MDD bake of the evaluated mesh of ``obj``, as a generator of one step per frame.

    The arguments are checked at once (errors are raised by this call, before
    any file is opened); the returned generator opens the file on its first
    step, yields ``("baking frame F", done, total)`` after each frame and
    returns the written ``pathlib.Path``. The file is written beside its
    destination and moved in place at the end, so closing the generator early
    (a cancel) or an error leaves an existing file untouched; the scene frame
    is restored either way.

    Parameters
    ----------
    obj : bpy.types.Object
    scene_frames : (T,) array_like of float
        PC2: increasing, evenly spaced; MDD: increasing.
    path : str or os.PathLike
        Destination (``//`` paths are relative to the .blend).
    fmt : {"PC2", "MDD"}
    mute_shape_keys_prefix : tuple of str
        Keys to leave out (default none: the final mesh).
    progress : callable(i, T), optional

    Returns
    -------
    generator
        Of ``(str, int, int)``; its return value is the ``pathlib.Path``.

    Raises
    ------
    MeshError
        ``obj`` is not a mesh object.
    FaceLabError
        Frames unfit for the format (see :func:`bake_pc2`, :func:`bake_mdd`) or an unknown format.
    OutputError
        The destination cannot be written (:func:`bake_destination`), checked here, before any frame.
    """
    require_mesh_object(obj)
    frames = checked_frames(scene_frames)
    header = _point_cache_header(frames, fmt)
    dest, n = bake_destination(path), len(obj.data.vertices)
    return bake_steps(obj, frames, lambda: pointcache_writer.PointCacheWriter(dest, fmt, n, len(frames), **header),
                       mute_prefixes=as_prefixes(mute_shape_keys_prefix), progress=progress)


def bake_pc2(obj, scene_frames, path, *, progress=None, mute_shape_keys_prefix=()) -> Path:
    """Bake the evaluated (corrected) mesh of ``obj`` over ``scene_frames`` to a PC2 file.

    Positions are object-local. The header's start frame is
    ``scene_frames[0]`` and its sample rate the frame step. The file is
    written next to its destination and moved in place at the end, so a
    failed bake leaves any existing file untouched.

    Parameters
    ----------
    obj : bpy.types.Object
    scene_frames : (T,) array_like of float
        Increasing, evenly spaced scene frames.
    path : str or os.PathLike
        Destination (``//`` paths are relative to the .blend).
    progress : callable(i, T), optional
    mute_shape_keys_prefix : tuple of str
        Keys to leave out (default none: the final mesh).

    Returns
    -------
    pathlib.Path
    """
    return run_steps(bake_point_cache_steps(obj, scene_frames, path, "PC2", progress=progress,
                                       mute_shape_keys_prefix=mute_shape_keys_prefix))


def bake_mdd(obj, scene_frames, path, *, progress=None, mute_shape_keys_prefix=()) -> Path:
    """Bake the evaluated (corrected) mesh of ``obj`` to an MDD file.

    Sample ``i`` gets the time ``scene_frames[i] / fps`` seconds (scene fps),
    Blender's clock, so a Mesh Cache in ``time_mode='TIME'`` with
    ``frame_start=0`` plays it back on the same frames.

    Parameters
    ----------
    obj : bpy.types.Object
    scene_frames : (T,) array_like of float
        Increasing scene frames.
    path : str or os.PathLike
    progress : callable(i, T), optional
    mute_shape_keys_prefix : tuple of str

    Returns
    -------
    pathlib.Path
    """
    return run_steps(bake_point_cache_steps(obj, scene_frames, path, "MDD", progress=progress,
                                       mute_shape_keys_prefix=mute_shape_keys_prefix))


def bake_alembic(obj, scene_frames, path, *, evaluation_mode="VIEWPORT") -> Path:
    """Export the evaluated (corrected) animation of ``obj`` alone to an Alembic file.

    Runs ``bpy.ops.wm.alembic_export`` with only ``obj`` selected (works in
    the headless bpy module without a window), over every frame from
    ``min(scene_frames)`` to ``max(scene_frames)``. Selection, active object
    and current frame are restored.

    Parameters
    ----------
    obj : bpy.types.Object
        A visible mesh object in the active view layer.
    scene_frames : array_like of int
        Frames to cover (the export is the whole integer range).
    path : str or os.PathLike
        Destination ``.abc``.
    evaluation_mode : {"VIEWPORT", "RENDER"}
        Which modifier visibility the export uses; ``"VIEWPORT"`` matches
        ``evaluate_frames``.

    Returns
    -------
    pathlib.Path

    Raises
    ------
    FaceLabError
        When the object is hidden.
    OutputError
        The destination cannot be written (:func:`bake_destination`) or the exporter fails.
    """
    require_mesh_object(obj)
    frames = checked_frames(scene_frames)
    start, end = int(math.floor(frames.min())), int(math.ceil(frames.max()))
    out = bake_destination(path)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise pointcache_writer.output_error(out, e) from None
    vl = bpy.context.view_layer
    if vl.objects.get(obj.name) is None or not obj.visible_get():
        raise FaceLabError(f"'{obj.name}' is hidden or not in this view layer; unhide it to export it to Alembic.")
    scene = bpy.context.scene
    prev_sel = [o for o in vl.objects if o.select_get()]
    prev_active = vl.objects.active
    try:
        with kept_frame(scene):
            for o in prev_sel:
                o.select_set(False)
            obj.select_set(True)
            vl.objects.active = obj
            with bpy.context.temp_override(active_object=obj, object=obj, selected_objects=[obj]):
                res = bpy.ops.wm.alembic_export(
                    filepath=str(out),
                    start=start,
                    end=end,
                    selected=True,
                    evaluation_mode=evaluation_mode,
                    as_background_job=False,
                    init_scene_frame_range=False,
                )
    finally:
        for o in vl.objects:
            o.select_set(False)
        for o in prev_sel:
            o.select_set(True)
        vl.objects.active = prev_active
    if "FINISHED" not in res or not out.is_file():
        raise OutputError(f"Alembic export of '{obj.name}' to '{out}' failed ({res}); check the path is writable.")
    return out


# --------------------------------------------------------------------------- correction caches
_KEEP_FILES = 2  # FaceLab's files kept per prefix: the current one and the one an undo step may show
def correction_cache_path(obj, prefix: str, fmt: str, directory=None) -> Path:
    """A new file for ``obj``'s ``prefix`` correction cache: ``<blend>_<object>_<prefix>.<fmt>``.

    In ``directory`` (default: the .blend's folder). A file that exists is never reused, FaceLab's
    own included (an undo step may still play it): ``.001``, ``.002``... are tried instead.

    Raises
    ------
    OutputError
        No ``directory`` and the .blend is not saved, or the folder cannot be written.
    """
    if not directory:
        if not bpy.data.filepath:
            raise OutputError("The correction needs a point cache beside the .blend, but the .blend is not saved; "
                              "save it first (or set a cache folder).")
        directory = os.path.dirname(bpy.data.filepath)
    folder = Path(bpy.path.abspath(os.fspath(directory)))
    if not folder.is_absolute():
        raise OutputError(f"The cache folder '{directory}' is a relative path; choose an absolute folder "
                          "(or save the .blend and use a '//' path relative to it).")
    stem = file_name_part(Path(bpy.data.filepath).stem) + "_" if bpy.data.filepath else ""
    base = f"{stem}{file_name_part(obj.name)}_{file_name_part(prefix.strip('_'))}"
    ext = "." + fmt.lower()
    path, i = folder / f"{base}{ext}", 0
    while path.exists() or path.with_name(path.name + pointcache_writer.TMP_SUFFIX).exists():
        i += 1
        path = folder / f"{base}.{i:03d}{ext}"
    return pointcache_writer.check_writable(path)


def remove_correction_cache(obj, prefix: str) -> list:
    """Remove FaceLab's correction-cache modifier for ``prefix`` (and its keyed factor).

    Files: only FaceLab's recorded ones, and not the last one (an undo step may play it). Another
    modifier, or a file FaceLab did not write, is never touched.

    Returns
    -------
    list of str
        What was removed, one phrase each.
    """
    done = []
    md, files = correction_cache(obj, prefix)
    entry = correction_cache_record(obj).get(prefix, {})
    if md is not None:
        name = md.name
        if md.type == "MESH_CACHE":
            remove_fcurve(obj, f'modifiers["{bpy.utils.escape_identifier(name)}"].factor')
        ng = md.node_group if md.type == "NODES" else None
        obj.modifiers.remove(md)
        done.append(f"removed modifier '{name}'")
        if ng is not None and ng.name == entry.get("node_group") and ng.users == 0:
            bpy.data.node_groups.remove(ng)
    patch = bpy.data.objects.get(entry.get("patch", "")) if entry.get("patch") else None
    if patch is not None and str(patch.get(CORRECTION_CACHES_PROP, "")).endswith(f":{prefix}"):  # FaceLab's only
        me = patch.data
        bpy.data.objects.remove(patch)
        if me is not None and me.users == 0:
            bpy.data.meshes.remove(me)
        done.append(f"removed patch object '{entry['patch']}'")
    attr = obj.data.attributes.get(entry.get("attribute", "")) if entry.get("attribute") else None
    if attr is not None:
        obj.data.attributes.remove(attr)
    rec = correction_cache_record(obj)
    if prefix in rec:
        keep = files[-1:]
        for f in files[:-1]:
            if os.path.isfile(f):
                os.remove(f)
                done.append(f"deleted {f}")
        rec[prefix] = {"modifier": "", "files": keep}
        obj[CORRECTION_CACHES_PROP] = rec
    return done


def add_correction_cache(obj, prefix: str, path, fmt: str, first_frame: float, last_frame: float, *,
                         integrate: bool, index: int = 0) -> str:
    """Play the point cache ``path`` on ``obj`` with a new Mesh Cache modifier; its name.

    Sample 0 shows on ``first_frame``, one sample per frame; the modifier's factor is keyed 1 from
    ``first_frame`` to ``last_frame`` and 0 outside (the cache holds its ends otherwise).

    Parameters
    ----------
    obj : bpy.types.Object
    prefix : str
        The key prefix the cache replaces (recorded with the file).
    path : pathlib.Path
        The written PC2 or MDD file (stored relative to the .blend when saved).
    fmt : {"PC2", "MDD"}
    first_frame, last_frame : float
    integrate : bool
        ``'INTEGRATE'`` deform mode (shape keys show on top: the cache holds rest + correction)
        or ``'OVERWRITE'`` (the cache holds the whole corrected input).
    index : int
        Position in the modifier stack (0: before every deformer, so a rig deforms the result).
    """
    name = unique_name(CORRECTION_CACHE_MODIFIER.format(prefix=prefix), (m.name for m in obj.modifiers))
    mc = obj.modifiers.new(name, "MESH_CACHE")
    mc.cache_format = fmt
    mc.filepath = blend_relative(path)
    mc.play_mode = "SCENE"
    if fmt == "MDD":
        mc.time_mode = "TIME"
        mc.frame_start = 0.0
    else:
        mc.time_mode = "FRAME"
        mc.frame_start = float(first_frame)
    mc.frame_scale = 1.0
    mc.interpolation = "LINEAR"
    mc.deform_mode = "INTEGRATE" if integrate else "OVERWRITE"
    mc.forward_axis, mc.up_axis = "POS_Y", "POS_Z"
    obj.modifiers.move(len(obj.modifiers) - 1, int(index))
    f0, f1 = float(first_frame), float(last_frame)
    key_property_bulk(obj, f'modifiers["{bpy.utils.escape_identifier(name)}"].factor',
                      [f0 - 1, f0, f1, f1 + 1], [0.0, 1.0, 1.0, 0.0])
    rec = correction_cache_record(obj)
    files = [f for f in rec.get(prefix, {}).get("files", []) if f != str(path)] + [str(path)]
    rec[prefix] = {"modifier": name, "files": files[-_KEEP_FILES:]}
    obj[CORRECTION_CACHES_PROP] = rec
    return name


def add_correction_patch(obj, prefix: str, path, fmt: str, vertices, first_frame: float, last_frame: float, *,
                         index: int) -> str:
    """Add the point cache ``path`` of offsets of a few ``vertices`` to ``obj``'s evaluated mesh; the modifier's name.

    A hidden mesh object (the *patch*: one vertex per corrected vertex, at the origin) plays the file with a
    Mesh Cache; a Geometry Nodes modifier on ``obj`` at ``index`` of its stack adds each patch vertex's
    position to its vertex (``Set Position`` offset, sampled by an integer attribute holding the patch index,
    -1 elsewhere). So the file holds only the correction (n x 3 floats a frame, not the whole mesh) and the
    offsets add to whatever the stack below gives (the capture, shape keys included). Everything is recorded
    for :func:`remove_correction_cache`.

    Parameters
    ----------
    obj : bpy.types.Object
    prefix : str
    path : pathlib.Path
        The written PC2 or MDD file with ``len(vertices)`` points: offsets, object-local scene units.
    fmt : {"PC2", "MDD"}
    vertices : (n,) int array_like
    first_frame, last_frame : float
        Sample 0 shows on ``first_frame``; the offsets are 0 outside.
    index : int
        Position of the modifier in the stack (right after the capture cache).
    """
    v = np.asarray(vertices, dtype=np.int64)
    name = unique_name(CORRECTION_CACHE_MODIFIER.format(prefix=prefix),
                       set(m.name for m in obj.modifiers) | set(obj.data.attributes.keys()))
    me = bpy.data.meshes.new(f"{obj.name} {name}")
    me.vertices.add(len(v))
    patch = bpy.data.objects.new(f"{obj.name} {name}", me)
    patch[CORRECTION_CACHES_PROP] = f"{obj.name}:{prefix}"
    (obj.users_collection[0] if obj.users_collection else bpy.context.scene.collection).objects.link(patch)
    patch.hide_select = True  # (rendered too: loose vertices show nothing, and a renderer evaluates it for sure)
    with contextlib.suppress(RuntimeError):  # not in the view layer: nothing to hide
        patch.hide_set(True)
    mc = patch.modifiers.new(name, "MESH_CACHE")
    mc.cache_format, mc.filepath, mc.play_mode = fmt, blend_relative(path), "SCENE"
    mc.time_mode, mc.frame_start = ("TIME", 0.0) if fmt == "MDD" else ("FRAME", float(first_frame))
    mc.frame_scale, mc.interpolation, mc.deform_mode = 1.0, "LINEAR", "OVERWRITE"
    mc.forward_axis, mc.up_axis = "POS_Y", "POS_Z"
    f0, f1 = float(first_frame), float(last_frame)
    key_property_bulk(patch, f'modifiers["{bpy.utils.escape_identifier(name)}"].factor',
                      [f0 - 1, f0, f1, f1 + 1], [0.0, 1.0, 1.0, 0.0])
    attr = obj.data.attributes.new(name, "INT", "POINT")
    at = np.full(len(obj.data.vertices), -1, np.int32)
    at[v] = np.arange(len(v), dtype=np.int32)
    attr.data.foreach_set("value", at)
    ng = _patch_nodes(name, patch, attr.name)
    md = obj.modifiers.new(name, "NODES")
    md.node_group = ng
    obj.modifiers.move(len(obj.modifiers) - 1, int(index))
    rec = correction_cache_record(obj)
    files = [f for f in rec.get(prefix, {}).get("files", []) if f != str(path)] + [str(path)]
    rec[prefix] = {"modifier": md.name, "files": files[-_KEEP_FILES:], "patch": patch.name,
                   "attribute": attr.name, "node_group": ng.name}
    obj[CORRECTION_CACHES_PROP] = rec
    return md.name


def _patch_nodes(name, patch, attribute):
    """The node group adding the positions of ``patch``'s vertices to the vertices the int ``attribute`` names."""
    ng = bpy.data.node_groups.new(name, "GeometryNodeTree")
    ng.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    ng.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    N, L = ng.nodes, ng.links
    gi, go = N.new("NodeGroupInput"), N.new("NodeGroupOutput")
    info = N.new("GeometryNodeObjectInfo")
    info.transform_space = "ORIGINAL"
    info.inputs["Object"].default_value = patch
    sample = N.new("GeometryNodeSampleIndex")
    sample.data_type, sample.domain = "FLOAT_VECTOR", "POINT"  # an index out of range (-1) samples 0
    pos = N.new("GeometryNodeInputPosition")
    idx = N.new("GeometryNodeInputNamedAttribute")
    idx.data_type = "INT"
    idx.inputs["Name"].default_value = attribute
    setpos = N.new("GeometryNodeSetPosition")
    L.new(info.outputs["Geometry"], sample.inputs["Geometry"])
    L.new(pos.outputs["Position"], sample.inputs["Value"])
    L.new(idx.outputs["Attribute"], sample.inputs["Index"])
    L.new(gi.outputs[0], setpos.inputs["Geometry"])
    L.new(sample.outputs["Value"], setpos.inputs["Offset"])
    L.new(setpos.outputs["Geometry"], go.inputs[0])
    for i, n in enumerate((gi, info, pos, idx, sample, setpos, go)):
        n.location = (200 * i, 0)
    return ng


def blend_relative(path) -> str:
    """``path`` relative to the saved .blend (``//...``), so the scene travels with its caches; absolute when
    the .blend is unsaved or on another drive."""
    fp = str(path)
    if bpy.data.filepath:
        try:
            fp = bpy.path.relpath(fp)
        except ValueError:  # another drive on Windows
            pass
    return fp
