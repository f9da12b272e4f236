"""3D bundles and jaw poses from Blender data -> arrays (Cong, Lan & Fedkiw, local geometric indexing).

Bundle sources (world space, scene units; (T,B,3) with NaN where a bundle is
missing):

* **empties**: one bundle per empty, animated by keys, constraints or
  drivers. An empty disabled in renders (``hide_render``, the camera icon,
  keyed where its track is lost) or hidden in the viewport on a frame is
  missing on that frame (hiding in the viewport also drops it from the
  selection, so key ``hide_render`` when the bundles are selected);
* **a point mesh** (a vertex list): one bundle per vertex, animated by shape
  keys, a Mesh Cache (PC2/MDD) or an Alembic Mesh Sequence Cache: its
  evaluated vertices are read on every frame; NaN coordinates are missing;
* **a Movie Clip's tracking reconstruction**: one *static* 3D point per
  solved track (Blender's camera/object solve gives no per-frame 3D
  positions); :func:`tracking_bundles` reads them and
  :func:`empties_from_tracks` turns them into empties that can then be
  animated or constrained.

Jaw poses (:func:`jaw_poses`): the rigid motion of a jaw bone or of any
object relative to the bind frame, in the face's object space, as (T,4,4)
matrices; skinning weights from a vertex group (:func:`vertex_group_weights`).
"""

from __future__ import annotations

import bpy
import numpy as np

from ..core.errors import BundleError, FaceLabError
from ..names import BUNDLES_COLLECTION, TRACK_EMPTY_PREFIX

__all__ = [
    "bundle_objects",
    "collection_bundles",
    "bundle_labels",
    "read_bundles",
    "tracking_bundles",
    "empties_from_tracks",
    "vertex_group_weights",
    "jaw_poses",
]


def bundle_objects(selected=(), source: str = "SELECTED", *, collection=None, mesh=None, exclude=()):
    """The bundle objects for a source, sorted by name.

    Parameters
    ----------
    selected : iterable of bpy.types.Object
        The selected objects (``context.selected_objects``), for ``SELECTED``.
    source : {"SELECTED", "COLLECTION", "MESH"}
        ``SELECTED``: the selected empties and point meshes, else the objects
        of the collection :data:`~facelab_addon.names.BUNDLES_COLLECTION`;
        ``COLLECTION``: the empties and meshes of ``collection``; ``MESH``:
        the point mesh ``mesh``.
    exclude : objects never used as bundles (the face).

    Raises
    ------
    FaceLabError
        When the source holds no bundle (the message names the fix).
    """
    ok = ("EMPTY", "MESH")
    if source == "MESH":
        if mesh is None or mesh.type != "MESH":
            raise FaceLabError("Bundle source is 'Point Mesh' but no mesh is set; pick the mesh whose vertices are "
                               "the bundles (animated by shape keys or a mesh cache).")
        return [mesh]
    if source == "COLLECTION":
        if collection is None:
            raise FaceLabError("Bundle source is 'Collection' but no collection is set; pick the collection of "
                               "bundle empties.")
        objs = [o for o in collection.all_objects if o.type in ok and o not in exclude]
        if not objs:
            raise FaceLabError(f"Collection '{collection.name}' holds no empties or point meshes to use as bundles.")
        return sorted(objs, key=lambda o: o.name)
    sel = [o for o in selected if o.type in ok and o not in exclude]
    if sel:
        return sorted(sel, key=lambda o: o.name)
    coll = bpy.data.collections.get(BUNDLES_COLLECTION)
    if coll is not None:
        objs = [o for o in coll.all_objects if o.type in ok and o not in exclude]
        if objs:
            return sorted(objs, key=lambda o: o.name)
    raise FaceLabError(
        "No bundles: select the bundle empties (or a point mesh), or put them in a collection named "
        f"'{BUNDLES_COLLECTION}', or pick a bundle source in FaceLab > Reconstruct from Bundles."
    )


def collection_bundles(collection=None) -> list:
    """The empties and point meshes of ``collection`` (default: the collection
    :data:`~facelab_addon.names.BUNDLES_COLLECTION`), sorted by name: the solve's bundles.

    Raises
    ------
    BundleError
        When there are none.
    """
    coll = collection or bpy.data.collections.get(BUNDLES_COLLECTION)
    objs = sorted([o for o in coll.all_objects if o.type in ("EMPTY", "MESH")], key=lambda o: o.name) if coll else []
    if not objs:
        raise BundleError(
            "Bundles are set to Empties but there are none: put the bundle empties in a collection and pick it as "
            f"the Bundle Collection (or name it '{BUNDLES_COLLECTION}'), or set Bundles to None."
        )
    return objs


def bundle_labels(objects) -> list:
    """One name per bundle: the empty's name, or ``mesh[vertex]`` for point meshes."""
    out = []
    for ob in objects:
        if ob.type == "MESH":
            out += [f"{ob.name}[{i}]" for i in range(len(ob.data.vertices))]
        else:
            out.append(ob.name)
    return out


