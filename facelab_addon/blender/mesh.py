"""Blender meshes <-> arrays: evaluated frames, triangles, vertex groups.

Positions are returned in world space (scene units) because cameras are in
world space; ``world_to_local_deltas`` maps a world-space correction back to
the object's local (shape-key) space.
"""

from __future__ import annotations

import numpy as np

from ..core.errors import MeshError
from ..core.lips.sketch_prior import separate_parts
from ..names import FIXED_GROUP

__all__ = [
    "mesh_triangles",
    "evaluated_vertices",
    "world_to_local_deltas",
    "vertex_group_mask",
    "set_vertex_group",
    "selected_vertices",
    "default_fixed_mask",
    "require_mesh",
]


def require_mesh(obj):
    """Raise ``MeshError`` unless ``obj`` is a mesh object with faces."""
    if obj is None or obj.type != "MESH":
        raise MeshError("No face mesh: select the captured face mesh (or set it in FaceLab > Setup).")
    if len(obj.data.polygons) == 0:
        raise MeshError(f"'{obj.name}' has no faces; FaceLab needs the captured face surface.")
    return obj


def mesh_triangles(mesh) -> np.ndarray:
    """(F,3) int64 triangles of a Blender mesh (its loop triangulation)."""
    mesh.calc_loop_triangles()
    tris = np.empty(len(mesh.loop_triangles) * 3, dtype=np.int32)
    mesh.loop_triangles.foreach_get("vertices", tris)
    return tris.reshape(-1, 3).astype(np.int64)


def evaluated_vertices(obj, depsgraph, *, world: bool = True) -> np.ndarray:
    """(V,3) float64 positions of the evaluated mesh (shape keys, modifiers) on the current frame.

    Raises
    ------
    MeshError
        When modifiers change the vertex count (the correction could not be
        mapped back to the mesh).
    """
    ev = obj.evaluated_get(depsgraph)
    me = ev.to_mesh()
    try:
        n = len(me.vertices)
        co = np.empty(n * 3, dtype=np.float64)
        me.vertices.foreach_get("co", co)
    finally:
        ev.to_mesh_clear()
    if n != len(obj.data.vertices):
        raise MeshError(
            f"The modifiers of '{obj.name}' change its vertex count ({len(obj.data.vertices)} -> {n}); "
            "disable topology-changing modifiers (Subdivision, Decimate...) before using FaceLab."
        )
    co = co.reshape(-1, 3)
    if world:
        M = np.array(ev.matrix_world, dtype=np.float64)
        co = co @ M[:3, :3].T + M[:3, 3]
    return co


def world_to_local_deltas(obj, deltas_world) -> np.ndarray:
    """(V,3) world-space displacements -> object-local displacements (shape-key space)."""
    M = np.array(obj.matrix_world, dtype=np.float64)[:3, :3]
    return np.asarray(deltas_world, dtype=np.float64) @ np.linalg.inv(M).T


def vertex_group_mask(obj, name: str, threshold: float = 0.5):
    """(V,) bool mask of vertices with weight > threshold in group ``name``, or None if absent."""
    vg = obj.vertex_groups.get(name)
    if vg is None:
        return None
    n = len(obj.data.vertices)
    mask = np.zeros(n, dtype=bool)
    gi = vg.index
    # vertex -> group weights is a ragged structure; iterate groups per vertex once
    for v in obj.data.vertices:
        for g in v.groups:
            if g.group == gi and g.weight > threshold:
                mask[v.index] = True
                break
    return mask


def set_vertex_group(obj, name: str, mask) -> None:
    """Replace the vertex group ``name`` of ``obj`` with the vertices of ``mask`` (V,) bool, weight 1."""
    vg = obj.vertex_groups.get(name)
    if vg is not None:
        obj.vertex_groups.remove(vg)
    vg = obj.vertex_groups.new(name=name)
    vg.add(np.flatnonzero(mask).tolist(), 1.0, "REPLACE")


def selected_vertices(obj) -> np.ndarray:
    """(k,) int64 ids of the selected vertices of ``obj``'s mesh (the Edit Mode selection, once in Object Mode)."""
    sel = np.zeros(len(obj.data.vertices), bool)
    obj.data.vertices.foreach_get("select", sel)
    return np.flatnonzero(sel)


def default_fixed_mask(obj, tris, group: str = FIXED_GROUP):
    """Vertices that must not move and are never lip silhouettes.

    The vertex group ``group`` if the mesh has one; otherwise every vertex that
    is not on the largest connected piece of the mesh (teeth, tongue, eyes
    and other separate parts): :func:`~facelab_addon.core.lips.sketch_prior.separate_parts`,
    the default of ``refine_lips`` too.

    Returns
    -------
    mask : (V,) bool
    source : str
        ``"vertex group <name>"`` or ``"separate mesh parts"``.
    """
    m = vertex_group_mask(obj, group)
    if m is not None:
        return m, f"vertex group '{group}'"
    return separate_parts(tris, len(obj.data.vertices)), "separate mesh parts"
