"""Objects and meshes -> arrays, beyond :mod:`.mesh`: world transforms over frames, world points in
an object's space, loop-triangle UVs, and whether two meshes share their topology."""

from __future__ import annotations

import numpy as np

from .camera import evaluated_depsgraph

__all__ = ["world_affine", "world_matrices", "points_to_local", "triangle_uvs", "same_polygons"]


def world_affine(obj, depsgraph=None):
    """``(A (3,3), b (3,))`` of the object's world matrix (evaluated in ``depsgraph`` when given)."""
    M = np.array((obj.evaluated_get(depsgraph) if depsgraph else obj).matrix_world, dtype=np.float64)
    return M[:3, :3], M[:3, 3]


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