def read_bundles(scene, objects, frames, *, progress=None) -> np.ndarray:
    """(T,B,3) world positions of the bundles on ``frames``; NaN where a bundle is missing.

    Each empty is one bundle (missing where it is disabled in renders or hidden);
    each point-mesh object contributes one bundle per vertex (its evaluated
    vertices: shape keys, Mesh Cache and Alembic modifiers apply). The scene
    frame is restored afterwards.
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
                    if len(co) != 3 * len(ob.data.vertices):
                        raise FaceLabError(f"Point mesh '{ob.name}' changes its vertex count on frame {f}; "
                                           "bundles must keep one vertex each.")
                    row.append(co.reshape(-1, 3) @ M[:3, :3].T + M[:3, 3])
                elif ob.hide_render or ob.hide_viewport:
                    row.append(np.full((1, 3), np.nan))
                else:
                    row.append(M[None, :3, 3])
            out.append(np.concatenate(row))
            if progress:
                progress(i, len(frames))
    finally:
        scene.frame_set(keep)
    return np.stack(out)


def tracking_bundles(clip, tracking_object=None):
    """Reconstructed bundles of a Movie Clip (solved tracks only), reconstruction space.

    Blender's tracking solve gives one static 3D point per track.

    Returns
    -------
    names : list of str
        Track names.
    points : (B,3) float64 ndarray

    Raises
    ------
    FaceLabError
        When the clip has no valid solve or no solved track.
    """
    tr = clip.tracking
    obj = tracking_object or tr.objects.active
    if not obj.reconstruction.is_valid:
        raise FaceLabError(
            f"Movie Clip '{clip.name}' has no valid camera solve; press Solve Camera Motion in the Clip editor first."
        )
    tracks = [t for t in obj.tracks if t.has_bundle]
    if not tracks:
        raise FaceLabError(f"Movie Clip '{clip.name}' has no reconstructed bundles; solve the tracks first.")
    return [t.name for t in tracks], np.asarray([t.bundle[:] for t in tracks], dtype=np.float64)


def empties_from_tracks(scene, clip, collection_name: str = BUNDLES_COLLECTION):
    """One empty per solved track of ``clip``, constrained to it (Follow Track, 3D position), in a collection.

    The empties sit on the static reconstructed bundles (Blender's solve has
    one 3D point per track); they become animated bundles once they are
    animated or re-constrained (e.g. per-frame triangulated positions).
    Existing empties are never replaced (new names get ``.001``...).

    Returns
    -------
    list of bpy.types.Object
    """
    names, pts = tracking_bundles(clip)
    coll = bpy.data.collections.get(collection_name)
    if coll is None:
        coll = bpy.data.collections.new(collection_name)
        scene.collection.children.link(coll)
    out = []
    for n, p in zip(names, pts):
        e = bpy.data.objects.new(f"{TRACK_EMPTY_PREFIX}{n}", None)
        e.empty_display_type = "SPHERE"
        e.empty_display_size = 0.002
        e.location = p
        c = e.constraints.new("FOLLOW_TRACK")
        c.clip = clip
        c.track = n
        c.use_3d_position = True
        coll.objects.link(e)
        out.append(e)
    return out


def vertex_group_weights(obj, name: str):
    """(V,) float64 weights of vertex group ``name`` (0 where unassigned), or None if absent."""
    vg = obj.vertex_groups.get(name)
    if vg is None:
        return None
    n = len(obj.data.vertices)
    w = np.zeros(n)
    gi = vg.index
    for v in obj.data.vertices:
        for g in v.groups:
            if g.group == gi:
                w[v.index] = g.weight
                break
    return w


def _driver_matrix(source, armature, bone):
    if source == "BONE":
        pb = armature.pose.bones[bone]
        return np.array(armature.matrix_world, dtype=np.float64) @ np.array(pb.matrix, dtype=np.float64)
    return np.array(armature.matrix_world, dtype=np.float64)


def jaw_poses(scene, face, frames, bind_frame: int, *, source: str, driver, bone: str = ""):
    """(T,4,4) rigid jaw motion per frame relative to ``bind_frame``, in ``face``'s object space.

    Parameters
    ----------
    source : {"BONE", "OBJECT"}
        ``BONE``: pose bone ``bone`` of armature ``driver``; ``OBJECT``: the
        object ``driver`` (an empty, a jaw mesh...).
    bind_frame : int
        The frame where the jaw is at rest (the face is neutral).

    Raises
    ------
    FaceLabError
        For a missing driver or bone.
    """
    if driver is None:
        raise FaceLabError("Jaw source is set but no jaw armature/object is picked; pick it or set Jaw to None.")
    if source == "BONE":
        if driver.type != "ARMATURE" or bone not in driver.pose.bones:
            raise FaceLabError(f"Armature '{driver.name}' has no bone '{bone}'; pick the jaw bone.")
    keep = scene.frame_current
    Mf = np.array(face.matrix_world, dtype=np.float64)
    Mfi = np.linalg.inv(Mf)
    out = []
    try:
        scene.frame_set(int(bind_frame))
        M0i = np.linalg.inv(_driver_matrix(source, driver, bone))
        for f in frames:
            scene.frame_set(int(f))
            J = _driver_matrix(source, driver, bone) @ M0i
            out.append(Mfi @ J @ Mf)
    finally:
        scene.frame_set(keep)
    J = np.stack(out)
    # keep the rigid part (scale on the driver is not a jaw motion)
    U, _, Vt = np.linalg.svd(J[:, :3, :3])
    J[:, :3, :3] = U @ Vt
    return J
