"""Reconstruct from Bundles and Generate Correctives (Cong, Lan & Fedkiw, local geometric indexing):
gather the face's dataset shapes, the bundles and the jaw, call core, write new shape keys, report."""

import time

import bpy
import numpy as np
from bpy.props import EnumProperty, IntProperty, PointerProperty, StringProperty

from ..blender.bundles import (
    bundle_labels,
    bundle_objects,
    empties_from_tracks,
    jaw_poses,
    read_bundles,
    vertex_group_weights,
)
from ..blender.mesh import mesh_triangles, require_mesh
from ..blender.shapekeys import add_corrective_key, add_keys_from_deltas, key_values_bulk, remove_keys, rest_vertices
from ..core.errors import FaceLabError
from ..core.geometry.compress import compress
from ..core.lgi.binding import bind_points
from ..core.lgi.correctives import RigCorrectives
from ..core.lgi.indexer import GeometricIndexer
from ..core.lgi.jaw import JawRig
from .ops import face_object, poll_face, progress_callback

RECON_PREFIX = "FL_Recon_"
CORRECTIVE_PREFIX = "FL_Corr_"

BUNDLE_SOURCES = [
    ("SELECTED", "Selected",
     "Selected empties (one bundle each, animated) and point meshes; else the collection 'FL_bundles'"),
    ("COLLECTION", "Collection", "The empties (and point meshes) of a collection"),
    ("MESH", "Point Mesh",
     "A vertex list: every vertex of a mesh is a bundle, animated by shape keys, a Mesh Cache (PC2/MDD) or an "
     "Alembic cache"),
]
JAW_SOURCES = [
    ("NONE", "None", "No jaw articulation: the dataset shapes are blended as they are"),
    ("BONE", "Jaw Bone",
     "The jaw bone of an armature: its rotation and translation from the bind frame drive linear blend skinning "
     "(weights: the face's vertex group named after the bone)"),
    ("OBJECT", "Object", "Any object (an empty, a jaw mesh) whose motion from the bind frame is the jaw's"),
]


def _mesh_poll(self, ob):
    return ob.type == "MESH"


def _armature_poll(self, ob):
    return ob.type == "ARMATURE"


class FACELAB_PG_reconstruct(bpy.types.PropertyGroup):
    """Scene settings of Reconstruct from Bundles and Generate Correctives (``scene.facelab_recon``)."""

    bundle_source: EnumProperty(name="Bundles", items=BUNDLE_SOURCES, default="SELECTED")
    bundle_collection: PointerProperty(name="Collection", type=bpy.types.Collection)
    bundle_mesh: PointerProperty(name="Point Mesh", type=bpy.types.Object, poll=_mesh_poll)
    bind_frame: IntProperty(name="Bind Frame", default=-1,
                            description="Frame where the face is neutral: bundles are bound to the surface there "
                                        "(-1: the scene's first frame)")
    smooth: IntProperty(name="Smoothing", default=1, min=1, max=15,
                        description="Central moving average of the barycentric weights over this many frames "
                                    "(1: off); the surface then passes through the bundles' moving average")
    jaw_source: EnumProperty(name="Jaw", items=JAW_SOURCES, default="NONE")
    jaw_armature: PointerProperty(name="Armature", type=bpy.types.Object, poll=_armature_poll)
    jaw_bone: StringProperty(name="Bone", default="jaw")
    jaw_object: PointerProperty(name="Jaw Object", type=bpy.types.Object)
    jaw_group: StringProperty(name="Jaw Weights",
                              description="Vertex group of the face with the jaw's skinning weights (empty: the "
                                          "bone's name)")
    rig_object: PointerProperty(name="Rig", type=bpy.types.Object, poll=_mesh_poll,
                                description="Mesh whose shape keys are the template rig (same vertex order as the "
                                            "face); the correctives are added to it")
    combinations: StringProperty(name="Combinations", default="",
                                 description="Rig-shape combinations, e.g. 'noseSneer_L+mouthUpperUp_L, "
                                             "mouthSmile_L+jawOpen'")


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


