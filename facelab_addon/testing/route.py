"""The artist route on a face with a known truth: a Blender scene for Auto Regions, Refine, Propagate and Bake.

:func:`build_route_scene` puts a face model (the ICT-FaceKit model, or the non-ICT
:class:`~facelab_addon.testing.remeshed.RemeshedFace`) in a Z-up scene (ICT's y-up, z-forward
axes turned to Blender's z-up, -y forward), in any scene unit and object scale, optionally under a
head + jaw armature: a performance of mouth expressions keyed on every frame (the truth) plus a
keyed ``CaptureError`` key (the inner lips pulled apart: the upper lip up, the lower lip down, more as
the jaw closes: the error the artist fixes; :func:`lip_sides` tells the lips apart), a frontal camera
40 cm from the mouth, a helmet-style lower camera 35° below the mouth looking up at it, and a witness
camera 35° to the side (:data:`CAMERAS`).
:func:`sketch_truth` draws the truth's inner-lip silhouettes on a frame as the artist would (one
Grease Pencil sketch per camera), and :func:`lip_errors` measures a result against the truth.

Positions the helpers return are object-local scene units unless named ``world``; millimetre
figures use :attr:`RouteScene.mm_per_unit`. Needs ``bpy``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .weights import CYCLIC_MOUTH_CHANNELS, cyclic_mouth_weights

__all__ = ["CAMERAS", "RouteScene", "build_route_scene", "sketch_truth", "lip_errors", "lip_sides", "ERROR_KEY",
           "UNITS"]

#: The cameras, ``name: (azimuth, elevation)`` in degrees around the mouth (azimuth 0: in front of the face,
#: positive toward the face's left; elevation positive above the mouth), all 40 cm from the mouth and looking at it.
#: ``Camera`` is the main (scene) camera. ``Camera.below`` is the lower camera of a helmet rig, 35 degrees below the
#: mouth looking up at it: its image direction across the lips mixes up-down with forward-back (sin 35 = 0.57), so
#: together with the frontal view it sees the lips' depth. ``Camera.side`` is a witness 35 degrees to the side at
#: mouth height: its image vertical is still the face's up, so it sees a vertical lip gap almost as the frontal
#: camera does and adds little depth.
CAMERAS = {"Camera": (0.0, 0.0), "Camera.below": (0.0, -35.0), "Camera.side": (35.0, 0.0)}
#: The shape key holding the capture error.
ERROR_KEY = "CaptureError"
#: Named unit set-ups: (scene units per centimetre of the face, scene unit scale, object scale).
UNITS = {"m": (0.01, 1.0, 1.0), "cm": (1.0, 0.01, 1.0), "mm": (10.0, 0.001, 1.0),
         "mm-object": (10.0, 0.001, 1000.0)}

_ZUP = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])  # ICT (y up, z forward) -> Blender (z up, -y forward)


@dataclass
class RouteScene:
    """What :func:`build_route_scene` made (see the module docstring)."""

    scene: object
    obj: object
    cameras: list
    frames: np.ndarray
    neutral: np.ndarray  # (V,3) object-local rest
    deltas: np.ndarray  # (S,V,3) object-local expression offsets
    weights: np.ndarray  # (T,S)
    error: np.ndarray  # (V,3) object-local capture error at weight 1
    error_weight: np.ndarray  # (T,)
    inner_lips: np.ndarray  # (V,) bool: skin within 6 mm of the lip contact line
    face_mask: np.ndarray  # (V,) bool: free skin (the model's M_Face)
    mm_per_unit: float  # millimetres of world space per object-local unit
    armature: object = None
    loop: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))

    def truth(self, frames=None) -> np.ndarray:
        """(T,V,3) object-local truth before any modifier (the shape-key mix without the error)."""
        i = np.arange(len(self.frames)) if frames is None else np.searchsorted(self.frames, frames)
        return self.neutral[None] + np.einsum("ts,svc->tvc", self.weights[i], self.deltas)

    def evaluated_truth(self, frames):
        """(T,V,3) object-local truth after the modifiers (the armature): the object with its error key muted."""
        from ..blender import caches

        return caches.evaluate_frames(self.obj, list(frames), mute_shape_keys_prefix=("FL_", ERROR_KEY)).astype(
            np.float64)


class _Turned:
    """A face model with its positions turned to Z-up and scaled (the attributes ``build_ict_face_scene`` reads)."""

    def __init__(self, face, scale, names):
        self.neutral = face.neutral @ _ZUP.T * scale
        self.expressions = {n: face.expressions[n] @ _ZUP.T * scale for n in names}
        self.poly_verts, self.poly_offsets = face.poly_verts, face.poly_offsets
        self.part_vertex_mask = face.part_vertex_mask


def build_route_scene(face, *, units: str = "m", frames=None, armature: bool = False, pose: bool = False,
                      error_mm: float = 1.25, expressions=CYCLIC_MOUTH_CHANNELS, name: str = "Face") -> RouteScene:
    """A factory-fresh scene with ``face`` performing, a capture error on its inner lips, three cameras.

    Parameters
    ----------
    face : ICTModel or RemeshedFace
        Positions in centimetres (``scale`` 1).
    units : str
        A key of :data:`UNITS`: ``"m"``, ``"cm"``, ``"mm"`` (mesh data in that unit, the scene's unit
        scale set to match), ``"mm-object"`` (data in metres on an object scaled 1000x in a millimetre
        scene); or ``"x<factor>"`` (data in metres times ``factor``, unit scale ``1 / factor``: the
        same physical scene in other numbers).
    frames : (T,) int, optional
        Default 1..40.
    armature : bool
        Put the face under an armature with a ``head`` and a ``jaw`` bone (Armature modifier).
    pose : bool
        Pose it: head turned 20° (nodding), jaw opened 5°.
    error_mm : float
        Largest displacement of each lip by the capture error (the gap grows by twice this).
    expressions : sequence of str
        The performed expressions (``cyclic_mouth_weights`` channels).
    name : str

    Returns
    -------
    RouteScene
    """
    import bpy

    from ..blender.camera import new_camera_object
    from ..blender.shapekeys import add_corrective_key, key_values_bulk
    from ..core.capture.camera import Camera
    from ..core.lips.lip_loop import inner_lip_loop
    from .scenes import build_ict_face_scene

    per_cm, unit_scale, obj_scale = _units(units)
    frames = np.arange(1, 41) if frames is None else np.asarray(frames)
    names = list(expressions)
    turned = _Turned(face, per_cm / obj_scale, names)
    W = cyclic_mouth_weights(frames)[:, : len(names)]
    fs = build_ict_face_scene(turned, names, weights=W, frames=frames, scale=1.0, name=name, fixed_group=True)
    scene, obj = fs.scene, fs.obj
    scene.unit_settings.scale_length = unit_scale
    obj.scale = (obj_scale,) * 3
    V0 = turned.neutral
    F = np.asarray(face.faces)
    face_mask = np.asarray(face.part_vertex_mask("M_Face"))
    # the capture error: lips pulled apart along up (z), smooth, fading at the corners
    loop = inner_lip_loop(face.neutral, F)
    up = np.array([0.0, 0.0, 1.0])
    lat = V0[loop, 0]
    cl, cr = loop[np.argmin(lat)], loop[np.argmax(lat)]
    from scipy.spatial import cKDTree

    d, _ = cKDTree(V0[loop]).query(V0)
    side = lip_sides(V0, F, loop, up)
    cm = per_cm / obj_scale
    half = 0.5 * (V0[cr, 0] - V0[cl, 0])
    mid = 0.5 * (V0[cr, 0] + V0[cl, 0])
    w = np.clip(1 - (d / (0.8 * cm)) ** 2, 0, 1) ** 2 * face_mask * np.clip(1 - ((V0[:, 0] - mid) / half) ** 4, 0, 1)
    err = np.outer(side * w * error_mm * 0.1 * cm, up)
    add_corrective_key(obj, ERROR_KEY, err)
    cap_w = 1.0 - 1.5 * W[:, 0]
    key_values_bulk(obj, [ERROR_KEY], frames, cap_w[:, None])
    inner = (d < 0.6 * cm) & face_mask
    arm = _add_armature(scene, obj, V0, loop, cm, pose) if armature else None
    # cameras (all 40 cm from the mouth, looking at it; see CAMERAS): the frontal main camera, the lower camera of a
    # helmet rig (below the chin, looking up at the mouth: it sees how far the lips sit forward), and a witness camera
    # to the side
    bpy.context.view_layer.update()
    M = np.array(obj.matrix_world)
    mc = (M[:3, :3] @ V0[loop].mean(axis=0)) + M[:3, 3]
    dist = 40.0 * per_cm
    cams = []
    for cname, (azim, elev) in CAMERAS.items():
        a, e = np.radians(azim), np.radians(elev)
        eye = mc + dist * np.array([np.sin(a) * np.cos(e), -np.cos(a) * np.cos(e), np.sin(e)])
        cam = Camera.look_at(eye, mc, [0, 0, 1], 50, 36, 1920, 1080)
        cams.append(new_camera_object(scene, cam, name=cname, make_active=cname == "Camera"))
    scene.camera = cams[0]
    bpy.context.view_layer.objects.active = obj
    obj.select_set(True)
    mm = 10.0 / per_cm * obj_scale  # mm per object-local unit: data is per_cm/obj_scale units per cm
    return RouteScene(scene=scene, obj=obj, cameras=cams, frames=frames, neutral=V0, deltas=fs.deltas, weights=W,
                      error=err, error_weight=cap_w, inner_lips=inner, face_mask=face_mask, mm_per_unit=mm,
                      armature=arm, loop=loop)


def _units(units):
    """``(scene units per cm of data, unit scale, object scale)`` of a units name (see build_route_scene)."""
    if units in UNITS:
        return UNITS[units]
    if isinstance(units, str) and units.startswith("x"):
        f = float(units[1:])
        return 0.01 * f, 1.0 / f, 1.0
    raise ValueError(f"units must be one of {list(UNITS)} or 'x<factor>', not {units!r}")


def lip_sides(V, F, loop, up) -> np.ndarray:
    """(V,) +1 on the upper lip, -1 on the lower lip, 0 off the loop's mesh piece: the side of the mouth.

    The contact ``loop`` (ordered, as :func:`~facelab_addon.core.lips.lip_loop.inner_lip_loop` returns it)
    is split at its two corners (its extremes across ``up``, i.e. along the mouth's width) into two halves;
    the half with the higher mean along ``up`` is the upper lip. Every vertex takes the side of the half
    nearest to it along the mesh (edge-length Dijkstra), so a vertex of the lower lip 0.1 mm below the
    upper one is still lower lip: the two lips meet on the mesh only at the corners.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import dijkstra

    V = np.asarray(V, dtype=np.float64)
    loop = np.asarray(loop)
    up = np.asarray(up, dtype=np.float64)
    P = V[loop] - V[loop].mean(axis=0)
    P -= np.outer(P @ up, up)
    width = np.linalg.svd(P, full_matrices=False)[2][0]  # the mouth's long axis, across up
    s = P @ width
    a, b = sorted((int(np.argmin(s)), int(np.argmax(s))))
    arc1, arc2 = loop[a + 1:b], np.r_[loop[b + 1:], loop[:a]]
    if (V[arc1] @ up).mean() < (V[arc2] @ up).mean():
        arc1, arc2 = arc2, arc1
    E = np.unique(np.sort(np.r_[F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]], axis=1), axis=0)
    L = np.linalg.norm(V[E[:, 0]] - V[E[:, 1]], axis=1)
    G = coo_matrix((L, (E[:, 0], E[:, 1])), shape=(len(V), len(V))).tocsr()
    src = np.r_[arc1, arc2]
    _, _, sources = dijkstra(G, directed=False, indices=src, min_only=True, return_predecessors=True)
    side = np.zeros(len(V))
    reach = sources >= 0
    side[reach] = np.where(np.isin(sources[reach], arc1), 1.0, -1.0)
    side[loop[[a, b]]] = 0.0
    return side


