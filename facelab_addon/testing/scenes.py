"""Blender scenes for tests, benchmarks and demos: the ICT-FaceKit face as a mesh object.

:func:`build_ict_face_scene` creates the face (optionally in a factory-fresh
scene) with ICT expressions as shape keys, keyed on a frame range, and the
vertex groups and camera the FaceLab operators read. :func:`keyed_empties`
adds animated empties (motion-capture bundles) that follow given world
positions frame by frame; :func:`baked_sequence_object` adds a mesh that
plays a given vertex sequence (a truth or a result to render beside the face).

Units: ``scale`` converts ICT-FaceKit centimetres to scene units (0.01: metres,
as a Blender user imports the face). Imports ``bpy`` inside the functions, so
the module itself loads without Blender.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..names import EYEBALL_GROUPS, FIXED_GROUP

__all__ = ["FaceScene", "build_ict_face_scene", "keyed_empties", "baked_sequence_object"]


@dataclass
class FaceScene:
    """What :func:`build_ict_face_scene` made.

    Attributes
    ----------
    scene : bpy.types.Scene
    obj : bpy.types.Object
        The face mesh object.
    neutral : (V,3) float64
        Its rest vertices (``ict.neutral * scale``), scene units.
    names : list of str
        The shape keys added, in order (expressions first, then ``shapes``).
    deltas : (S,V,3) float64
        Their offsets from the rest vertices, scene units (as written, before
        Blender stores them in float32).
    fixed : (V,) bool
        The hidden vertices (everything but ICT's ``M_Face``).
    camera : bpy.types.Object or None
        The camera object, when a camera was asked for.
    """

    scene: object
    obj: object
    neutral: np.ndarray
    names: list = field(default_factory=list)
    deltas: np.ndarray = field(default_factory=lambda: np.zeros((0, 0, 3)))
    fixed: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    camera: object = None


def build_ict_face_scene(ict, expressions=(), *, shapes=None, weights=None, frames=None, frame_range=None,
                         scale: float = 0.01, name: str = "Face", fixed_group: bool = False,
                         eyeball_groups: bool = False, uv_layer: bool = False, camera=None, reset: bool = True,
                         select: bool = True) -> FaceScene:
    """The ICT-FaceKit face as a Blender mesh object with expression shape keys, optionally animated.

    Steps, in order: a factory-fresh empty scene (``reset``); the frame range;
    the mesh (ICT's polygons, vertices ``ict.neutral * scale``); a UV layer;
    a ``Basis`` key and one key per expression and per extra shape; the key
    values keyed on ``frames``; the ``FL_fixed`` and eyeball vertex groups; a
    camera; the face made active and selected.

    Parameters
    ----------
    ict : ICTModel
        The model, in its own units (``ict.scale``; centimetres by default).
    expressions : sequence of str
        ICT expressions added as shape keys of the same name, offset
        ``(ict.expressions[n] - ict.neutral) * scale``.
    shapes : dict name -> (V,3) float, optional
        Further shape keys given as positions in the model's units (for
        example generated in-betweens); offset ``(x - ict.neutral) * scale``.
    weights : (T,S) float, optional
        Key values of all added keys (``expressions`` then ``shapes``) on
        ``frames``, keyed in bulk with linear interpolation.
    frames : (T,) int, optional
        The frames of ``weights``; also the scene's frame range when
        ``frame_range`` is not given.
    frame_range : (int, int), optional
        Scene start and end frame.
    scale : float
        Scene units per model unit (0.01: centimetres to metres).
    name : str
        Name of the object and its mesh.
    fixed_group : bool
        Add the ``FL_fixed`` vertex group: the hidden vertices (all but
        ``M_Face``: mouth bag, teeth, eyes, back of the head).
    eyeball_groups : bool
        Add the ``FL_eyeball_left`` / ``FL_eyeball_right`` vertex groups (the
        ``M_ScleraLeft`` / ``M_ScleraRight`` vertices).
    uv_layer : bool
        Add ICT's UVs as the layer ``UVMap``.
    camera : core Camera, optional
        Add it as a Blender camera object (the scene camera).
    reset : bool
        Start from ``bpy.ops.wm.read_factory_settings(use_empty=True)``;
        False adds the face to the current scene.
    select : bool
        Make the face the active, selected object.

    Returns
    -------
    FaceScene
    """
    import bpy

    from ..blender.scene import new_mesh_object
    from ..blender.shapekeys import add_corrective_key, key_values_bulk

    if reset:
        bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    if frame_range is None and frames is not None and len(frames):
        frame_range = (frames[0], frames[-1])
    if frame_range is not None:
        scene.frame_start, scene.frame_end = int(frame_range[0]), int(frame_range[1])
    neutral = ict.neutral * scale
    obj = new_mesh_object(name, neutral, poly_verts=ict.poly_verts, poly_offsets=ict.poly_offsets)
    if uv_layer:
        uv = obj.data.uv_layers.new(name="UVMap")
        uv.data.foreach_set("uv", ict.uvs[ict.poly_uv].astype(np.float32).ravel())
    offsets = [(n, (ict.expressions[n] - ict.neutral) * scale) for n in expressions]
    offsets += [(n, (np.asarray(x) - ict.neutral) * scale) for n, x in (shapes or {}).items()]
    if offsets:
        obj.shape_key_add(name="Basis", from_mix=False)
    names = []
    for n, d in offsets:
        names.append(add_corrective_key(obj, n, d).name)
    if weights is not None:
        if frames is None:
            raise ValueError("weights need the frames they are keyed on")
        key_values_bulk(obj, names, frames, weights)
    fixed = ~ict.part_vertex_mask("M_Face")
    if fixed_group:
        obj.vertex_groups.new(name=FIXED_GROUP).add(np.flatnonzero(fixed).tolist(), 1.0, "REPLACE")
    if eyeball_groups:
        for side, part in (("left", "M_ScleraLeft"), ("right", "M_ScleraRight")):
            ids = np.flatnonzero(ict.part_vertex_mask(part))
            obj.vertex_groups.new(name=EYEBALL_GROUPS[side]).add(ids.tolist(), 1.0, "REPLACE")
    cam_obj = None
    if camera is not None:
        from ..blender.camera import new_camera_object

        cam_obj = new_camera_object(scene, camera)
    if select:
        bpy.context.view_layer.objects.active = obj
        obj.select_set(True)
    deltas = np.stack([d for _, d in offsets]) if offsets else np.zeros((0,) + neutral.shape)
    return FaceScene(scene=scene, obj=obj, neutral=neutral, names=names, deltas=deltas, fixed=fixed,
                     camera=cam_obj)


def keyed_empties(scene, points, *, prefix: str = "B", digits: int = 2, collection=None, first_frame: int = 0,
                  select: bool = False, display_size: float | None = None) -> list:
    """Empties that follow ``points`` frame by frame (motion-capture bundles).

    Parameters
    ----------
    scene : bpy.types.Scene
    points : (T,B,3) float
        World positions, scene units, of bundle ``b`` on frame ``first_frame + t``.
    prefix : str
        Empty ``b`` is named ``f"{prefix}{b:0{digits}d}"``.
    digits : int
    collection : str or bpy.types.Collection, optional
        Where the empties are linked: the scene's master collection (default),
        a new collection of this name linked under it, or this collection.
    first_frame : int
    select : bool
        Select the empties (the operators' "selected objects" bundle source).
    display_size : float, optional
        Draw the empties as spheres of this size (scene units).

    Returns
    -------
    list of bpy.types.Object
        The empties, in bundle order.
    """
    import bpy

    P = np.asarray(points, dtype=np.float64)
    if collection is None:
        coll = scene.collection
    elif isinstance(collection, str):
        coll = bpy.data.collections.new(collection)
        scene.collection.children.link(coll)
    else:
        coll = collection
    out = []
    for b in range(P.shape[1]):
        e = bpy.data.objects.new(f"{prefix}{b:0{digits}d}", None)
        if display_size is not None:
            e.empty_display_type, e.empty_display_size = "SPHERE", display_size
        coll.objects.link(e)
        for t in range(len(P)):
            e.location = P[t, b]
            e.keyframe_insert("location", frame=first_frame + t)
        if select:
            e.select_set(True)
        out.append(e)
    return out


def baked_sequence_object(ict, name: str, X, frames):
    """A mesh with ICT's polygons that plays the sequence ``X`` on ``frames``, one shape key per frame.

    Parameters
    ----------
    ict : ICTModel
        Gives the polygons.
    name : str
    X : (T,V,3) float
        Vertices per frame, scene units; ``X[0]`` is the rest shape.
    frames : (T,) int

    Returns
    -------
    bpy.types.Object
        Keys ``Frame00``, ``Frame01``... (value 1 on their own frame, 0 on the others).
    """
    from ..blender.scene import new_mesh_object
    from ..blender.shapekeys import add_keys_from_deltas, key_values_bulk

    ob = new_mesh_object(name, X[0], poly_verts=ict.poly_verts, poly_offsets=ict.poly_offsets)
    ob.shape_key_add(name="Basis", from_mix=False)
    keys = add_keys_from_deltas(ob, "Frame", X - X[0][None])
    key_values_bulk(ob, keys, frames, np.eye(len(frames)))
    return ob