def jaw_setup(scene, obj, recon, neutral, shapes, frames, bind):
    """(JawRig, shape poses (S,4,4), frame poses (T,4,4)) from the panel's jaw settings, or Nones."""
    if recon.jaw_source == "NONE":
        return None, None, None
    group = recon.jaw_group or (recon.jaw_bone if recon.jaw_source == "BONE" else "")
    w = vertex_group_weights(obj, group) if group else None
    if w is None or w.max() <= 0:
        raise FaceLabError(
            f"The face has no vertex group {group!r} with jaw skinning weights; paint one (1 on the chin and lower "
            "teeth, fading to 0 on the cheeks) and name it in Jaw Weights (for a bone: the bone's name)."
        )
    rig = JawRig(np.zeros(3), [1.0, 0.0, 0.0], w)
    shape_jaw = np.stack([rig.fit_pose(s, neutral) for s in shapes])  # every dataset shape's jaw pose (§6)
    driver = recon.jaw_armature if recon.jaw_source == "BONE" else recon.jaw_object
    J = jaw_poses(scene, obj, frames, bind, source=recon.jaw_source, driver=driver, bone=recon.jaw_bone)
    return rig, shape_jaw, J


class FACELAB_OT_reconstruct_from_bundles(bpy.types.Operator):
    """Rebuild the high-resolution face on every frame from animated 3D bundles and the face's shape-key dataset (local geometric indexing); the result passes through the bundles and is keyed as corrective shape keys"""

    bl_idname = "facelab.reconstruct_from_bundles"
    bl_label = "Reconstruct from Bundles"
    bl_options = {"REGISTER", "UNDO"}

    frame_start: IntProperty(name="Start", default=-1, description="First frame (-1: the scene's start)")
    frame_end: IntProperty(name="End", default=-1, description="Last frame (-1: the scene's end)")
    bind_frame: IntProperty(name="Bind Frame", default=-2,
                            description="Frame where the face is neutral (-1: the first frame; -2: the panel's "
                                        "setting)")
    smooth: IntProperty(name="Smoothing", default=0, min=0, max=15,
                        description="Moving average of the barycentric weights over this many frames (0: the "
                                    "panel's setting)")

    @classmethod
    def poll(cls, context):
        return poll_face(cls, context)

    def execute(self, context):
        scene = context.scene
        recon = scene.facelab_recon
        t0 = time.perf_counter()
        f0 = scene.frame_start if self.frame_start < 0 else self.frame_start
        f1 = scene.frame_end if self.frame_end < 0 else self.frame_end
        frames = np.arange(f0, f1 + 1)
        bind = self.bind_frame if self.bind_frame != -2 else recon.bind_frame
        bind = f0 if bind < 0 else bind
        smooth = self.smooth or recon.smooth
        try:
            obj = require_mesh(face_object(context))
            tris = mesh_triangles(obj.data)
            neutral = rest_vertices(obj)
            names, shapes = dataset_shapes(obj)
            objs = bundle_objects(context, recon.bundle_source, collection=recon.bundle_collection,
                                  mesh=recon.bundle_mesh, exclude={obj})
            labels = bundle_labels(objs)
            Qw = read_bundles(scene, objs, np.r_[bind, frames])
            q_bind, Q = to_local(obj, Qw[0]), to_local(obj, Qw[1:])
            bf, bb, _ = bind_points(neutral, tris, q_bind, bundle_names=labels)
            jaw, shape_jaw, J = jaw_setup(scene, obj, recon, neutral, shapes, frames, bind)
            indexer = GeometricIndexer(neutral, tris, shapes, bf, bb, names=names, uvs=triangle_uvs(obj.data),
                                       jaw=jaw, shape_jaw=shape_jaw, bundle_names=labels)
            try:
                X, skipped = indexer.reconstruct_sequence(
                    Q, J, smooth=smooth, progress=progress_callback(context, len(frames), "FaceLab Reconstruct"))
            finally:
                indexer.close()
                context.window_manager.progress_end()
            if len(skipped) == len(frames):
                raise FaceLabError(
                    f"Every frame has missing bundles (e.g. {self._missing(Q, labels, skipped[:1])}); check the "
                    "bundles' animation over the frame range."
                )
            D = X - neutral[None]
            D[np.isnan(D)] = 0.0  # skipped frames show the neutral
            basis, weights = compress(D, metres_per_unit=scene.unit_settings.scale_length or 1.0)
        except FaceLabError as e:
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        remove_keys(obj, RECON_PREFIX)  # FaceLab's own previous reconstruction only
        keys = add_keys_from_deltas(obj, RECON_PREFIX, basis)
        if keys:
            key_values_bulk(obj, keys, frames, weights)
        live = [kb.name for kb in obj.data.shape_keys.key_blocks[1:] if not kb.name.startswith("FL_") and kb.value]
        st = indexer.stats
        msg = (f"Reconstructed {len(frames) - len(skipped):,} frames from {Q.shape[1]} bundles and {len(names)} "
               f"shapes in {time.perf_counter() - t0:.1f} s: {len(keys)} corrective keys ({RECON_PREFIX}*), "
               f"{st['tetrahedra_kept']:,} tetrahedra ({st['memory_bytes_total'] / 2**20:.0f} MB)"
               + (", jaw from " + (recon.jaw_bone if recon.jaw_source == "BONE" else recon.jaw_object.name)
                  if jaw is not None else "") + (f", smoothing {smooth} frames" if smooth > 1 else ""))
        if skipped:
            msg += (f"; skipped {len(skipped)} frames with missing bundles (shown neutral): "
                    f"{[int(frames[i]) for i in skipped][:10]} ({self._missing(Q, labels, skipped)})")
        if live:
            msg += f"; note: dataset keys {live[:5]} are not zero and add on top"
        self.report({"WARNING"} if skipped or live else {"INFO"}, msg)
        return {"FINISHED"}

    @staticmethod
    def _missing(Q, labels, skipped):
        bad = np.flatnonzero((~np.isfinite(Q[skipped])).any(axis=(0, 2)))
        if len(bad) == 0:
            return "no jaw pose"
        return "missing: " + ", ".join(labels[i] for i in bad[:5]) + ("..." if len(bad) > 5 else "")


