"""3D bundles from Blender data -> (T,B,3) arrays (Cong, Lan & Fedkiw, local geometric indexing).

Sources: animated empties (one bundle each), the vertices of a point mesh
(one bundle per vertex, animated by shape keys or a cache), or the bundles
of a Movie Clip's tracking reconstruction (static: the same position on every
frame). Positions are world space, scene units; frames where a bundle has no
value are NaN.
"""

from __future__ import annotations

import bpy
import numpy as np

from ..core.errors import FaceLabError

__all__ = ["bundle_objects", "read_bundles", "tracking_bundles"]


def bundle_objects(context):
    """The bundle objects: selected empties, else the objects of a collection named 'FL_bundles'."""
    sel = [o for o in context.selected_objects if o.type == "EMPTY"]
    if sel:
        return sorted(sel, key=lambda o: o.name)
    coll = bpy.data.collections.get("FL_bundles")
    if coll is not None:
        objs = [o for o in coll.all_objects if o.type in ("EMPTY", "MESH")]
        if objs:
            return sorted(objs, key=lambda o: o.name)
    raise FaceLabError(
        "No bundles: select the bundle empties (or put them, or a point mesh, in a collection named "
        "'FL_bundles')."
    )


def read_bundles(scene, objects, frames, *, progress=None) -> np.ndarray:
    """(T,B,3) world positions of the bundles on ``frames``.

    Each empty is one bundle; each point-mesh object contributes one bundle per
    vertex (its evaluated vertices). The scene frame is restored afterwards.
    """
    frames = [int(f) for f in frames]
    keep = scene.frame_current
    out = []
    try:
        for i, f in enumerate(frames):
            scene.frame_set(f)
            dg = bpy.context.evaluated_depsgraph_get()
            row = []
            for ob in objects:
                ev = ob.evaluated_get(dg)
                M = np.array(ev.matrix_world, dtype=np.float64)
                if ob.type == "MESH":
                    me = ev.to_mesh()
                    co = np.empty(len(me.vertices) * 3)
                    me.vertices.foreach_get("co", co)
                    ev.to_mesh_clear()
                    row.append(co.reshape(-1, 3) @ M[:3, :3].T + M[:3, 3])
                else:
                    row.append(M[None, :3, 3])
            out.append(np.concatenate(row))
            if progress:
                progress(i, len(frames))
    finally:
        scene.frame_set(keep)
    return np.stack(out)


def tracking_bundles(clip, tracking_object=None) -> np.ndarray:
    """(B,3) reconstructed bundle positions of a Movie Clip (tracks with a bundle only), clip space.

    Raises ``FaceLabError`` when the clip has no camera solve.
    """
    tr = clip.tracking
    obj = tracking_object or tr.objects.active
    if not obj.reconstruction.is_valid:
        raise FaceLabError(
            f"Movie Clip '{clip.name}' has no valid camera solve; press Solve Camera Motion in the Clip editor first."
        )
    pts = [t.bundle[:] for t in obj.tracks if t.has_bundle]
    if not pts:
        raise FaceLabError(f"Movie Clip '{clip.name}' has no reconstructed bundles; solve the tracks first.")
    return np.asarray(pts, dtype=np.float64)
