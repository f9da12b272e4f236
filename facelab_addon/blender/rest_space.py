"""Corrections measured on the deformed mesh -> shape-key offsets in rest space.

A correction FaceLab computes on the *evaluated* mesh (after an Armature, a Lattice, any
deforming modifier) must be stored as a shape-key offset *before* those modifiers, or the rig
deforms it a second time. :func:`to_rest_space` maps each vertex's wanted displacement back
through the inverse of the per-vertex Jacobian of the modifier stack on that frame, as Blender's
corrective shape-key tools do for armatures. When an Armature deforming by linear-blend skinning
is the only deformer, each vertex's Jacobian is the weighted mean of its bones' pose matrices
(one scene evaluation per frame). Any other stack is measured numerically: it is evaluated with
temporary unit offsets along x, y and z (three temporary shape keys), which is exact for any
affine deformer; one Newton step, verified on the evaluated mesh, corrects stacks that bend
space non-linearly.

Capture caches (Mesh Cache, Mesh Sequence Cache) and FaceLab's own correction caches are not
part of the map (their Integrate mapping is ``cache_integrate``'s). Displacements are
object-local, scene units: ``deltas[t, i]`` is the wanted change of the evaluated position of
vertex ``vertices[i]`` on ``frames[t]``.
"""

from __future__ import annotations

import bpy
import numpy as np

from ..core.errors import MeshError
from ..names import REST_SPACE_KEY
from .caches import kept_frame, set_frame
from .objects import evaluated_object
from .ownership import is_correction_cache

__all__ = ["deforming_modifiers", "require_same_vertex_count", "to_rest_space"]

_CACHE_TYPES = ("MESH_CACHE", "MESH_SEQUENCE_CACHE")


def deforming_modifiers(obj) -> list:
    """The enabled (viewport) modifiers of ``obj`` a correction must be mapped back through.

    Every enabled modifier except capture caches and FaceLab's correction caches (Mesh Cache,
    Mesh Sequence Cache, a correction patch), whose mapping is :mod:`.cache_integrate`'s.
    """
    return [m for m in obj.modifiers if m.show_viewport and m.type not in _CACHE_TYPES and not is_correction_cache(obj, m)]


def _evaluated(obj, dg, n):
    ev = evaluated_object(obj, dg)
    me = ev.to_mesh()
    try:
        m = len(me.vertices)
        if m != n:
            raise MeshError(
                f"The modifiers of '{obj.name}' change its vertex count ({n} -> {m}), so a correction cannot be "
                f"mapped back to its shape keys; disable or apply the topology-changing modifiers "
                f"({', '.join(repr(md.name) for md in deforming_modifiers(obj)) or 'none enabled'}) first."
            )
        co = np.empty(n * 3, np.float64)
        me.vertices.foreach_get("co", co)
    finally:
        ev.to_mesh_clear()
    return co.reshape(n, 3)


def require_same_vertex_count(obj, depsgraph=None) -> None:
    """Refuse a modifier stack that changes the vertex count (Subdivision, Decimate, Remesh...).

    Raises
    ------
    MeshError
        Naming the enabled modifiers and the fix.
    """
    dg = depsgraph or bpy.context.evaluated_depsgraph_get()
    _evaluated(obj, dg, len(obj.data.vertices))


def _solve(J, d):
    """``J⁻¹ d`` per vertex (pseudo-inverse where a deformer flattens a vertex)."""
    det = np.linalg.det(J)
    scale = np.maximum(np.abs(J).max(axis=(1, 2)), 1e-300) ** 3
    ok = np.abs(det) > 1e-9 * scale
    out = np.empty_like(d)
    if ok.any():
        out[ok] = np.linalg.solve(J[ok], d[ok][..., None])[..., 0]
    if (~ok).any():
        out[~ok] = (np.linalg.pinv(J[~ok]) @ d[~ok][..., None])[..., 0]
    return out