def parse_combinations(text: str) -> list:
    """'a+b, c+d+e' -> [("a", "b"), ("c", "d", "e")] (commas, semicolons or new lines separate)."""
    out = []
    for part in text.replace(";", ",").replace("\n", ",").split(","):
        names = tuple(n.strip() for n in part.split("+") if n.strip())
        if names:
            out.append(names)
    return out


def rig_shapes(rig_obj, neutral):
    """{name: (V,3)} the rig object's shape keys as deltas applied to the face's neutral (FaceLab's excluded)."""
    names, shapes = dataset_shapes(rig_obj)
    if shapes.shape[1] != len(neutral):
        raise FaceLabError(
            f"Rig '{rig_obj.name}' has {shapes.shape[1]} vertices, the face {len(neutral)}; the template rig must "
            "share the face's topology (transfer it onto the actor's neutral first)."
        )
    base = rest_vertices(rig_obj)
    return {n: neutral + (s - base) for n, s in zip(names, shapes)}


def _add_product_driver(key, kb, components):
    """Drive ``kb.value`` by the product of the component keys' values (a combination corrective)."""
    fc = kb.driver_add("value")
    drv = fc.driver
    drv.type = "SCRIPTED"
    terms = []
    for i, name in enumerate(components):
        v = drv.variables.new()
        v.name = f"w{i}"
        v.type = "SINGLE_PROP"
        v.targets[0].id_type = "KEY"
        v.targets[0].id = key
        v.targets[0].data_path = f'key_blocks["{bpy.utils.escape_identifier(name)}"].value'
        terms.append(v.name)
    drv.expression = " * ".join(terms)
    return fc


