"""Auto Regions: the trusted mouth region and the inner-lip region Propagate predicts (Dinev et al. 2018 §4).

The regions are two vertex groups on the face, :data:`~facelab_addon.names.MOUTH_GROUP`
(the mouth area the regression trusts) and :data:`~facelab_addon.names.LIPS_GROUP` (the
inner lips it predicts). :func:`auto_regions` proposes them as geodesic bands around the
inner-lip contact loop (:func:`facelab_addon.core.lips.regions.auto_regions`), found with
the scene camera and the lip sketch when there are (on a whole body the eyelids, fingers and
toes touch as the lips do); :func:`region_faces` reads them back, validated, for Propagate.
Sizes are relative to the mouth (band widths) or millimetres of world space (contact gap).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ..assets import load_preset
from ..blender.camera import camera_from_blender, evaluated_depsgraph
from ..blender.mesh import (
    face_topology,
    require_mesh,
    selected_vertices,
    set_vertex_group,
    vertex_group_mask,
)
from ..blender.objects import require_editable
from ..blender.shapekeys import rest_vertices
from ..blender.strokes import find_sketch_object, read_lip_strokes, sketch_keyframes
from ..core.errors import RegionError, SketchError
from ..core.lips import regions as core_regions
from ..core.lips.lip_loop import inner_lip_loop, loop_width
from ..names import LIPS_GROUP, MOUTH_GROUP
from .settings import setting

__all__ = ["REGION_DEFAULTS", "RegionSettings", "RegionsResult", "auto_regions", "region_faces"]

#: Band widths of ``assets/presets/regions.json`` as fractions of the mouth width
#: (``core.lips.lip_loop.loop_width``): ``lip_width`` (inner-lip band half-width) and
#: ``mouth_width`` (trusted band outside it). The defaults of :class:`RegionSettings`.
REGION_DEFAULTS = load_preset("regions", {"lip_width": float, "mouth_width": float})


@dataclass
class RegionSettings:
    """How :func:`auto_regions` proposes the regions.

    Attributes
    ----------
    replace : bool
        Overwrite existing region groups (otherwise refuse).
    use_selection : bool
        Take the inner-lip loop from the selected vertices instead of finding it.
    lip_width, mouth_width : float
        Widths of the inner-lip band and of the mouth band around it, as
        fractions of the mouth width (corner to corner along the loop);
        the add-on's defaults come from ``assets/presets/regions.json``.
    contact_gap : float
        Largest distance between the upper and lower lip in the rest pose for
        them to count as touching, millimetres of the object's world space
        (the scene's unit scale and the object's scale are accounted for);
        0 (default): twice the median edge length of the mesh, so a head
        imported at any scale is searched at its own resolution.
    use_camera : bool
        Use the scene camera and the lip sketch when there are: the lips are the
        contact nearest to the sketched lines, and the loop follows the side of
        the contact facing the camera.
    """

    replace: bool = False
    use_selection: bool = False
    lip_width: float = setting(REGION_DEFAULTS["lip_width"], label="Lip Band", min=0.01, max=1.0, unit="mouth",
                               description="Half-width of the inner-lip band FL_lips, in mouth widths")
    mouth_width: float = setting(REGION_DEFAULTS["mouth_width"], label="Mouth Band", min=0.01, max=3.0,
                                 unit="mouth",
                                 description="Width of the trusted mouth band FL_mouth around the lips, in mouth widths")
    contact_gap: float = setting(0.0, label="Lip Contact Gap", min=0.0, soft_max=20.0, unit="mm",
                                 description="Largest distance between the lips in the rest pose for them to count "
                                             "as touching, in millimetres (0: twice the mesh's median edge length); "
                                             "raise it when the rest mouth is open")
    use_camera: bool = setting(True, label="Use Camera and Sketch",
                               description="Find the lips where the lip sketch is drawn and on the side facing the "
                                           "scene camera (when there are a sketch and a camera)")


@dataclass
class RegionsResult:
    """What :func:`auto_regions` wrote.

    Attributes
    ----------
    object : str
        The face object's name.
    mouth_vertices, lip_vertices : int
        Vertices in the mouth and inner-lip groups.
    groups : tuple of str
        The vertex groups written (mouth, lips).
    replaced : list of str
        Groups that existed and were overwritten.
    seconds : float
    """

    object: str
    mouth_vertices: int
    lip_vertices: int
    groups: tuple = (MOUTH_GROUP, LIPS_GROUP)
    replaced: list = field(default_factory=list)
    seconds: float = 0.0


def auto_regions(obj, settings: RegionSettings | None = None, *, scene=None, camera_obj=None,
                 sketch=None) -> RegionsResult:
    """Propose and write the mouth and inner-lip vertex groups of the face ``obj``.

    Reads the rest pose (Basis key, else the mesh) and its triangles (welded along split seams:
    :func:`~facelab_addon.blender.mesh.face_topology`; each duplicate gets its representative's
    groups), runs
    :func:`facelab_addon.core.lips.regions.auto_regions` and writes the two
    groups with weight 1. ``obj`` must be in Object Mode (the selection of an
    edited mesh is read from its mesh data). With ``settings.use_camera`` and a
    scene camera, the lips are looked for on the side of the face that faces
    the camera, and with a lip sketch, where the sketch is drawn (a whole body
    has eyelids, fingers and toes whose facing surfaces touch as the lips do).

    Parameters
    ----------
    obj : bpy.types.Object
        The face mesh.
    settings : RegionSettings, optional
    scene : bpy.types.Scene, optional
        For the camera, the sketch and the unit scale; default the first
        scene using ``obj``.
    camera_obj : bpy.types.Object, optional
        Default ``scene.camera``.
    sketch : bpy.types.Object, optional
        The Grease Pencil lip sketch; default found in the scene
        (:func:`facelab_addon.blender.strokes.find_sketch_object`).

    Returns
    -------
    RegionsResult

    Raises
    ------
    RegionError
        The groups exist and ``settings.replace`` is off, fewer than 4 vertices
        are selected with ``use_selection``, or no inner-lip loop is found.
    MeshError
        ``obj`` is not a mesh with faces.
    """
    settings = settings or RegionSettings()
    t0 = time.perf_counter()
    existing = [g for g in (MOUTH_GROUP, LIPS_GROUP) if obj.vertex_groups.get(g) is not None]
    if existing and not settings.replace:
        raise RegionError(f"{', '.join(existing)} already exist on '{obj.name}'; enable 'Replace Existing "
                          "Groups' to overwrite them, or edit them by weight painting.")
    require_mesh(obj)
    require_editable(obj, "Auto Regions")
    if scene is None and len(obj.users_scene):
        scene = obj.users_scene[0]
    topo = face_topology(obj)  # a mesh split along its UV seams is one surface
    tris = topo.tris
    V = rest_vertices(obj)
    loop = None
    if settings.use_selection:
        loop = selected_vertices(obj)
        if topo.n_duplicates:  # a selected duplicate stands for its representative
            loop = np.unique(topo.weld.representative[loop])
        if len(loop) < 4:
            raise RegionError("Select the inner-lip edge loop (at least 4 vertices) in Edit Mode first.")
    find = dict(gap_name="the Lip Contact Gap (Auto Regions settings)")
    if settings.contact_gap > 0:
        find["max_gap"] = settings.contact_gap / _mm_per_local_unit(obj, scene)
    if loop is None and settings.use_camera and scene is not None:
        find.update(_camera_hints(scene, obj, camera_obj, sketch))
    loop = inner_lip_loop(V, tris, loop, **find)
    width = loop_width(V, loop)
    mouth, lips = core_regions.auto_regions(V, tris, loop=loop, lip_width=settings.lip_width * width,
                                            mouth_width=settings.mouth_width * width)
    mouth, lips = topo.spread(mouth), topo.spread(lips)  # each duplicate in its representative's groups
    for name, mask in ((MOUTH_GROUP, mouth), (LIPS_GROUP, lips)):
        set_vertex_group(obj, name, mask)
    return RegionsResult(object=obj.name, mouth_vertices=int(mouth.sum()), lip_vertices=int(lips.sum()),
                         replaced=existing, seconds=time.perf_counter() - t0)


def _mm_per_local_unit(obj, scene) -> float:
    """Millimetres of world space per object-local unit: the scene's unit scale times the object's scale."""
    metres = (scene.unit_settings.scale_length or 1.0) if scene is not None else 1.0
    M = np.array(obj.matrix_world, dtype=np.float64)[:3, :3]
    return 1000.0 * metres * float(np.cbrt(abs(np.linalg.det(M))) or 1.0)


def _camera_hints(scene, obj, camera_obj, sketch) -> dict:
    """``inner_lip_loop`` hints in object-local space: ``toward`` the camera, ``rays`` through the lip sketch.

    Empty without a camera; without a readable sketch (none, or none on any of its keyframes) only
    ``toward``.
    """
    cam_obj = camera_obj if camera_obj is not None else scene.camera
    if cam_obj is None:
        return {}
    dg = evaluated_depsgraph(scene)
    cam = camera_from_blender(scene, cam_obj, dg)
    inv = np.linalg.inv(np.array(obj.matrix_world, dtype=np.float64))
    centre = -cam.R.T @ cam.t
    out = {"toward": inv[:3, :3] @ centre + inv[:3, 3]}
    try:
        gp = find_sketch_object(scene, sketch)
        frames = sketch_keyframes(gp) if gp is not None else []
        if frames:
            strokes = read_lip_strokes(scene, cam, frames[0], gp_obj=gp, depsgraph=dg)
            px = np.vstack([p for lip in ("upper", "lower") for p in strokes[lip]])
            o, d = cam.rays(px)
            out["rays"] = (o @ inv[:3, :3].T + inv[:3, 3], d @ inv[:3, :3].T)
    except SketchError:
        pass  # no usable sketch: the camera alone
    return out


def region_faces(obj, tris) -> tuple:
    """The mouth and inner-lip triangles of ``obj``, from its region vertex groups, validated.

    Parameters
    ----------
    obj : bpy.types.Object
    tris : (F,3) int array
        ``face_topology(obj).tris`` (or ``mesh_triangles(obj.data)``).

    Returns
    -------
    mouth_faces, lip_faces : (m,), (l,) int64 ndarray
        Indices into ``tris``.

    Raises
    ------
    RegionError
        A group is missing, or the regions are empty, overlap or leave the
        inner lips without a border (``core.lips.regions.validate_regions``).
    """
    mouth = vertex_group_mask(obj, MOUTH_GROUP)
    lips = vertex_group_mask(obj, LIPS_GROUP)
    missing = [g for g, m in ((MOUTH_GROUP, mouth), (LIPS_GROUP, lips)) if m is None]
    if missing:
        raise RegionError(
            f"'{obj.name}' has no vertex group {' or '.join(missing)}; press Auto Regions (or paint the "
            f"groups: {MOUTH_GROUP} = trusted mouth area, {LIPS_GROUP} = inner lips to predict)."
        )
    mf = core_regions.faces_in_region(tris, mouth)
    lf = core_regions.faces_in_region(tris, lips)
    core_regions.validate_regions(tris, mf, lf, len(obj.data.vertices), rest_vertices(obj))
    return mf, lf
