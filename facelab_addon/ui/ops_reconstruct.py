"""Operators of Reconstruct from Bundles, Generate Correctives and Bundles from Tracking (Cong, Lan & Fedkiw,
local geometric indexing): gather the settings (:mod:`.props_reconstruct`), call
:mod:`facelab_addon.pipeline.reconstruct`, report."""

import bpy
from bpy.props import BoolProperty, IntProperty, StringProperty

from ..core.errors import FaceLabError
from ..names import BUNDLES_COLLECTION, RECONSTRUCT_PREFIX
from ..pipeline.frames import frame_range
from ..pipeline.reconstruct import (
    bundles_from_clip,
    generate_correctives,
    reconstruct_from_bundles,
)
from ..pipeline.shot_settings import corrective_settings, reconstruct_settings
from . import props_reconstruct
from .common import face_object, fill_scene_range, operator_range, poll_face, progress_callback


def _dataset_keys(obj) -> int:
    """Shape keys of ``obj`` besides its Basis (the dataset of Reconstruct / Generate Correctives)."""
    key = obj.data.shape_keys
    return max(0, len(key.key_blocks) - 1) if key is not None else 0


def bundles_problem(context) -> str | None:
    """Why Reconstruct has no bundles to read with the panel's bundle source (None when it has some)."""
    r = context.scene.facelab_recon
    face = face_object(context)
    if r.bundle_source == "COLLECTION":
        if r.bundle_collection is None or not len(r.bundle_collection.all_objects):
            return "No bundles: pick a Collection of bundle empties in Reconstruct from Bundles"
        return None
    if r.bundle_source == "MESH":
        return None if r.bundle_mesh is not None else "No bundles: pick the Point Mesh in Reconstruct from Bundles"
    picked = [o for o in context.selected_objects if o.type in ("EMPTY", "MESH") and o != face]
    coll = bpy.data.collections.get(BUNDLES_COLLECTION)
    if picked or (coll is not None and len(coll.all_objects)):
        return None
    return (f"No bundles: select the bundle empties (or point meshes), or fill the collection '{BUNDLES_COLLECTION}' "
            "(Bundles from Tracking), or pick another bundle source")


