"""Properties of the contour-based solve and retargeting (Bhat et al. 2013).

``Scene.facelab_solve`` (:class:`FACELAB_PG_solve_scene`): the views (camera
object + Movie Clip + optional Mask / Grease Pencil contour sources), the
bundle source, solve options and the retarget target.

``Object.facelab_solve`` (:class:`FACELAB_PG_solve_object`): the bindings of
the face mesh: one item per track (or bundle) name with the triangle vertex
ids and barycentric weights of its surface point, written by Bind Tracks
(read and written as arrays by :mod:`facelab_addon.blender.bindings`).

:func:`facelab_addon.pipeline.shot_settings.bind_settings`, ``solve_settings`` and
``retarget_settings`` gather these properties into the pipelines' settings. The solve and
retarget options take their defaults (and, for the settings the pipeline declares with
:func:`facelab_addon.pipeline.settings.setting`, their labels, bounds and tooltips) from
:class:`~facelab_addon.pipeline.solve.SolveSettings` and
:class:`~facelab_addon.pipeline.retarget.RetargetSettings`, whose defaults are the core's: one place to
change a default.
"""

from dataclasses import fields

import bpy
from bpy.props import (
    BoolProperty,
    CollectionProperty,
    EnumProperty,
    FloatProperty,
    FloatVectorProperty,
    IntProperty,
    IntVectorProperty,
    PointerProperty,
)

from ..names import BUNDLES_COLLECTION, SOLVE_ACTION, SOLVE_PREFIX
from ..pipeline.retarget import RetargetSettings
from ..pipeline.settings import describe
from ..pipeline.solve import SolveSettings

_SOLVE = {f.name: f.default for f in fields(SolveSettings)}  # the pipeline's (the core's) defaults
_RETARGET = {f.name: f.default for f in fields(RetargetSettings)}
_DECLARED = {d["name"]: d for d in describe(SolveSettings)}


def _declared(prop, name: str):
    """``prop`` (a ``bpy.props`` function) for the setting ``name`` of SolveSettings: its label, default,
    bounds and tooltip."""
    d = _DECLARED[name]
    bounds = {k: d[k] for k in ("min", "max", "soft_min", "soft_max") if d[k] is not None}
    return prop(name=d["label"], default=d["default"], description=d["description"], **bounds)


def _is_camera(self, obj):
    return obj.type == "CAMERA"


def _is_mesh(self, obj):
    return obj.type == "MESH"


def _is_gp(self, obj):
    return obj.type == "GREASEPENCIL"


class FACELAB_PG_solve_view(bpy.types.PropertyGroup):
    """One tracking camera: the camera object and the footage it filmed."""

    camera: PointerProperty(name="Camera", type=bpy.types.Object, poll=_is_camera,
                            description="Camera object: its pose is the camera's pose in the scene")
    clip: PointerProperty(name="Movie Clip", type=bpy.types.MovieClip,
                          description="The footage of this camera: its tracks are the 2D markers and its camera "
                                      "calibration (Track tab > Camera) gives the lens")
    mask: PointerProperty(name="Mask", type=bpy.types.Mask,
                          description="Optional: a Mask drawn over this clip with layers named after contours "
                                      "('Upper lip', 'Lower lip', 'Eyelid L upper'...)")
    sketch: PointerProperty(name="Sketch", type=bpy.types.Object, poll=_is_gp,
                            description="Optional: a Grease Pencil object drawn in this camera's view with contour "
                                        "layers ('Upper lip', 'Eyelid R lower'...)")


class FACELAB_PG_binding(bpy.types.PropertyGroup):
    """A track (or bundle) tied to the face surface: ``x = sum bary_k * V[vertices_k]``."""

    # ``name`` (built in) is the track / bundle name
    kind: EnumProperty(name="Kind", items=[("MARKER", "Marker", "2D track"), ("BUNDLE", "Bundle", "3D bundle")],
                       default="MARKER", description="Whether a 2D track or a 3D bundle is tied to the face")
    vertices: IntVectorProperty(name="Vertices", size=3, default=(-1, -1, -1),
                                description="The face triangle the track is tied to (its three vertex indices)")
    bary: FloatVectorProperty(name="Barycentric", size=3, default=(0.0, 0.0, 0.0),
                              description="Where on that triangle the track sits (weights of its three corners)")


