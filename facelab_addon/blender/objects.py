"""Objects and meshes -> arrays, beyond :mod:`.mesh`: world transforms over frames, world points in
an object's space, loop-triangle UVs, whether two meshes share their topology, and whether FaceLab
may write to an object at all (:func:`require_editable`), and how long a physical length is in an
object's own units (:func:`local_length`)."""

from __future__ import annotations

import contextlib
import os

import bpy
import numpy as np

from ..core.errors import FaceLabError, MeshError
from .camera import evaluated_depsgraph

__all__ = ["enabled_modifier_names", "NotEditableError", "require_editable", "ModifierState", "modifier_enabled", "disabled_modifiers",
           "world_affine", "world_matrices", "local_length", "tolerance_length", "RELATIVE_TOLERANCE",
           "points_to_local", "triangle_uvs", "same_polygons", "evaluated_object"]


def evaluated_object(obj, depsgraph):
    """``obj`` as ``depsgraph`` evaluated it (its shape keys, modifiers and animation on the current frame).

    Raises
    ------
    MeshError
        Blender does not evaluate ``obj``: it is not in the active view layer, or it (or a collection holding
        it) is disabled in viewports (the monitor icon); ``evaluated_get`` then hands back the original object,
        whose mesh is the undeformed one on every frame, never the face Blender shows when it is enabled.
    """
    ev = obj.evaluated_get(depsgraph)
    if ev.is_evaluated:
        return ev
    if bpy.context.view_layer.objects.get(obj.name) is None:
        raise MeshError(f"'{obj.name}' is not in the active view layer, so Blender does not evaluate it; "
                        "link it to a collection of this scene (and do not exclude that collection).")
    raise MeshError(f"'{obj.name}' is disabled in viewports (the monitor icon of the object or of a collection "
                    "holding it), so Blender does not evaluate it and its undeformed mesh would be read instead of "
                    "the performance; enable it in viewports (Object Properties > Visibility > Show In Viewports, "
                    "and its collections') first.")


class NotEditableError(FaceLabError):
    """The object, its mesh or its shape keys are linked from a library (or a library override
    without editable data): whatever FaceLab wrote would not be saved."""


def _linked_part(obj):
    """``(what, datablock)`` of the first part of ``obj`` FaceLab could not save, or None."""
    if obj.library is not None or not obj.is_editable:
        return "object", obj
    ov = obj.override_library
    if ov is not None and ov.is_system_override:
        return "object", obj
    data = obj.data
    if data is not None and (data.library is not None or not data.is_editable or data.override_library is not None):
        return "mesh data", data
    keys = getattr(data, "shape_keys", None)
    if keys is not None and (keys.library is not None or not keys.is_editable or keys.override_library is not None):
        return "shape keys", keys
    return None


def require_editable(obj, what: str = "FaceLab"):
    """``obj`` if FaceLab may write to it (shape keys, vertex groups, animation), else raise.

    Checked by every pipeline that writes, before anything changes: a linked object (or one
    whose mesh or shape keys are linked, or a library override whose mesh data is still the
    library's) accepts edits in memory that are never saved.

    Parameters
    ----------
    obj : bpy.types.Object
    what : str
        The step asking, for the message (e.g. ``"Propagate"``).

    Raises
    ------
    NotEditableError
        Naming the object, the library file and the fix (make it local).
    """
    bad = _linked_part(obj)
    if bad is None:
        return obj
    part, idb = bad
    if idb.library is not None:
        where = f"is linked from the library '{idb.library.filepath}'"
    elif idb.override_library is not None:
        lib = idb.override_library.reference.library if idb.override_library.reference else None
        where = "is a library override" + (f" of '{lib.filepath}'" if lib is not None else "") + \
            " (overrides do not store new shape keys or vertex groups)"
    else:
        where = "cannot be edited"
    raise NotEditableError(
        f"{what} cannot change '{obj.name}': its {part} {where}, so a change would not be "
        "saved. Make it local (Object > Relations > Make Local > Selected Objects and Data; for a library "
        "override, make its mesh local too), or open the library .blend and work there.")