class FACELAB_OT_reconstruct_from_bundles(bpy.types.Operator):
    """Rebuild the high-resolution face on every frame from animated 3D bundles and the face's shape-key dataset (a bounded blendshape fit plus the noise-filtered residual at the bundles, or the exact local geometric indexing); the result is keyed as corrective shape keys"""

    bl_idname = "facelab.reconstruct_from_bundles"
    bl_label = "Reconstruct from Bundles"
    bl_options = {"REGISTER", "UNDO"}

    frame_start: IntProperty(name="Start", default=1, options={"SKIP_SAVE"},
                             description="First frame to rebuild (starts at the scene's start; negative frames "
                                         "are allowed)")
    frame_end: IntProperty(name="End", default=250, options={"SKIP_SAVE"},
                           description="Last frame to rebuild (starts at the scene's end)")
    bind_frame: IntProperty(name="Bind Frame", default=-2,
                            description="Frame where the face is neutral (-1: the first frame; -2: the panel's "
                                        "setting)")
    smooth: IntProperty(name="Smoothing", default=0, min=0, max=15,
                        description="Moving average of the barycentric weights over this many frames (0: the "
                                    "panel's setting)")

    @classmethod
    def poll(cls, context):
        if not poll_face(cls, context):
            return False
        if not _dataset_keys(face_object(context)):
            cls.poll_message_set("The face has no shape keys: Reconstruct needs at least 4 dataset shapes (the "
                                 "face's shape keys)")
            return False
        why = bundles_problem(context)
        if why:
            cls.poll_message_set(why)
            return False
        return True

    def execute(self, context):
        scene = context.scene
        f0, f1 = operator_range(self)
        settings = reconstruct_settings(scene, context.selected_objects, frame_start=f0, frame_end=f1,
                                        bind_frame=self.bind_frame, smooth=self.smooth)
        try:
            frames = frame_range(scene, f0, f1, "Reconstruct")
        except FaceLabError as e:
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        fill_scene_range(self, scene)
        prog = progress_callback(context, len(frames), "FaceLab Reconstruct")
        try:
            r = reconstruct_from_bundles(scene, face_object(context), settings, progress=prog)
        except FaceLabError as e:
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        finally:
            context.window_manager.progress_end()
        st = r.stats
        how = (f"{st['tetrahedra_kept']:,} tetrahedra ({st['memory_bytes_total'] / 2**20:.0f} MB)"
               if r.method == "INDEXING" else f"fit + residual, bundle noise {r.noise_mm:.2f} mm"
               + (" (estimated)" if scene.facelab_recon.noise < 0 else ""))
        msg = (f"Reconstructed {len(r.frames) - len(r.skipped):,} frames from {r.n_bundles} bundles and {r.n_shapes} "
               f"shapes in {r.time_s:.1f} s: {len(r.keys)} corrective keys ({RECONSTRUCT_PREFIX}*), {how}"
               + (", jaw from " + r.jaw if r.jaw is not None else "")
               + (f", smoothing {r.smooth} frames" if r.smooth > 1 else ""))
        if r.skipped:
            msg += (f"; skipped {len(r.skipped)} frames with missing bundles (shown neutral): {r.skipped[:10]} "
                    f"({r.missing})")
        if r.method != "INDEXING" and scene.facelab_recon.jaw_source != "NONE":
            msg += "; the jaw setting is used by Local Indexing only"
        if r.live_keys:
            msg += f"; note: dataset keys {r.live_keys[:5]} are not zero and add on top"
        self.report({"WARNING"} if r.skipped or r.live_keys else {"INFO"}, msg)
        return {"FINISHED"}


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
    drivers: BoolProperty(name="Drive by Components", default=True,
                          description="Drive each corrective by the product of its components' values")

    @classmethod
    def poll(cls, context):
        if not poll_face(cls, context):
            return False
        if not _dataset_keys(face_object(context)):
            cls.poll_message_set("The face has no shape keys: its dataset shapes are what the correctives are "
                                 "learnt from")
            return False
        rig = context.scene.facelab_recon.rig_object
        if rig is None:
            cls.poll_message_set("Pick the template Rig (a mesh with the rig's shape keys) in Reconstruct from "
                                 "Bundles")
            return False
        if not _dataset_keys(rig):
            cls.poll_message_set(f"The Rig '{rig.name}' has no shape keys: pick the mesh holding the template rig")
            return False
        return True

    def execute(self, context):
        scene = context.scene
        try:
            r = generate_correctives(scene, face_object(context),
                                     corrective_settings(scene, self.combinations, self.bundles, self.drivers))
        except FaceLabError as e:
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        unit = scene.unit_settings.scale_length or 1.0
        msg = (f"Added {len(r.added)} corrective keys to '{r.rig}' in {r.time_s:.1f} s "
               f"(dataset {r.n_dataset} shapes, {r.n_bundles} bundles): "
               + ", ".join(f"{n} (max {d * unit * 1e3:.2f} mm)" for n, d, _ in r.added[:6]))
        beyond = [n for n, _, p in r.added if p]
        if r.dropped:
            msg += f"; dataset shapes without rig content left out: {r.dropped[:5]}"
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

    @classmethod
    def poll(cls, context):
        clips = list(bpy.data.movieclips)
        if not clips:
            cls.poll_message_set("No Movie Clip: load the footage in the Movie Clip Editor, track it and Solve Camera "
                                 "Motion")
            return False
        if not any(_solved(c) for c in clips):
            cls.poll_message_set("No Movie Clip with a camera solve: the clips have no valid camera solve; press "
                                 "Solve Camera Motion in the Movie Clip Editor (Track tab)")
            return False
        return True

    def execute(self, context):
        clip = bpy.data.movieclips.get(self.clip) if self.clip else context.scene.active_clip
        try:
            empties = bundles_from_clip(context.scene, clip)
        except FaceLabError as e:
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        self.report({"INFO"}, f"Added {len(empties)} bundle empties in '{BUNDLES_COLLECTION}' from '{clip.name}' "
                              "(static bundles: animate them or constrain them per frame before Reconstruct)")
        return {"FINISHED"}


def _solved(clip) -> bool:
    """Whether ``clip`` has a valid camera (or object) solve with at least one bundle."""
    tr = clip.tracking
    solved = tr.reconstruction.is_valid or any(o.reconstruction.is_valid for o in tr.objects)
    return solved and any(t.has_bundle for o in tr.objects for t in o.tracks)


classes = (FACELAB_OT_reconstruct_from_bundles, FACELAB_OT_generate_correctives, FACELAB_OT_bundles_from_clip)
_register, _unregister = bpy.utils.register_classes_factory(classes)


def register():
    # the settings' property group, until ui/__init__.py registers props_reconstruct itself
    props_reconstruct.register()
    _register()


def unregister():
    _unregister()
    props_reconstruct.unregister()
