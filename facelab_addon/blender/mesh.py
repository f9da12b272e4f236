"""Blender meshes <-> arrays: evaluated frames, triangles, vertex groups.

Positions are returned in world space (scene units) because cameras are in
world space; ``world_to_local_deltas`` maps a world-space correction back to
the object's local (shape-key) space.

:func:`face_topology` is the face's surface as the Dinev route reads it: its triangles with the
vertices a UV-seam split duplicated (a glTF import, a game export) welded back
(:mod:`facelab_addon.core.geometry.weld`), and the map that gives every duplicate its
representative's value in what is written back.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import chain

import numpy as np

from ..core.errors import MeshError
from ..core.geometry.weld import Weld, weld
from ..core.lips.sketch_prior import separate_parts
from ..names import FIXED_GROUP
from .objects import enabled_modifier_names, evaluated_object

__all__ = [
    "mesh_triangles",
    "FaceTopology",
    "face_topology",
    "spread_key_offsets",
    "evaluated_vertices",
    "world_to_local_deltas",
    "world_winding",
    "vertex_group_mask",
    "set_vertex_group",
    "selected_vertices",
    "default_fixed_mask",
    "require_mesh",
]


#: The coarsest spacing of float32 coordinates accepted, as a share of the mesh's size (:func:`require_mesh`).
FLOAT32_SHARE = 1e-4


def require_mesh(obj):
    """Raise ``MeshError`` unless ``obj`` is a mesh object with faces whose coordinates float32 holds finely.

    Blender stores vertex and shape-key positions in float32, whose steps grow with the distance from the
    object's origin (about 1.2e-7 of it): a face modelled 1e6 units from its origin is quantised to
    about 0.1 unit, and a correction there would be off by a good share of itself. Refused when the step
    at the mesh's farthest coordinate exceeds :data:`FLOAT32_SHARE` of the mesh's size (its bounding box's
    diagonal), naming the distance and the fix (set the origin to the geometry).
    """
    if obj is None or obj.type != "MESH":
        raise MeshError("No face mesh: select the captured face mesh (or set it in FaceLab > Setup).")
    if len(obj.data.polygons) == 0:
        raise MeshError(f"'{obj.name}' has no faces; FaceLab needs the captured face surface.")
    n = len(obj.data.vertices)
    co = np.empty(n * 3, np.float32)
    obj.data.vertices.foreach_get("co", co)
    co = co.reshape(n, 3).astype(np.float64)
    if np.isfinite(co).all():
        far = float(np.abs(co).max())
        size = float(np.linalg.norm(co.max(axis=0) - co.min(axis=0)))
        step = float(np.spacing(np.float32(far)))
        if size > 0 and step > FLOAT32_SHARE * size:
            raise MeshError(
                f"The mesh of '{obj.name}' lies {far:.4g} units from its object's origin, where Blender's float32 "
                f"coordinates are {step:.3g} units apart ({100 * step / size:.2g} % of the face's size), so a "
                "correction there would be off by that much. Move the origin onto the face (Object > Set Origin > "
                "Origin to Geometry, which keeps it where it is in the scene) and run again.")
    return obj


def mesh_triangles(mesh) -> np.ndarray:
    """(F,3) int64 triangles of a Blender mesh (its loop triangulation)."""
    mesh.calc_loop_triangles()
    tris = np.empty(len(mesh.loop_triangles) * 3, dtype=np.int32)
    mesh.loop_triangles.foreach_get("vertices", tris)
    return tris.reshape(-1, 3).astype(np.int64)


@dataclass(frozen=True)
class FaceTopology:
    """The face's surface as one piece: welded triangles and the representative of every vertex.

    Attributes
    ----------
    tris : (F,3) int64
        ``mesh_triangles`` with every corner replaced by its representative (same order and count);
        the duplicates are used by no triangle. The mesh's own triangles when nothing was welded.
    weld : Weld
        :class:`~facelab_addon.core.geometry.weld.Weld`: ``weld.representative`` (V,) int64.
    """

    tris: np.ndarray
    weld: Weld

    @property
    def n_duplicates(self) -> int:
        """Vertices welded onto a coincident twin (0 on a mesh without split seams)."""
        return self.weld.n_duplicates

    def spread(self, values):
        """(V, ...) ``values`` with each duplicate given its representative's value (``values`` itself when
        nothing was welded): what every mask, offset and position written back goes through."""
        return self.weld.spread(values)


def face_topology(obj, poses=()) -> FaceTopology:
    """The triangles of ``obj``'s mesh with the vertices split along seams welded (see the module docstring).

    Vertices are welded only when they coincide (within 1e-4 median edge lengths,
    :func:`~facelab_addon.core.geometry.weld.weld`) in the mesh, in every shape key and in every
    pose of ``poses``, and only where they close a seam (two pieces sewn edge to edge into one
    consistently oriented surface; a part merely touching the face, as ICT-FaceKit's eyelashes on the lid
    rims, stays apart): a lip cut (upper and lower lip coincident at rest) that a key or a read frame opens
    stays cut. On a mesh without such vertices the keys and ``poses`` are never read and ``tris`` is
    ``mesh_triangles(obj.data)`` itself.

    Parameters
    ----------
    obj : bpy.types.Object
        A mesh object.
    poses : iterable of (V,3) float array_like
        Further object-local positions the caller reads (evaluated frames); consumed lazily, only when
        the mesh has coincident vertices.

    Returns
    -------
    FaceTopology
    """
    mesh = obj.data
    tris = mesh_triangles(mesh)
    n = len(mesh.vertices)
    rest = np.empty(n * 3, dtype=np.float64)
    mesh.vertices.foreach_get("co", rest)

    def keys():
        sk = mesh.shape_keys
        for kb in (sk.key_blocks if sk is not None else ()):
            co = np.empty(n * 3, dtype=np.float64)
            kb.data.foreach_get("co", co)
            yield co.reshape(n, 3)

    w = weld(tris, rest.reshape(n, 3), chain(keys(), poses))
    return FaceTopology(tris=w.faces, weld=w)


def spread_key_offsets(obj, names, topology: FaceTopology) -> None:
    """Give every duplicate of ``topology`` its representative's offset in the shape keys ``names`` of ``obj``.

    The offset of a key is its positions minus its relative key's; a duplicate's new position is its own
    relative-key position plus its representative's offset (written with ``foreach_set``). Nothing happens
    when ``topology`` welded nothing.
    """
    if topology.n_duplicates == 0:
        return
    blocks = obj.data.shape_keys.key_blocks
    n = len(obj.data.vertices)
    co = np.empty(n * 3, dtype=np.float64)
    base = np.empty(n * 3, dtype=np.float64)
    for name in names:
        kb = blocks[name]
        kb.data.foreach_get("co", co)
        kb.relative_key.data.foreach_get("co", base)
        B = base.reshape(n, 3)
        out = B + topology.spread(co.reshape(n, 3) - B)
        kb.data.foreach_set("co", out.astype(np.float32).ravel())
    obj.data.update()


def evaluated_vertices(obj, depsgraph, *, world: bool = True) -> np.ndarray:
    """(V,3) float64 positions of the evaluated mesh (shape keys, modifiers) on the current frame.

    Raises
    ------
    MeshError
        When modifiers change the vertex count (the correction could not be
        mapped back to the mesh), or Blender does not evaluate ``obj``
        (:func:`~facelab_addon.blender.objects.evaluated_object`).
    """
    ev = evaluated_object(obj, depsgraph)
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
            f"disable the topology-changing one (Subdivision, Decimate...) among its enabled modifiers "
            f"({enabled_modifier_names(obj)}) before using FaceLab."
        )
    co = co.reshape(-1, 3)
    if world:
        M = np.array(ev.matrix_world, dtype=np.float64)
        co = co @ M[:3, :3].T + M[:3, 3]
    return co


def world_winding(tris, A) -> np.ndarray:
    """(F,3) triangles ``tris`` wound for world-space positions of an object whose world matrix is ``A`` (3,3).

    A mirroring world matrix (negative determinant: a scale of -1 on the object, a parent or an Armature
    parent) turns every triangle's corner order over, so normals computed from world positions with the
    mesh's own triangles point into the face: silhouettes would face away from the camera and the upper
    and lower lip (told apart by their normals) swap. Then the corners' order is reversed (a new array);
    otherwise ``tris`` itself is returned.
    """
    A = np.asarray(A, dtype=np.float64)
    if np.linalg.det(A[:3, :3]) < 0:
        return np.ascontiguousarray(np.asarray(tris)[:, ::-1])
    return tris


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


def default_fixed_mask(obj, topology: FaceTopology, group: str = FIXED_GROUP):
    """Vertices that must not move and are never lip silhouettes.

    The vertex group ``group`` if the mesh has one; otherwise every vertex that
    is not on the largest connected piece of the welded surface ``topology`` (:func:`face_topology`: a seam
    split does not make a piece), that is teeth, tongue, eyes and other separate parts:
    :func:`~facelab_addon.core.lips.sketch_prior.separate_parts`, the default of ``refine_lips`` too.
    Each duplicate takes its representative's value.

    Returns
    -------
    mask : (V,) bool
    source : str
        ``"vertex group <name>"`` or ``"separate mesh parts"``.
    """
    m = vertex_group_mask(obj, group)
    if m is not None:
        return topology.spread(m), f"vertex group '{group}'"
    return topology.spread(separate_parts(topology.tris, len(obj.data.vertices))), "separate mesh parts"
