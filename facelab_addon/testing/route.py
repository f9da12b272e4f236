"""The artist route on a face with a known truth: a Blender scene for Auto Regions, Refine, Propagate and Bake.

:func:`build_route_scene` puts a face model (the ICT-FaceKit model, or the non-ICT
:class:`~facelab_addon.testing.remeshed.RemeshedFace`) in a Z-up scene (ICT's y-up, z-forward
axes turned to Blender's z-up, -y forward), in any scene unit and object scale, optionally under a
head + jaw armature: a performance of mouth expressions keyed on every frame (the truth) plus a
keyed ``CaptureError`` key (by default the inner lips pulled apart: the upper lip up, the lower lip down,
more as the jaw closes: the error the artist fixes; placed around the truth's lip contact line,
:func:`facelab_addon.testing.lip_truth.truth_line`, found from the model's own ``jawOpen`` and never by the
Auto Regions detector the benchmark grades, which also gives the measured vertices, the rig and the cameras' aim; :func:`lip_sides` tells the lips apart; other
physically plausible capture errors in :data:`ERRORS`, :func:`capture_error`), a frontal camera
40 cm from the mouth, a helmet-style lower camera 35° below the mouth looking up at it, and a witness
camera 35° to the side (:data:`CAMERAS`).
:func:`sketch_truth` draws the truth's inner-lip silhouettes on a frame as the artist would (one
Grease Pencil sketch per camera; optionally with a hand's smooth jitter, :func:`jitter_stroke`), and :func:`lip_errors` measures a result against the truth.

Positions the helpers return are object-local scene units unless named ``world``; millimetre
figures use :attr:`RouteScene.mm_per_unit`. Needs ``bpy``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .weights import CYCLIC_MOUTH_CHANNELS, cyclic_mouth_weights

__all__ = ["CAMERAS", "ERRORS", "RouteScene", "build_route_scene", "capture_error", "sketch_truth", "jitter_stroke",
           "lip_errors", "lip_sides", "ERROR_KEY", "UNITS"]

#: The cameras, ``name: (azimuth, elevation)`` in degrees around the mouth (azimuth 0: in front of the face,
#: positive toward the face's left; elevation positive above the mouth), all 40 cm from the mouth and looking at it.
#: ``Camera`` is the main (scene) camera. ``Camera.below`` is the lower camera of a helmet rig, 35 degrees below the
#: mouth looking up at it: its image direction across the lips mixes up-down with forward-back (sin 35 = 0.57), so
#: together with the frontal view it sees the lips' depth. ``Camera.side`` is a witness 35 degrees to the side at
#: mouth height: its image vertical is still the face's up, so it sees a vertical lip gap almost as the frontal
#: camera does and adds little depth.
CAMERAS = {"Camera": (0.0, 0.0), "Camera.below": (0.0, -35.0), "Camera.side": (35.0, 0.0)}
#: The capture error models of :func:`capture_error`, ``name: what it is``. Sizes are millimetres of the face
#: (any scene unit); each is smooth (C1), zero on the mouth's interior and the corner vertices, and scaled so its
#: largest displacement is ``error_mm``.
ERRORS = {
    "wide": "the inner lips pulled apart along the face's up axis (upper lip up, lower lip down), weight "
            "(1 - (d / 8 mm)^2)^2 of the distance d to the lip contact loop, fading toward the corners: a "
            "performance-capture solve that does not close the lips",
    "narrow": "as wide, but concentrated at the lip contact: weight (1 - (d / 3 mm)^2)^2, zero beyond 3 mm of the "
              "contact loop: what multi-view stereo gets wrong where the lips touch",
    "corners": "lost corner fleshiness: the skin within 8 mm of each mouth corner pulled in toward the middle of "
               "the mouth, along its width (weight (1 - (c / 8 mm)^2)^2 of the distance c to the corner), zero at "
               "the middle of the mouth",
    "roll": "the lips' red part rolled in: within 6 mm of the contact loop (weight as wide, radius 6 mm) the lip "
            "moves back into the mouth along the face's forward axis and 30 degrees toward its own side (upper "
            "lip up, lower lip down): an error mostly in depth, which a frontal view hardly sees",
}
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
    error_model: str = "wide"  # a key of ERRORS

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
                      error_mm: float = 1.25, error: str = "wide", expressions=CYCLIC_MOUTH_CHANNELS,
                      name: str = "Face", lens_mm: float = 50.0, camera_cm: float = 40.0, camera_yaw: float = 0.0,
                      camera_roll: float = 0.0, obj_import: bool = False,
                      import_scale: float = 1.0) -> RouteScene:
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
    error : str
        The capture error's model, a key of :data:`ERRORS` (default ``"wide"``: the inner lips pulled apart
        along the face's up axis); see :func:`capture_error`.
    expressions : sequence of str
        The performed expressions (``cyclic_mouth_weights`` channels).
    name : str
    lens_mm : float
        Focal length of every camera (36 mm sensor width).
    camera_cm : float
        Every camera's distance from the mouth, centimetres of the face.
    camera_yaw : float
        Degrees added to every camera's azimuth of :data:`CAMERAS` (turned around the face's up axis).
    camera_roll : float
        Degrees every camera is rolled about its viewing axis.
    obj_import : bool
        Make the mesh as an artist imports a head: ``face`` written to an OBJ as it is (Y up, centimetres) and read
        back with ``bpy.ops.wm.obj_import`` and Blender's default axis settings into a metre scene (``units`` must
        be ``"m"``); the object keeps the transform the importer gives it (rotated 90° about X, data in the
        OBJ's numbers: a centimetre head read as metres is 100 times too big), and the shape keys, the capture
        error, the armature and the cameras follow that transform (the truth is the same face). Default off.
    import_scale : float
        The importer's ``global_scale`` (``obj_import`` only; 0.01 is the artist's fix for a centimetre OBJ).

    Returns
    -------
    RouteScene
    """
    import bpy

    from ..blender.camera import new_camera_object
    from ..blender.shapekeys import add_corrective_key, key_values_bulk
    from ..core.capture.camera import Camera
    from .lip_truth import truth_line
    from .scenes import build_ict_face_scene

    per_cm, unit_scale, obj_scale = _units(units)
    frames = np.arange(1, 41) if frames is None else np.asarray(frames)
    names = list(expressions)
    W = cyclic_mouth_weights(frames)[:, : len(names)]
    F = np.asarray(face.faces)
    face_mask = np.asarray(face.part_vertex_mask("M_Face"))
    loop = truth_line(face).loop  # the truth's own contact line, not Auto Regions' detector (testing.lip_truth)
    if obj_import:
        if units != "m":
            raise ValueError("obj_import reads the OBJ into a metre scene: units must be 'm'")
        scene, obj, deltas, A = _imported_face_scene(face, names, W, frames, name, import_scale)
        V0 = face.neutral @ A.T  # object-local (the OBJ's axes)
        M3 = np.array(obj.matrix_world)[:3, :3]
        per_cm = float(np.cbrt(abs(np.linalg.det(M3 @ A))))  # world units per cm of the face
        obj_scale = float(np.cbrt(abs(np.linalg.det(M3))))
        Vz = V0 @ M3.T  # world axes (Z up), world units
        err_w, d = capture_error(Vz, F, loop, face_mask, per_cm, error_mm, error)
        err = err_w @ np.linalg.inv(M3).T
        d = d / per_cm * float(np.cbrt(abs(np.linalg.det(A))))  # object-local units
        cm = float(np.cbrt(abs(np.linalg.det(A))))  # object-local units per cm
    else:
        turned = _Turned(face, per_cm / obj_scale, names)
        fs = build_ict_face_scene(turned, names, weights=W, frames=frames, scale=1.0, name=name, fixed_group=True)
        scene, obj, deltas = fs.scene, fs.obj, fs.deltas
        scene.unit_settings.scale_length = unit_scale
        obj.scale = (obj_scale,) * 3
        V0 = turned.neutral
        cm = per_cm / obj_scale
        err, d = capture_error(V0, F, loop, face_mask, cm, error_mm, error)
    add_corrective_key(obj, ERROR_KEY, err)
    cap_w = 1.0 - 1.5 * W[:, 0]
    key_values_bulk(obj, [ERROR_KEY], frames, cap_w[:, None])
    inner = (d < 0.6 * cm) & face_mask
    if not armature:
        arm = None
    elif obj_import:  # the rig in world axes (Z up), unscaled, at the object's location
        bpy.context.view_layer.update()
        arm = _add_armature(scene, obj, Vz, loop, per_cm, pose, matrix=np.array(obj.matrix_world))
    else:
        arm = _add_armature(scene, obj, V0, loop, cm, pose)
    # cameras (all 40 cm from the mouth, looking at it; see CAMERAS): the frontal main camera, the lower camera of a
    # helmet rig (below the chin, looking up at the mouth: it sees how far the lips sit forward), and a witness camera
    # to the side
    bpy.context.view_layer.update()
    M = np.array(obj.matrix_world)
    mc = (M[:3, :3] @ V0[loop].mean(axis=0)) + M[:3, 3]
    dist = camera_cm * per_cm
    cams = []
    for cname, (azim, elev) in CAMERAS.items():
        a, e = np.radians(azim + camera_yaw), np.radians(elev)
        eye = mc + dist * np.array([np.sin(a) * np.cos(e), -np.cos(a) * np.cos(e), np.sin(e)])
        up = np.array([0.0, 0.0, 1.0])
        if camera_roll:  # the up vector turned about the viewing axis
            z = (mc - eye) / np.linalg.norm(mc - eye)
            u = up - (up @ z) * z
            u /= np.linalg.norm(u)
            r = np.radians(camera_roll)
            up = np.cos(r) * u + np.sin(r) * np.cross(z, u)
        cam = Camera.look_at(eye, mc, up, lens_mm, 36, 1920, 1080)
        cams.append(new_camera_object(scene, cam, name=cname, make_active=cname == "Camera"))
    scene.camera = cams[0]
    bpy.context.view_layer.objects.active = obj
    obj.select_set(True)
    mm = 10.0 / per_cm * obj_scale  # mm per object-local unit: data is per_cm/obj_scale units per cm
    if obj_import:  # world millimetres (a metre scene) per object-local unit
        mm = 1000.0 * obj_scale
    return RouteScene(scene=scene, obj=obj, cameras=cams, frames=frames, neutral=V0, deltas=deltas, weights=W,
                      error=err, error_weight=cap_w, inner_lips=inner, face_mask=face_mask, mm_per_unit=mm,
                      armature=arm, loop=loop, error_model=error)