def _linear_armature(obj):
    """The Armature modifier when it is the only deformer and deforms by linear-blend skinning, else None.

    Linear: vertex groups only (no envelopes, no preserve volume, no multi-modifier, no mask group) and
    no deforming B-Bone segments, so each vertex's Jacobian is the weighted mean of its bones' matrices.
    """
    mods = deforming_modifiers(obj)
    if len(mods) != 1 or mods[0].type != "ARMATURE":
        return None
    md = mods[0]
    arm = md.object
    if arm is None or arm.type != "ARMATURE" or not md.use_vertex_groups or md.use_bone_envelopes \
            or md.use_deform_preserve_volume or md.use_multi_modifier or md.vertex_group:
        return None
    if any(b.use_deform and b.bbone_segments > 1 for b in arm.data.bones):
        return None
    return md


def _skin_weights(obj, arm):
    """(V,B) float64 weights of ``arm``'s deforming bones from ``obj``'s vertex groups, and the bone names."""
    bones = [b.name for b in arm.data.bones if b.use_deform and b.name in obj.vertex_groups]
    col = {obj.vertex_groups[b].index: k for k, b in enumerate(bones)}
    W = np.zeros((len(obj.data.vertices), len(bones)))
    for v in obj.data.vertices:
        for g in v.groups:
            k = col.get(g.group)
            if k is not None:
                W[v.index, k] = g.weight
    return W, bones


def _armature_jacobians(obj, md, frames, idx, W, bones):
    """(T,n,3,3) object-space Jacobians of a linear-blend-skinning Armature on ``frames``."""
    scene = bpy.context.scene
    Wv = W[idx]
    contrib = Wv.sum(axis=1)
    skinned = contrib > 1e-4  # Blender's threshold: below it the vertex is left where it is
    out = np.empty((len(frames), len(idx), 3, 3))
    with kept_frame(scene):
        for t, f in enumerate(frames):
            set_frame(scene, float(f))
            dg = bpy.context.evaluated_depsgraph_get()
            arm = md.object.evaluated_get(dg)
            ob = obj.evaluated_get(dg)
            pre = np.array(arm.matrix_world.inverted() @ ob.matrix_world, dtype=np.float64)[:3, :3]
            M = np.stack([np.array(arm.pose.bones[b].matrix @ arm.data.bones[b].matrix_local.inverted(),
                                   dtype=np.float64)[:3, :3] for b in bones]) if bones else np.zeros((0, 3, 3))
            J = np.einsum("vb,bij->vij", Wv, M)
            J[skinned] /= contrib[skinned, None, None]
            J[~skinned] = np.eye(3)
            out[t] = np.linalg.inv(pre) @ J @ pre  # object space: pre⁻¹ J pre
    return out


