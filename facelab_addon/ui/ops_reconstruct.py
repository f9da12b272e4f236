"""Reconstruct from Bundles (Cong, Lan & Fedkiw, local geometric indexing): gather the
face's dataset shapes and the animated bundles, call core, key the result, report."""

import time

import bpy
import numpy as np
from bpy.props import IntProperty

from ..blender.bundles import bundle_objects, read_bundles
from ..blender.mesh import mesh_triangles, require_mesh
from ..blender.shapekeys import add_keys_from_deltas, key_values_bulk, remove_keys, rest_vertices
from ..core.compress import compress
from ..core.errors import FaceLabError
from ..core.geometric_indexing import GeometricIndexer, bind_points
from .ops import face_object, poll_face

RECON_PREFIX = "FL_Recon_"


def dataset_shapes(obj):
    """(names, shapes (S,V,3)) object-local positions of the face's own shape keys (FaceLab's excluded)."""
    key = obj.data.shape_keys
    if key is None:
        raise FaceLabError(
            f"'{obj.name}' has no shape keys; the dataset of facial shapes must be shape keys of the face "
            "(at least 4)."
        )
    n = len(obj.data.vertices)
    basis = key.reference_key

    def co(kb):
        c = np.empty(n * 3, np.float64)
        kb.data.foreach_get("co", c)
        return c.reshape(n, 3)

    base = co(basis)
    names, shapes = [], []
    for kb in key.key_blocks:
        if kb == basis or kb.name.startswith("FL_"):
            continue
        names.append(kb.name)
        shapes.append(base + co(kb) - co(kb.relative_key))
    return names, np.array(shapes).reshape(-1, n, 3)


def triangle_uvs(mesh):
    """(F,3,2) UVs of the loop triangles (the active UV map), or None."""
    if not mesh.uv_layers:
        return None
    mesh.calc_loop_triangles()
    loops = np.empty(len(mesh.loop_triangles) * 3, np.int32)
    mesh.loop_triangles.foreach_get("loops", loops)
    uv = np.empty(len(mesh.loops) * 2, np.float64)
    mesh.uv_layers.active.data.foreach_get("uv", uv)
    return uv.reshape(-1, 2)[loops].reshape(-1, 3, 2)


def to_local(obj, world):
    """World points (...,3) -> the object's local space."""
    M = np.linalg.inv(np.array(obj.matrix_world, dtype=np.float64))
    return world @ M[:3, :3].T + M[:3, 3]


class FACELAB_OT_reconstruct_from_bundles(bpy.types.Operator):
    """Rebuild the high-resolution face on every frame from animated 3D bundles and the face's shape-key dataset (local geometric indexing); the result passes through the bundles and is keyed as corrective shape keys"""

    bl_idname = "facelab.reconstruct_from_bundles"
    bl_label = "Reconstruct from Bundles"
    bl_options = {"REGISTER", "UNDO"}

    frame_start: IntProperty(name="Start", default=-1, description="First frame (-1: the scene's start)")
    frame_end: IntProperty(name="End", default=-1, description="Last frame (-1: the scene's end)")
    bind_frame: IntProperty(name="Bind Frame", default=-1,
                            description="Frame where the face is neutral: bundles are bound to the surface there "
                                        "(-1: the first frame)")
    smooth: IntProperty(name="Smoothing", default=1, min=1, max=15,
                        description="Central moving average of the barycentric weights over this many frames")

    @classmethod
    def poll(cls, context):
        return poll_face(cls, context)

    def execute(self, context):
        scene = context.scene
        t0 = time.perf_counter()
        f0 = scene.frame_start if self.frame_start < 0 else self.frame_start
        f1 = scene.frame_end if self.frame_end < 0 else self.frame_end
        frames = np.arange(f0, f1 + 1)
        bind = f0 if self.bind_frame < 0 else self.bind_frame
        try:
            obj = require_mesh(face_object(context))
            tris = mesh_triangles(obj.data)
            neutral = rest_vertices(obj)
            names, shapes = dataset_shapes(obj)
            objs = [o for o in bundle_objects(context) if o != obj]
            q_bind = to_local(obj, read_bundles(scene, objs, [bind])[0])
            bf, bb, _ = bind_points(neutral, tris, q_bind)
            indexer = GeometricIndexer(neutral, tris, shapes, bf, bb, names=names, uvs=triangle_uvs(obj.data))
            Q = to_local(obj, read_bundles(scene, objs, frames))
            try:
                X, skipped = indexer.reconstruct_sequence(Q, smooth=self.smooth)
            finally:
                indexer.close()
            D = X - neutral[None]
            D[np.isnan(D)] = 0.0  # skipped frames show the neutral
            basis, weights = compress(D, metres_per_unit=scene.unit_settings.scale_length or 1.0)
        except FaceLabError as e:
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        remove_keys(obj, RECON_PREFIX)
        keys = add_keys_from_deltas(obj, RECON_PREFIX, basis)
        if keys:
            key_values_bulk(obj, keys, frames, weights)
        live = [kb.name for kb in obj.data.shape_keys.key_blocks[1:] if not kb.name.startswith("FL_") and kb.value]
        msg = (f"Reconstructed {len(frames) - len(skipped):,} frames from {Q.shape[1]} bundles and {len(names)} "
               f"shapes in {time.perf_counter() - t0:.1f} s: {len(keys)} corrective keys ({RECON_PREFIX}*), "
               f"{indexer.stats['tetrahedra_kept']:,} tetrahedra ({indexer.stats['memory_bytes_total'] / 2**20:.0f} MB)")
        if skipped:
            msg += f"; skipped {len(skipped)} frames with missing bundles: {[int(frames[i]) for i in skipped][:10]}"
        if live:
            msg += f"; note: dataset keys {live[:5]} are not zero and add on top"
        self.report({"WARNING"} if skipped or live else {"INFO"}, msg)
        return {"FINISHED"}


classes = (FACELAB_OT_reconstruct_from_bundles,)
register, unregister = bpy.utils.register_classes_factory(classes)