def capture_error(V, F, loop, face_mask, cm: float, error_mm: float, kind: str = "wide"):
    """The capture error of a :data:`ERRORS` model on a Z-up face (x across the face toward its left, -y forward).

    Parameters
    ----------
    V : (V,3) float
        Rest positions, Z-up (object-local units).
    F : (F,3) int
    loop : (L,) int
        The inner-lip contact loop (ordered).
    face_mask : (V,) bool
        The skin that may carry the error (the model's ``M_Face``).
    cm : float
        Object-local units per centimetre.
    error_mm : float
        The largest displacement, millimetres.
    kind : str
        A key of :data:`ERRORS`.

    Returns
    -------
    err : (V,3) float
        The error at key weight 1, object-local units.
    d : (V,) float
        Each vertex's distance to the contact loop's vertices, object-local units.
    """
    from scipy.spatial import cKDTree

    if kind not in ERRORS:
        raise ValueError(f"error must be one of {list(ERRORS)}, not {kind!r}")
    up, back = np.array([0.0, 0.0, 1.0]), np.array([0.0, 1.0, 0.0])
    lat = V[loop, 0]
    cl, cr = loop[np.argmin(lat)], loop[np.argmax(lat)]
    d, _ = cKDTree(V[loop]).query(V)
    side = lip_sides(V, F, loop, up)
    half = 0.5 * (V[cr, 0] - V[cl, 0])
    mid = 0.5 * (V[cr, 0] + V[cl, 0])
    along = np.clip(1 - ((V[:, 0] - mid) / half) ** 4, 0, 1)  # fading toward the corners
    size = error_mm * 0.1 * cm
    if kind == "wide":
        w = np.clip(1 - (d / (0.8 * cm)) ** 2, 0, 1) ** 2 * face_mask * along
        return np.outer(side * w * error_mm * 0.1 * cm, up), d  # as it always was (bit for bit)
    if kind == "narrow":
        w = np.clip(1 - (d / (0.3 * cm)) ** 2, 0, 1) ** 2 * face_mask * along
        return np.outer(side * w * size, up), d
    if kind == "corners":
        c = np.minimum(np.linalg.norm(V - V[cl], axis=1), np.linalg.norm(V - V[cr], axis=1))
        w = np.clip(1 - (c / (0.8 * cm)) ** 2, 0, 1) ** 2 * face_mask
        inward = -np.sign(V[:, 0] - mid)
        return np.outer(inward * w * size, [1.0, 0.0, 0.0]), d
    # roll
    w = np.clip(1 - (d / (0.6 * cm)) ** 2, 0, 1) ** 2 * face_mask * along * np.abs(side)
    a = np.radians(30.0)
    return (w * size)[:, None] * (np.cos(a) * back + np.sin(a) * side[:, None] * up), d