def to_rest_space(obj, frames, deltas, vertices=None, depsgraph=None, *, newton: bool = True,
                  numeric: bool = False) -> np.ndarray:
    """Shape-key offsets that show as ``deltas`` on the evaluated mesh of ``obj``.

    Parameters
    ----------
    obj : bpy.types.Object
        Mesh object in the active view layer.
    frames : (T,) array_like of float
        Scene frames of the rows of ``deltas``.
    deltas : (T,n,3) array_like
        Wanted displacement of the evaluated vertices, object-local scene units.
    vertices : (n,) int array_like, optional
        Vertex ids of the columns of ``deltas`` (default: every vertex).
    depsgraph : bpy.types.Depsgraph, optional
        The evaluated depsgraph (default: the context's).
    newton : bool
        Numeric path: verify each frame on the evaluated mesh and take one Newton step where the
        stack is not linear (skipped after the first frame when the stack is affine to float precision).
    numeric : bool
        Measure the Jacobian numerically even for a plain Armature (a cross-check).

    Returns
    -------
    (T,n,3) float64 ndarray
        Rest-space offsets, object-local scene units; ``deltas`` itself (as float64) when no
        modifier deforms the mesh.

    Raises
    ------
    MeshError
        The modifier stack changes the vertex count, or ``deltas`` has the wrong shape.

    Notes
    -----
    A plain Armature costs one scene evaluation per frame; the numeric path four (five with the
    Newton check). The scene frame, the shape keys and the active key are restored afterwards, also on
    errors.
    """
    D = np.asarray(deltas, dtype=np.float64)
    frames = np.atleast_1d(np.asarray(frames, dtype=np.float64))
    n_all = len(obj.data.vertices)
    idx = np.arange(n_all) if vertices is None else np.asarray(vertices, dtype=np.int64)
    if D.ndim != 3 or D.shape != (len(frames), len(idx), 3):
        raise MeshError(f"deltas must be ({len(frames)},{len(idx)},3) for {len(frames)} frames of {len(idx)} "
                        f"vertices, got {D.shape}.")
    if not deforming_modifiers(obj) or len(frames) == 0:
        return D.copy()
    md = None if numeric else _linear_armature(obj)
    if md is not None:  # analytic: weighted bone matrices, one scene evaluation per frame
        require_same_vertex_count(obj, depsgraph)
        W, bones = _skin_weights(obj, md.object)
        out = np.empty_like(D)
        for i in range(0, len(frames), 64):
            J = _armature_jacobians(obj, md, frames[i:i + 64], idx, W, bones)
            for t in range(len(J)):
                out[i + t] = _solve(J[t], D[i + t])
        return out
    scene = depsgraph.scene if depsgraph is not None else bpy.context.scene
    made_basis = obj.data.shape_keys is None
    if made_basis:
        obj.shape_key_add(name="Basis", from_mix=False)
    key = obj.data.shape_keys
    basis = key.reference_key
    rest = np.empty(n_all * 3, np.float64)
    basis.data.foreach_get("co", rest)
    rest = rest.reshape(n_all, 3)
    ext = rest.max(axis=0) - rest.min(axis=0)
    h = 0.01 * float(ext.max()) if ext.max() > 0 else 1.0  # LBS is affine: exact for any step
    active = obj.active_shape_key_index
    temp = []
    out = np.empty_like(D)
    linear = False
    try:
        for k in range(3):  # three temporary keys: +h along x, y, z on the vertices asked for
            kb = obj.shape_key_add(name=f"{REST_SPACE_KEY}{'xyz'[k]}", from_mix=False)
            kb.relative_key = basis
            co = rest.copy()
            co[idx, k] += h
            kb.data.foreach_set("co", co.astype(np.float32).ravel())
            kb.slider_min, kb.slider_max = -10.0, 10.0
            kb.value = 0.0
            temp.append(kb)
        probe = obj.shape_key_add(name=f"{REST_SPACE_KEY}c", from_mix=False)  # the Newton check
        probe.relative_key = basis
        probe.value = 0.0
        temp.append(probe)
        with kept_frame(scene):
            for t, f in enumerate(frames):
                set_frame(scene, float(f))
                dg = bpy.context.evaluated_depsgraph_get()
                base = _evaluated(obj, dg, n_all)[idx]
                J = np.empty((len(idx), 3, 3))
                for k in range(3):
                    temp[k].value = 1.0
                    dg.update()
                    J[:, :, k] = (_evaluated(obj, dg, n_all)[idx] - base) / h
                    temp[k].value = 0.0
                c = _solve(J, D[t])
                if newton and not linear and np.any(D[t]):
                    co = rest.copy()
                    co[idx] += c
                    probe.data.foreach_set("co", co.astype(np.float32).ravel())
                    probe.value = 1.0
                    dg.update()
                    shown = _evaluated(obj, dg, n_all)[idx] - base
                    probe.value = 0.0
                    res = D[t] - shown
                    size = float(np.abs(D[t]).max())
                    if float(np.abs(res).max()) <= 1e-4 * size + 4e-7 * float(np.abs(rest).max()):  # float32
                        linear = True  # affine stack: later frames need no check
                    else:
                        c = c + _solve(J, res)
                out[t] = c
    finally:
        for kb in reversed(temp):
            obj.shape_key_remove(kb)
        if made_basis and obj.data.shape_keys is not None:
            obj.shape_key_clear()
        obj.active_shape_key_index = min(active, max(len(obj.data.shape_keys.key_blocks) - 1, 0)) \
            if obj.data.shape_keys is not None else 0
        obj.data.update()
    return out