class ModifierState:
    """What an operator may change on an object's modifiers, recorded to put it back on cancel or failure.

    Records each modifier's name, viewport / render switches and (Mesh Cache) deform mode;
    :meth:`restore` puts them back, removes modifiers added since and deletes the point-cache
    files those added modifiers were reading (files FaceLab baked for them, e.g. an Alembic
    capture baked to PC2). Use as ``state = ModifierState(obj)`` ... ``state.restore()``.
    """

    def __init__(self, obj):
        self.obj = obj
        self.saved = {m.name: (m.show_viewport, m.show_render, getattr(m, "deform_mode", None))
                      for m in obj.modifiers}
        self.files = {bpy.path.abspath(m.filepath) for m in obj.modifiers if m.type == "MESH_CACHE" and m.filepath}

    def restore(self) -> list:
        """Put the recorded modifier state back; returns what was undone, one phrase each."""
        undone = []
        obj = self.obj
        for m in list(obj.modifiers):
            if m.name not in self.saved:
                name = m.name
                path = bpy.path.abspath(m.filepath) if m.type == "MESH_CACHE" and m.filepath else ""
                obj.modifiers.remove(m)
                undone.append(f"removed the added modifier '{name}'")
                if path and path not in self.files and os.path.isfile(path):
                    os.remove(path)
                    undone.append(f"deleted {path}")
        for m in obj.modifiers:
            view, render, mode = self.saved[m.name]
            if (m.show_viewport, m.show_render) != (view, render):
                m.show_viewport, m.show_render = view, render
                undone.append(f"modifier '{m.name}' shown as before")
            if mode is not None and m.deform_mode != mode:
                m.deform_mode = mode
                undone.append(f"modifier '{m.name}' back to {mode.title()}")
        return undone


def modifier_enabled(md) -> bool:
    """Whether the modifier ``md`` shows in the viewport (the evaluation FaceLab reads)."""
    return bool(md.show_viewport)


@contextlib.contextmanager
def disabled_modifiers(mods):
    """Turn ``show_viewport`` off for ``mods``; restore on exit."""
    saved = [(m, m.show_viewport) for m in mods]
    try:
        for m in mods:
            m.show_viewport = False
        yield
    finally:
        for m, v in saved:
            m.show_viewport = v


def world_affine(obj, depsgraph=None):
    """``(A (3,3), b (3,))`` of the object's world matrix (evaluated in ``depsgraph`` when given)."""
    M = np.array((obj.evaluated_get(depsgraph) if depsgraph else obj).matrix_world, dtype=np.float64)
    return M[:3, :3], M[:3, 3]


def local_length(scene, obj, metres: float) -> float:
    """``metres`` of the object's world space, in the object's local units (its mesh coordinates).

    Accounts for the scene's unit scale (``scene.unit_settings.scale_length``: metres per Blender
    unit) and for the object's scale (the largest stretch of its world matrix, so a local length
    never shows longer than ``metres`` in any direction).

    Parameters
    ----------
    scene : bpy.types.Scene
    obj : bpy.types.Object
    metres : float
        A physical length, for example a tolerance of 0.01 mm = ``1e-5``.

    Returns
    -------
    float
        The same length in object-local units.
    """
    mpu = float(scene.unit_settings.scale_length or 1.0)
    A = world_affine(obj, evaluated_depsgraph(scene))[0]  # evaluated: a scale just set counts
    stretch = float(np.linalg.svd(A, compute_uv=False)[0]) if np.isfinite(A).all() else 1.0
    return float(metres) / mpu / (stretch if stretch > 0 else 1.0)


#: The finest a storage tolerance gets relative to the face: its bounding box's diagonal times this.
RELATIVE_TOLERANCE = 1e-4