def _add_armature(scene, obj, V, loop, cm, pose):
    """A head bone (neck to crown) and a jaw bone (below the ears to the chin); skin weights; optional pose."""
    import bpy

    arm_data = bpy.data.armatures.new("Rig")
    arm = bpy.data.objects.new("Rig", arm_data)
    scene.collection.objects.link(arm)
    arm.scale = obj.scale
    bpy.context.view_layer.objects.active = arm
    bpy.ops.object.mode_set(mode="EDIT")
    mc = V[loop].mean(axis=0)
    neck = mc + np.array([0.0, 8.0 * cm, -6.0 * cm])
    pivot = mc + np.array([0.0, 7.0 * cm, 1.5 * cm])
    chin = mc + np.array([0.0, -0.5 * cm, -3.0 * cm])
    head = arm_data.edit_bones.new("head")
    head.head, head.tail = neck, neck + np.array([0.0, 0.0, 10.0 * cm])
    jaw = arm_data.edit_bones.new("jaw")
    jaw.head, jaw.tail = pivot, chin
    jaw.parent = head
    bpy.ops.object.mode_set(mode="OBJECT")
    # jaw weight: below the lip line, ramping over 6 mm; the head takes the rest
    z = V[:, 2] - mc[2]
    wj = np.clip(0.5 - z / (0.6 * cm), 0.0, 1.0) * (V[:, 1] < pivot[1])
    for name, wts in (("jaw", wj), ("head", 1.0 - wj)):
        vg = obj.vertex_groups.new(name=name)
        for value in np.unique(np.round(wts, 3)):
            if value > 0:
                vg.add(np.flatnonzero(np.round(wts, 3) == value).tolist(), float(value), "REPLACE")
    mod = obj.modifiers.new("Armature", "ARMATURE")
    mod.object = arm
    if pose:
        arm.pose.bones["head"].rotation_mode = "XYZ"
        arm.pose.bones["head"].rotation_euler = (np.radians(20.0), 0.0, 0.0)
        arm.pose.bones["jaw"].rotation_mode = "XYZ"
        arm.pose.bones["jaw"].rotation_euler = (np.radians(5.0), 0.0, 0.0)
    bpy.context.view_layer.objects.active = obj
    bpy.context.view_layer.update()
    return arm