class FACELAB_PG_solve_object(bpy.types.PropertyGroup):
    bindings: CollectionProperty(type=FACELAB_PG_binding)
    active_binding_index: IntProperty(default=0)
    bind_frame: IntProperty(name="Bound On", default=0, description="Frame the bindings were made on")


class FACELAB_PG_solve_scene(bpy.types.PropertyGroup):
    views: CollectionProperty(type=FACELAB_PG_solve_view)
    active_view_index: IntProperty(default=0)
    bind_frame: IntProperty(name="Bind Frame", default=-1,
                            description="Reference frame for binding tracks to the surface (-1: the current frame); "
                                        "the face mesh should match the footage there (e.g. the neutral pose)")
    bind_current: BoolProperty(
        name="Current Frame", get=lambda self: self.bind_frame < 0,
        set=lambda self, v: setattr(self, "bind_frame", -1 if v else self.id_data.frame_current),
        description="Bind on the frame shown when Bind Tracks runs (off: on the Bind Frame below)")
    bundles: EnumProperty(
        name="Bundles",
        items=[("NONE", "None", "No 3D bundles"),
               ("EMPTIES", "Empties", "The empties (or point meshes) of the Bundle Collection"),
               ("TRACKING", "Tracking", "The reconstructed bundles of the first view's Movie Clip (its camera solve)")],
        default=_SOLVE["bundles"],
        description="3D bundles to fit besides the 2D markers",
    )
    bundle_collection: PointerProperty(name="Bundle Collection", type=bpy.types.Collection,
                                       description=f"Collection of bundle empties (default: '{BUNDLES_COLLECTION}')")
    use_contours: BoolProperty(name="Contours", default=_SOLVE["use_contours"],
                               description="Fit the inner-lip and eyelid contours of the views' masks / sketches")
    annotation_view: IntProperty(name="Annotation View", default=_SOLVE["annotation_view"], min=-1,
                                 description="View whose camera the scene annotation's contour layers were drawn "
                                             "through (-1: ignore the annotation)")
    use_annotation: BoolProperty(
        name="Annotation Contours", get=lambda self: self.annotation_view >= 0,
        set=lambda self, v: setattr(self, "annotation_view", max(0, self.annotation_view) if v else -1),
        description="Also fit the contour layers of the scene's annotation, drawn through the camera of the "
                    "Annotation View")
    use_corrective: BoolProperty(name="Corrective", default=_SOLVE["use_corrective"],
                                 description="Add the per-frame out-of-subspace corrective (compressed corrective "
                                             f"shape keys {SOLVE_PREFIX}*)")
    sliding: BoolProperty(name="Sliding Contours", default=_SOLVE["sliding"],
                          description="Re-match contour correspondences every frame (off: keep the first frame's)")
    use_scene_range: BoolProperty(name="Scene Range", default=True,
                                  description="Work on the scene's frame range (off: the Start / End below)")
    frame_start: IntProperty(name="Start", get=lambda self: _range_get(self, 0),
                             set=lambda self, v: _range_set(self, 0, v),
                             description="First frame (the scene's start while Scene Range is on; negative frames "
                                         "are allowed)")
    frame_end: IntProperty(name="End", get=lambda self: _range_get(self, 1),
                           set=lambda self, v: _range_set(self, 1, v),
                           description="Last frame (the scene's end while Scene Range is on)")
    weight_min: FloatProperty(name="Min Weight", default=_SOLVE["weight_min"], soft_min=-1.0, soft_max=0.0,
                              description="Lowest weight a shape key may get (-1 allows subtracting shapes); raise "
                                          "it to 0 when the solve uses shapes backwards")
    weight_max: FloatProperty(name="Max Weight", default=_SOLVE["weight_max"], soft_min=0.0, soft_max=1.0,
                              description="Highest weight a shape key may get; lower it when expressions overshoot "
                                          "the rig's sculpted shapes")
    marker_weight: FloatProperty(name="Marker Weight", default=_SOLVE["marker_weight"], min=0.0,
                                 description="How much the solve trusts the tracked markers; lower it when noisy "
                                             "tracks make the face jitter")
    contour_weight: FloatProperty(name="Contour Weight", default=_SOLVE["contour_weight"], min=0.0,
                                  description="How much the solve trusts the lip and eyelid contours against the "
                                              "markers; raise it when lips or lids miss their contours")
    anchor_weight: _declared(FloatProperty, "anchor_weight")
    contour_damping: _declared(FloatProperty, "contour_damping")
    lip_passes: _declared(IntProperty, "lip_passes")
    lip_line_weight: _declared(FloatProperty, "lip_line_weight")
    lip_damping: _declared(FloatProperty, "lip_damping")
    existing_animation: EnumProperty(
        name="Existing Animation",
        items=[("NEW_ACTION", "New Action", "Keep the artist's shape-key action (fake user) and write the solve to a "
                                            f"copy of it named {SOLVE_ACTION} (switch back in the Shape Key Editor)"),
               ("REPLACE", "Replace Curves", "Overwrite the rig keys' curves in the current action")],
        default=_SOLVE["existing_animation"],
        description="What to do when the rig's shape keys are already animated by an action FaceLab did not make",
    )
    # retarget
    creature: PointerProperty(name="Creature", type=bpy.types.Object, poll=_is_mesh,
                              description="The mesh to carry the performance to")
    correspondence: EnumProperty(
        name="Correspondence",
        items=[("AUTO", "Auto", "Same topology if the vertex counts and triangles match, else markers"),
               ("TOPOLOGY", "Same Topology", "Vertex i of the actor is vertex i of the creature"),
               ("MARKERS", "Markers", "Empties in the Creature Markers collection named like the actor's bound "
                                      "tracks mark the same points on the creature")],
        default=_RETARGET["correspondence"],
        description="How the creature's points are matched to the actor's",
    )
    creature_markers: PointerProperty(name="Creature Markers", type=bpy.types.Collection,
                                      description="Empties on the creature named like the actor's tracks")
    lip_sync: BoolProperty(name="Lip Sync", default=_RETARGET["lip_sync"],
                           description="Seal the creature's lip corners so its talking portion matches the actor's "
                                       "lip length")
    lip_threshold: FloatProperty(name="Threshold", default=_RETARGET["lip_threshold"], min=0.0, subtype="DISTANCE",
                                 description="Extra talking length allowed before the corners are sealed")
    use_end_points: BoolProperty(name="Custom End Points", default=False,
                                 description="Set the talking portion by hand instead of automatically")
    end_points_upper: FloatVectorProperty(name="Upper", size=2, default=(0.1, 0.9), min=0.0, max=1.0,
                                          description="Left and right end of the upper lip's talking portion "
                                                      "(fraction of its length from the left corner)")
    end_points_lower: FloatVectorProperty(name="Lower", size=2, default=(0.1, 0.9), min=0.0, max=1.0,
                                          description="Left and right end of the lower lip's talking portion")