def tolerance_length(scene, obj, metres: float) -> float:
    """A storage tolerance of ``metres`` of world space in ``obj``'s local units, never coarser than
    :data:`RELATIVE_TOLERANCE` of the mesh's own size (the diagonal of its rest bounding box).

    A physical tolerance (0.01 mm) suits a face of its real size; on a face far smaller in the world (a head
    imported at 1/1000, a miniature) it would be larger than the whole correction, which would then be
    dropped as noise. The relative bound keeps the correction to the same share of the face at any scale.

    Returns
    -------
    float
        Object-local units; :func:`local_length` itself on a face of ordinary size.
    """
    tol = local_length(scene, obj, metres)
    n = len(obj.data.vertices)
    if n == 0:
        return tol
    co = np.empty(n * 3, np.float64)
    obj.data.vertices.foreach_get("co", co)
    co = co.reshape(n, 3)
    size = float(np.linalg.norm(co.max(axis=0) - co.min(axis=0))) if np.isfinite(co).all() else 0.0
    return min(tol, RELATIVE_TOLERANCE * size) if size > 0 else tol


def world_matrices(scene, obj, frames) -> np.ndarray:
    """(T,4,4) evaluated world matrices of ``obj`` on ``frames``.

    The first, middle and last frames are probed; when they agree the object
    is taken as not animated and that one matrix is broadcast (a read-only
    view). The scene frame is restored afterwards.
    """
    keep = scene.frame_current
    probe = sorted({int(frames[0]), int(frames[len(frames) // 2]), int(frames[-1])})
    mats = {}
    try:
        for f in probe:
            scene.frame_set(f)
            mats[f] = np.array(obj.evaluated_get(evaluated_depsgraph(scene)).matrix_world, dtype=np.float64)
        if all(np.allclose(mats[f], mats[probe[0]], atol=1e-9) for f in probe):
            return np.broadcast_to(mats[probe[0]], (len(frames), 4, 4))
        out = []
        for f in frames:
            scene.frame_set(int(f))
            out.append(np.array(obj.evaluated_get(evaluated_depsgraph(scene)).matrix_world, dtype=np.float64))
        return np.stack(out)
    finally:
        scene.frame_set(keep)


def points_to_local(obj, world) -> np.ndarray:
    """World points (...,3) -> ``obj``'s local space (its current ``matrix_world``)."""
    M = np.linalg.inv(np.array(obj.matrix_world, dtype=np.float64))
    return world @ M[:3, :3].T + M[:3, 3]


def triangle_uvs(mesh):
    """(F,3,2) float64 UVs of the loop triangles from the active UV map, or None without UVs."""
    if not mesh.uv_layers:
        return None
    mesh.calc_loop_triangles()
    loops = np.empty(len(mesh.loop_triangles) * 3, np.int32)
    mesh.loop_triangles.foreach_get("loops", loops)
    uv = np.empty(len(mesh.loops) * 2, np.float64)
    mesh.uv_layers.active.data.foreach_get("uv", uv)
    return uv.reshape(-1, 2)[loops].reshape(-1, 3, 2)


def same_polygons(me_a, me_b) -> bool:
    """Whether two meshes share their topology: vertex count and every polygon's vertex list."""
    if len(me_a.vertices) != len(me_b.vertices) or len(me_a.loops) != len(me_b.loops) \
            or len(me_a.polygons) != len(me_b.polygons):
        return False
    out = []
    for me in (me_a, me_b):
        lv = np.empty(len(me.loops), np.int32)
        me.loops.foreach_get("vertex_index", lv)
        ls = np.empty(len(me.polygons), np.int32)
        me.polygons.foreach_get("loop_start", ls)
        out.append((lv, ls))
    return bool(np.array_equal(out[0][0], out[1][0]) and np.array_equal(out[0][1], out[1][1]))


def enabled_modifier_names(obj) -> str:
    """The names of ``obj``'s modifiers enabled in viewports, quoted and comma-separated, for messages that
    ask the artist to disable one of them ("none enabled" when there is none)."""
    return ", ".join(repr(m.name) for m in obj.modifiers if m.show_viewport) or "none enabled"