def _imported_face_scene(face, names, W, frames, name, import_scale):
    """A factory-fresh metre scene holding ``face`` as Blender's OBJ importer (default axes) reads it.

    Returns ``(scene, obj, deltas, A)``: ``A`` (3,3) maps the face's coordinates to the object's local ones
    (``local = A @ x``), measured on the neutral; ``deltas`` (S,V,3) the expression offsets, object-local; the keys, keyed with ``W`` on ``frames``, and the
    ``FL_fixed`` group (all but ``M_Face``) as :func:`~facelab_addon.testing.scenes.build_ict_face_scene` adds.
    """
    import os
    import tempfile

    import bpy

    from ..blender.shapekeys import add_corrective_key, key_values_bulk
    from ..names import FIXED_GROUP

    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = int(frames[0]), int(frames[-1])
    V = np.asarray(face.neutral, dtype=np.float64)
    path = os.path.join(tempfile.mkdtemp(prefix="facelab-obj-"), f"{name}.obj")
    with open(path, "w") as fh:
        fh.write(f"o {name}\n")
        fh.write("".join(f"v {x:.6f} {y:.6f} {z:.6f}\n" for x, y, z in V))
        off = np.asarray(face.poly_offsets)
        pv = np.asarray(face.poly_verts) + 1
        fh.write("".join("f " + " ".join(map(str, pv[off[p]:off[p + 1]])) + "\n" for p in range(len(off) - 1)))
    bpy.ops.wm.obj_import(filepath=path, global_scale=float(import_scale))
    obj = bpy.context.selected_objects[0]
    Xl = np.zeros(3 * len(obj.data.vertices))
    obj.data.vertices.foreach_get("co", Xl)
    Xl = Xl.reshape(-1, 3)
    if len(Xl) != len(V):
        raise RuntimeError(f"the OBJ importer made {len(Xl)} vertices of {len(V)}")
    c = V.mean(axis=0)
    A = np.linalg.lstsq(V - c, Xl - Xl.mean(axis=0), rcond=None)[0].T
    if np.abs((V - c) @ A.T - (Xl - Xl.mean(axis=0))).max() > 1e-4 * np.ptp(V):
        raise RuntimeError("the OBJ importer changed the vertex order or shape")
    obj.shape_key_add(name="Basis", from_mix=False)
    deltas = np.stack([(face.expressions[n] - face.neutral) @ A.T for n in names])
    keys = [add_corrective_key(obj, n, d).name for n, d in zip(names, deltas)]
    key_values_bulk(obj, keys, frames, W)
    fixed = ~np.asarray(face.part_vertex_mask("M_Face"))
    obj.vertex_groups.new(name=FIXED_GROUP).add(np.flatnonzero(fixed).tolist(), 1.0, "REPLACE")
    obj.name = name
    return scene, obj, deltas, A


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

    The contact ``loop`` (ordered: corner, one lip, corner, the other lip, as
    :attr:`facelab_addon.testing.lip_truth.TruthLine.loop` and ``inner_lip_loop`` return it) is split at its
    two corners (its extremes across ``up``, i.e. along the mouth's width) into two halves;
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


def _add_armature(scene, obj, V, loop, cm, pose, matrix=None):
    """A head bone (neck to crown) and a jaw bone (below the ears to the chin); skin weights; optional pose.

    ``V``: Z-up positions in the armature's space (the object's local space, the armature scaled as the object),
    ``cm`` units per centimetre. With ``matrix`` (the object's world matrix), ``V`` is ``V_local @ matrix[:3, :3].T``
    (world axes and units, Z up) and the armature is unscaled and unrotated at the object's location.
    """
    import bpy

    arm_data = bpy.data.armatures.new("Rig")
    arm = bpy.data.objects.new("Rig", arm_data)
    scene.collection.objects.link(arm)
    if matrix is None:
        arm.scale = obj.scale
    else:
        arm.location = tuple(np.asarray(matrix)[:3, 3])
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


def sketch_truth(rs: RouteScene, frame: int, camera_obj=None, sketch_name: str | None = None, *,
                 noise_px: float = 0.0, seed: int = 0):
    """Draw the truth's inner-lip silhouettes on ``frame`` through a camera, as the artist would.

    With ``noise_px`` > 0 each stroke gets a hand's smooth jitter (:func:`jitter_stroke`: RMS ``noise_px``
    pixels, a few waves along the stroke, its own per ``seed``, frame, camera and lip).

    Returns ``(gp_obj, upper_px, lower_px)`` (the pixels as drawn); the sketch is a Grease Pencil object
    attached to the camera (one per camera: ``FL_LipSketch`` for the scene camera, ``FL_LipSketch.<camera>``
    for another).
    """
    import zlib

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
    if noise_px > 0:
        rng = np.random.default_rng([int(seed), int(frame), zlib.crc32(cam_obj.name.encode())])
        up_px, lo_px = jitter_stroke(up_px, noise_px, rng), jitter_stroke(lo_px, noise_px, rng)
    name = sketch_name or ("FL_LipSketch" if cam_obj == scene.camera else f"FL_LipSketch.{cam_obj.name}")
    gp = new_lip_sketch(scene, cam_obj, name=name)
    write_stroke_pixels(gp, "Upper lip", int(frame), [up_px], cam)
    write_stroke_pixels(gp, "Lower lip", int(frame), [lo_px], cam)
    return gp, up_px, lo_px


def jitter_stroke(px, noise_px: float, rng, waves: int = 3) -> np.ndarray:
    """A stroke ``px`` (N,2) as a hand draws it: plus a smooth, low-frequency offset of RMS ``noise_px`` pixels.

    The offset (each image axis) is a constant (a hand's bias) plus ``waves`` cosines along the stroke's
    arc length, wave ``k`` spanning ``k`` half periods over the stroke with amplitude ~ 1 / (1 + k) and a random
    phase; the whole is scaled so the RMS length of the offsets is ``noise_px``. ``rng``: a NumPy Generator.
    """
    px = np.asarray(px, dtype=np.float64)
    if len(px) < 2 or noise_px <= 0:
        return px.copy()
    s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(px, axis=0), axis=1))]
    t = s / max(s[-1], 1e-12)
    off = np.zeros_like(px)
    for k in range(waves + 1):
        amp = rng.normal(size=2) / (1.0 + k)
        phase = rng.uniform(0.0, 2 * np.pi, size=2)
        off += amp * np.cos(np.pi * k * t[:, None] + phase)
    rms = float(np.sqrt(np.mean(np.sum(off * off, axis=1))))
    return px + off * (noise_px / max(rms, 1e-12))


def truth_contours(rs: RouteScene, Vw, cam):
    """Upper and lower inner-lip silhouette pixels of world positions ``Vw`` (left to right)."""
    from ..core.geometry.silhouette import lip_side, silhouette_edges

    from ..blender.mesh import world_winding

    F = world_winding(_tris(rs.obj), np.array(rs.obj.matrix_world)[:3, :3])  # a mirrored object: normals outward
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

