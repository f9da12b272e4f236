"""Properties of Reconstruct from Bundles and Generate Correctives (Cong, Lan & Fedkiw).

``Scene.facelab_recon`` (:class:`FACELAB_PG_reconstruct`): the bundle source,
bind frame, method and bundle noise, smoothing, jaw and the template rig with
its combinations.
:func:`facelab_addon.pipeline.shot_settings.reconstruct_settings` and ``corrective_settings``
gather them into the pipeline's settings (:mod:`facelab_addon.pipeline.reconstruct`).
"""

import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, PointerProperty, StringProperty

from ..names import BUNDLES_COLLECTION
from ..pipeline.reconstruct import ReconstructSettings
from ..pipeline.settings import describe

_SETTINGS = {d["name"]: d for d in describe(ReconstructSettings)}
METHODS = [tuple(c) for c in _SETTINGS["method"]["choices"]]

BUNDLE_SOURCES = [
    ("SELECTED", "Selected",
     f"Selected empties (one bundle each, animated) and point meshes; else the collection '{BUNDLES_COLLECTION}'"),
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

    bundle_source: EnumProperty(name="Bundles", items=BUNDLE_SOURCES, default="SELECTED",
                                description="Where the animated 3D bundles come from")
    bundle_collection: PointerProperty(name="Collection", type=bpy.types.Collection,
                                       description="Collection of the bundle empties (and point meshes)")
    bundle_mesh: PointerProperty(name="Point Mesh", type=bpy.types.Object, poll=_mesh_poll,
                                 description="Mesh whose animated vertices are the bundles")
    bind_frame: IntProperty(name="Bind Frame", default=-1,
                            description="Frame where the face is neutral: bundles are bound to the surface there "
                                        "(-1: the scene's first frame)")
    bind_scene_start: BoolProperty(
        name="Scene Start", get=lambda self: self.bind_frame < 0,
        set=lambda self, v: setattr(self, "bind_frame", -1 if v else self.id_data.frame_start),
        description="Bind on the scene's first frame (off: on the Bind Frame below)")
    smooth: IntProperty(name="Smoothing", default=1, min=1, max=15,
                        description="Central moving average of the per-frame weights over this many frames "
                                    "(1: off); Local Indexing then passes through the bundles' moving average")
    method: EnumProperty(name=_SETTINGS["method"]["label"], items=METHODS, default=_SETTINGS["method"]["default"],
                         description=_SETTINGS["method"]["description"])
    noise: FloatProperty(name=_SETTINGS["noise"]["label"], default=_SETTINGS["noise"]["default"],
                         min=_SETTINGS["noise"]["min"], soft_max=_SETTINGS["noise"]["soft_max"], precision=3,
                         description=_SETTINGS["noise"]["description"])
    jaw_source: EnumProperty(name="Jaw", items=JAW_SOURCES, default="NONE",
                             description="What moves the jaw (Local Indexing only); set it when the shot's jaw "
                                         "opens wider than the dataset shapes")
    jaw_armature: PointerProperty(name="Armature", type=bpy.types.Object, poll=_armature_poll,
                                  description="Armature holding the jaw bone")
    jaw_bone: StringProperty(name="Bone", default="jaw", description="Name of the jaw bone in the armature")
    jaw_object: PointerProperty(name="Jaw Object", type=bpy.types.Object,
                                description="Object (an empty, a jaw mesh) that moves with the jaw")
    jaw_group: StringProperty(name="Jaw Weights",
                              description="Vertex group of the face with the jaw's skinning weights (empty: the "
                                          "bone's name)")
    rig_object: PointerProperty(name="Rig", type=bpy.types.Object, poll=_mesh_poll,
                                description="Mesh whose shape keys are the template rig (same vertex order as the "
                                            "face); the correctives are added to it")
    combinations: StringProperty(name="Combinations", default="",
                                 description="Rig-shape combinations, e.g. 'noseSneer_L+mouthUpperUp_L, "
                                             "mouthSmile_L+jawOpen'")


classes = (FACELAB_PG_reconstruct,)
_register, _unregister = bpy.utils.register_classes_factory(classes)


def register():
    _register()
    bpy.types.Scene.facelab_recon = PointerProperty(type=FACELAB_PG_reconstruct)


def unregister():
    del bpy.types.Scene.facelab_recon
    _unregister()