class FACELAB_OT_generate_correctives(bpy.types.Operator):
    """Generate actor-specific corrective shapes for combinations of template rig shapes from the face's dataset (local geometric indexing of the dataset's nonlinear residuals, Fig. 7); adds them as new shape keys on the rig, driven by the product of their components"""

    bl_idname = "facelab.generate_correctives"
    bl_label = "Generate Correctives"
    bl_options = {"REGISTER", "UNDO"}

    combinations: StringProperty(name="Combinations", default="",
                                 description="e.g. 'noseSneer_L+mouthUpperUp_L, mouthSmile_L+jawOpen' (empty: the "
                                             "panel's)")
    bundles: IntProperty(name="Bundles", default=100, min=8, max=2000,
                         description="Bundles placed automatically over the region the rig moves")
    drivers: bpy.props.BoolProperty(name="Drive by Components", default=True,
                                    description="Drive each corrective by the product of its components' values")

    @classmethod
    def poll(cls, context):
        return poll_face(cls, context)

    def execute(self, context):
        scene = context.scene
        recon = scene.facelab_recon
        t0 = time.perf_counter()
        try:
            obj = require_mesh(face_object(context))
            rig_obj = recon.rig_object
            if rig_obj is None or rig_obj == obj:
                raise FaceLabError(
                    "Pick the template rig (a mesh with the rig's shape keys, same vertex order as the face) in "
                    "Reconstruct > Rig; the face's own shape keys are the actor's dataset."
                )
            combos = parse_combinations(self.combinations or recon.combinations)
            if not combos:
                raise FaceLabError("No combinations: type them as 'shapeA+shapeB, shapeC+shapeD' in Combinations.")
            tris = mesh_triangles(obj.data)
            neutral = rest_vertices(obj)
            names, shapes = dataset_shapes(obj)
            rig = rig_shapes(rig_obj, neutral)
            unknown = sorted({n for c in combos for n in c if n not in rig})
            if unknown:
                raise FaceLabError(f"The rig '{rig_obj.name}' has no shape keys {unknown[:5]}; check the names "
                                   f"(rig keys: {list(rig)[:8]}...).")
            rc = RigCorrectives(neutral, tris, rig, shapes, dataset_names=names, n_bundles=self.bundles,
                                uvs=triangle_uvs(obj.data))
            try:
                results = [(c,) + rc.corrective(c) for c in combos]
            finally:
                rc.close()
        except FaceLabError as e:
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        added = []
        for combo, corr, info in results:
            kb = add_corrective_key(rig_obj, CORRECTIVE_PREFIX + "+".join(combo), corr)  # unique name: never overwrites
            if self.drivers:
                _add_product_driver(rig_obj.data.shape_keys, kb, combo)
            added.append((kb.name, float(np.linalg.norm(corr, axis=1).max()), info["projected"]))
        unit = scene.unit_settings.scale_length or 1.0
        msg = (f"Added {len(added)} corrective keys to '{rig_obj.name}' in {time.perf_counter() - t0:.1f} s "
               f"(dataset {len(rc.dataset_names)} shapes, {rc.indexer.B} bundles): "
               + ", ".join(f"{n} (max {d * unit * 1e3:.2f} mm)" for n, d, _ in added[:6]))
        beyond = [n for n, _, p in added if p]
        if rc.dropped:
            msg += f"; dataset shapes without rig content left out: {rc.dropped[:5]}"
        if beyond:
            msg += f"; {beyond[:3]} go beyond the dataset at some bundles (add such combinations to it)"
        self.report({"INFO"}, msg)
        return {"FINISHED"}


class FACELAB_OT_bundles_from_clip(bpy.types.Operator):
    """Create one bundle empty per solved track of the active Movie Clip (static: Blender's solve has one 3D point per track), in the collection FL_bundles"""

    bl_idname = "facelab.bundles_from_clip"
    bl_label = "Bundles from Tracking"
    bl_options = {"REGISTER", "UNDO"}

    clip: StringProperty(name="Movie Clip", default="", description="Movie Clip name (empty: the scene's active clip)")

    def execute(self, context):
        scene = context.scene
        clip = bpy.data.movieclips.get(self.clip) if self.clip else scene.active_clip
        if clip is None:
            self.report({"ERROR"}, "No Movie Clip: set the scene's active clip (or name one) with a solved camera.")
            return {"CANCELLED"}
        try:
            empties = empties_from_tracks(scene, clip)
        except FaceLabError as e:
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        self.report({"INFO"}, f"Added {len(empties)} bundle empties in 'FL_bundles' from '{clip.name}' (static "
                              "bundles: animate them or constrain them per frame before Reconstruct)")
        return {"FINISHED"}


classes = (FACELAB_PG_reconstruct, FACELAB_OT_reconstruct_from_bundles, FACELAB_OT_generate_correctives,
           FACELAB_OT_bundles_from_clip)
_register, _unregister = bpy.utils.register_classes_factory(classes)


def register():
    _register()
    bpy.types.Scene.facelab_recon = PointerProperty(type=FACELAB_PG_reconstruct)


def unregister():
    del bpy.types.Scene.facelab_recon
    _unregister()
