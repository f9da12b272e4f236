"""Properties of the contour-based solve and retargeting (Bhat et al. 2013).

``Scene.facelab_solve`` (:class:`FACELAB_PG_solve_scene`): the views (camera
object + Movie Clip + optional Mask / Grease Pencil contour sources), the
bundle source, solve options and the retarget target.

``Object.facelab_solve`` (:class:`FACELAB_PG_solve_object`): the bindings of
the face mesh: one item per track (or bundle) name with the triangle vertex
ids and barycentric weights of its surface point, written by Bind Tracks.
"""

import bpy
import numpy as np
from bpy.props import (
    BoolProperty,
    CollectionProperty,
    EnumProperty,
    FloatProperty,
    FloatVectorProperty,
    IntProperty,
    IntVectorProperty,
    PointerProperty,
    StringProperty,
)


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
                       default="MARKER")
    vertices: IntVectorProperty(name="Vertices", size=3, default=(-1, -1, -1))
    bary: FloatVectorProperty(name="Barycentric", size=3, default=(0.0, 0.0, 0.0))


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
    bundles: EnumProperty(
        name="Bundles",
        items=[("NONE", "None", "No 3D bundles"),
               ("EMPTIES", "Empties", "The empties (or point meshes) of the Bundle Collection"),
               ("TRACKING", "Tracking", "The reconstructed bundles of the first view's Movie Clip (its camera solve)")],
        default="NONE",
        description="3D bundles to fit (Bhat Eq. 2) besides the 2D markers",
    )
    bundle_collection: PointerProperty(name="Bundle Collection", type=bpy.types.Collection,
                                       description="Collection of bundle empties (default: 'FL_bundles')")
    use_contours: BoolProperty(name="Contours", default=True,
                               description="Fit the inner-lip and eyelid contours of the views' masks / sketches")
    annotation_view: IntProperty(name="Annotation View", default=-1, min=-1,
                                 description="View whose camera the scene annotation's contour layers were drawn "
                                             "through (-1: ignore the annotation)")
    use_corrective: BoolProperty(name="Corrective", default=True,
                                 description="Add the per-frame out-of-subspace corrective (compressed corrective "
                                             "shape keys FL_Solve_*)")
    sliding: BoolProperty(name="Sliding Contours", default=True,
                          description="Re-match contour correspondences every frame (off: keep the first frame's)")
    frame_start: IntProperty(name="Start", default=-1, description="First frame (-1: the scene's start)")
    frame_end: IntProperty(name="End", default=-1, description="Last frame (-1: the scene's end)")
    weight_min: FloatProperty(name="Min Weight", default=-1.0, soft_min=-1.0, soft_max=0.0)
    weight_max: FloatProperty(name="Max Weight", default=1.0, soft_min=0.0, soft_max=1.0)
    marker_weight: FloatProperty(name="Marker Weight", default=1.0, min=0.0)
    contour_weight: FloatProperty(name="Contour Weight", default=1.0, min=0.0)
    existing_animation: EnumProperty(
        name="Existing Animation",
        items=[("NEW_ACTION", "New Action", "Keep the artist's shape-key action (fake user) and write the solve to a "
                                            "copy of it named FL_Solve (switch back in the Shape Key Editor)"),
               ("REPLACE", "Replace Curves", "Overwrite the rig keys' curves in the current action")],
        default="NEW_ACTION",
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
        default="AUTO",
    )
    creature_markers: PointerProperty(name="Creature Markers", type=bpy.types.Collection,
                                      description="Empties on the creature named like the actor's tracks")
    lip_sync: BoolProperty(name="Lip Sync", default=True,
                           description="Seal the creature's lip corners so its talking portion matches the actor's "
                                       "lip length (Bhat §5.1)")
    lip_threshold: FloatProperty(name="Threshold", default=0.0, min=0.0, subtype="DISTANCE",
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


# --------------------------------------------------------------------------- binding storage
def write_bindings(obj, kind: str, names, vertices, bary) -> None:
    """Replace the ``kind`` bindings of ``obj`` by ``names`` with (m,3) vertex ids and barycentrics (bulk)."""
    coll = obj.facelab_solve.bindings
    keep = [(b.name, b.kind, tuple(b.vertices), tuple(b.bary)) for b in coll if b.kind != kind]
    coll.clear()
    rows = keep + [(n, kind, tuple(int(x) for x in v), tuple(float(x) for x in w))
                   for n, v, w in zip(names, np.asarray(vertices), np.asarray(bary))]
    for _ in rows:
        coll.add()
    coll.foreach_set("vertices", np.array([r[2] for r in rows], np.int32).ravel() if rows else np.zeros(0, np.int32))
    coll.foreach_set("bary", np.array([r[3] for r in rows], np.float32).ravel() if rows else np.zeros(0, np.float32))
    for item, r in zip(coll, rows):
        item.name, item.kind = r[0], r[1]


def read_bindings(obj, kind: str):
    """``(names, vertices (m,3) int64, bary (m,3) float64)`` of the ``kind`` bindings of ``obj``."""
    coll = obj.facelab_solve.bindings
    n = len(coll)
    v = np.empty(3 * n, np.int32)
    b = np.empty(3 * n, np.float32)
    coll.foreach_get("vertices", v)
    coll.foreach_get("bary", b)
    sel = [i for i, it in enumerate(coll) if it.kind == kind]
    names = [coll[i].name for i in sel]
    V = v.reshape(n, 3)[sel].astype(np.int64)
    B = b.reshape(n, 3)[sel].astype(np.float64)
    B /= np.where(B.sum(1, keepdims=True) > 0, B.sum(1, keepdims=True), 1.0)  # float32 storage: re-normalise
    return names, V, B