classes = (FACELAB_PG_solve_view, FACELAB_PG_binding, FACELAB_PG_solve_object, FACELAB_PG_solve_scene)


def register():
    for c in classes:
        bpy.utils.register_class(c)
    bpy.types.Scene.facelab_solve = PointerProperty(type=FACELAB_PG_solve_scene)
    bpy.types.Object.facelab_solve = PointerProperty(type=FACELAB_PG_solve_object)


def unregister():
    del bpy.types.Object.facelab_solve
    del bpy.types.Scene.facelab_solve
    for c in reversed(classes):
        bpy.utils.unregister_class(c)


# --------------------------------------------------------------------------- Start / End of the range
def _range_get(s, end: int) -> int:
    """Start (``end`` 0) or End (1) of FaceLab > Solve: the scene's while Scene Range is on."""
    scene = s.id_data
    own = ("_frame_start", "_frame_end")[end]
    if s.use_scene_range or own not in s:
        return scene.frame_end if end else scene.frame_start
    return int(s[own])


def _range_set(s, end: int, value: int) -> None:
    """Setting Start or End turns Scene Range off (so a script's or the CLI's range is honoured)."""
    if s.use_scene_range:  # the other end starts from the scene's
        s[("_frame_start", "_frame_end")[1 - end]] = _range_get(s, 1 - end)
    s[("_frame_start", "_frame_end")[end]] = int(value)
    s.use_scene_range = False