def sketch_truth(rs: RouteScene, frame: int, camera_obj=None, sketch_name: str | None = None):
    """Draw the truth's inner-lip silhouettes on ``frame`` through a camera, as the artist would.

    Returns ``(gp_obj, upper_px, lower_px)``; the sketch is a Grease Pencil object attached to the camera
    (one per camera: ``FL_LipSketch`` for the scene camera, ``FL_LipSketch.<camera>`` for another).
    """
    from ..blender.camera import camera_from_blender
    from ..blender.strokes import new_lip_sketch, write_stroke_pixels

    scene = rs.scene
    cam_obj = camera_obj or scene.camera
    scene.frame_set(int(frame))
    T = rs.evaluated_truth([frame])[0]
    M = np.array(rs.obj.matrix_world)
    Tw = T @ M[:3, :3].T + M[:3, 3]
    cam = camera_from_blender(scene, cam_obj)
    up_px, lo_px = truth_contours(rs, Tw, cam)
    name = sketch_name or ("FL_LipSketch" if cam_obj == scene.camera else f"FL_LipSketch.{cam_obj.name}")
    gp = new_lip_sketch(scene, cam_obj, name=name)
    write_stroke_pixels(gp, "Upper lip", int(frame), [up_px], cam)
    write_stroke_pixels(gp, "Lower lip", int(frame), [lo_px], cam)
    return gp, up_px, lo_px


def truth_contours(rs: RouteScene, Vw, cam):
    """Upper and lower inner-lip silhouette pixels of world positions ``Vw`` (left to right)."""
    from ..core.geometry.silhouette import lip_side, silhouette_edges

    F = _tris(rs.obj)
    E = silhouette_edges(Vw, F, cam)
    E = E[rs.inner_lips[E].all(1)]
    side = lip_side(Vw, F, cam, E.ravel()).reshape(-1, 2)
    up, lo = np.unique(E[(side == 1).all(1)]), np.unique(E[(side == -1).all(1)])
    px = cam.project(Vw)
    return px[up[np.argsort(px[up, 0])]], px[lo[np.argsort(px[lo, 0])]]


def _tris(obj):
    from ..blender.mesh import mesh_triangles

    return mesh_triangles(obj.data)


def lip_errors(rs: RouteScene, X, frames) -> np.ndarray:
    """(T,) inner-lip RMS error in millimetres of object-local frames ``X`` (T,V,3) against the evaluated truth."""
    T = rs.evaluated_truth(frames)
    d = np.linalg.norm(np.asarray(X, dtype=np.float64) - T, axis=2)[:, rs.inner_lips]
    return np.sqrt(np.mean(d * d, axis=1)) * rs.mm_per_unit

