"""Headless end to end: ICT face + camera + backplate + Grease Pencil sketch -> Refine Lips."""

import bpy  # noqa: E402  (conftest set BLENDER_USER_RESOURCES)
import numpy as np
import pytest

from facelab_addon.blender.camera import camera_from_blender, new_camera_object
from facelab_addon.blender.mesh import evaluated_vertices, mesh_triangles
from facelab_addon.blender.scene import new_mesh_object, set_backplate
from facelab_addon.blender.strokes import write_stroke_pixels
from facelab_addon.core.capture.camera import Camera
from facelab_addon.core.geometry.silhouette import contour_distance, lip_side, silhouette_edges

pytestmark = pytest.mark.blender

FRAME = 12
SCALE = 0.01  # ICT centimetres -> metres, as a Blender user would import it


def lip_contours(V, F, cam, face_mask, mouth):
    """Truth inner-lip silhouettes (pixels), left to right; and the lip vertices (V,) mask."""
    E = silhouette_edges(V, F, cam)
    E = E[face_mask[E].all(1)]
    corner_x = np.abs(V[mouth, 0]).max()
    mc = V[mouth].mean(0)
    E = E[(np.abs(V[E, 0]) < 0.98 * corner_x).all(1) & (np.abs(V[E, 1] - mc[1]) < 0.01).all(1)]
    side = lip_side(V, F, cam, E.ravel()).reshape(-1, 2)
    up, lo = np.unique(E[(side == 1).all(1)]), np.unique(E[(side == -1).all(1)])
    px = cam.project(V)
    return px[up[np.argsort(px[up, 0])]], px[lo[np.argsort(px[lo, 0])]], up, lo


def scene_setup(tmp_path, ict):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.frame_set(FRAME)
    T = ict.pose({"jawOpen": 0.2, "mouthFunnel": 0.3}) * SCALE
    F = ict.faces
    face_mask = ict.part_vertex_mask("M_Face")
    mouth = np.arange(6632, 6706)  # ICT lip ring (see shared/ict-facekit/README.md)
    mc = T[mouth].mean(0)
    cam = Camera.look_at(mc + [0, 0, 0.40], mc, [0, 1, 0], 50, 36, 1920, 1080)
    up_px, lo_px, up, lo = lip_contours(T, F, cam, face_mask, mouth)
    # capture error: a 2.5 mm gap, smooth over the inner lips, fading at the corners
    from scipy.spatial import cKDTree

    d, j = cKDTree(T[np.r_[up, lo]]).query(T)
    sign = np.r_[np.ones(len(up)), -np.ones(len(lo))][j]
    w = np.clip(1 - (d / 0.008) ** 2, 0, 1) ** 2 * face_mask * np.clip(1 - (T[:, 0] / np.abs(T[mouth, 0]).max()) ** 4, 0, 1)
    C = T.copy()
    C[:, 1] += sign * w * 0.00125
    obj = new_mesh_object("Face", C, poly_verts=ict.poly_verts, poly_offsets=ict.poly_offsets)
    vg = obj.vertex_groups.new(name="FL_fixed")
    vg.add(np.flatnonzero(~face_mask).tolist(), 1.0, "REPLACE")
    cam_obj = new_camera_object(scene, cam)
    from PIL import Image
    from skimage import data

    plate = tmp_path / "plate.png"
    Image.fromarray(data.astronaut()).resize((1920, 1080)).save(plate)
    set_backplate(cam_obj, plate)
    bpy.context.view_layer.objects.active = obj
    obj.select_set(True)
    return dict(scene=scene, obj=obj, cam=cam, C=C, T=T, up_px=up_px, lo_px=lo_px, face_mask=face_mask, F=F)


def test_refine_lips_operator_end_to_end(tmp_path, ict, addon):
    s = scene_setup(tmp_path, ict)
    scene, obj = s["scene"], s["obj"]
    assert bpy.ops.facelab.new_lip_sketch() == {"FINISHED"}
    gp = scene.facelab.sketch
    assert gp is not None and scene.facelab.face == obj
    cam = camera_from_blender(scene)
    write_stroke_pixels(gp, "Upper lip", FRAME, [s["up_px"]], cam)
    write_stroke_pixels(gp, "Lower lip", FRAME, [s["lo_px"]], cam)
    bpy.context.view_layer.objects.active = obj
    bpy.ops.ed.undo_push(message="sketched")

    assert bpy.ops.facelab.refine_lips() == {"FINISHED"}
    # Headless Blender does not push undo steps for script-called operators; the UI
    # does so for every operator with bl_options 'UNDO'. Emulate it.
    bpy.ops.ed.undo_push(message="Refine Lips")

    dg = bpy.context.evaluated_depsgraph_get()
    X = evaluated_vertices(obj, dg)
    F = mesh_triangles(obj.data)
    fm = s["face_mask"]
    before = np.r_[
        contour_distance(s["C"], F, cam, s["up_px"], +1, candidates=fm),
        contour_distance(s["C"], F, cam, s["lo_px"], -1, candidates=fm),
    ]
    after = np.r_[
        contour_distance(X, F, cam, s["up_px"], +1, candidates=fm),
        contour_distance(X, F, cam, s["lo_px"], -1, candidates=fm),
    ]
    assert before.mean() > 4.0  # the injected gap is visible
    assert after.mean() < 1.0, after.mean()  # the silhouettes moved onto the strokes
    # inner-lip 3D error against the truth falls
    lip = np.linalg.norm(s["C"] - s["T"], axis=1) > 1e-6
    e0 = np.sqrt((np.linalg.norm(s["C"] - s["T"], axis=1)[lip] ** 2).mean())
    e1 = np.sqrt((np.linalg.norm(X - s["T"], axis=1)[lip] ** 2).mean())
    assert e1 < 0.7 * e0, (e0, e1)
    # fixed (hidden) vertices did not move
    assert np.abs(X - s["C"])[~fm].max() < 1e-4 * 0.01 * 100  # < 0.01 mm

    # a new corrective shape key, keyed 1 on the frame and 0 on its neighbours
    keys = obj.data.shape_keys.key_blocks
    kb = keys[f"FL_Refine_{FRAME:04d}"]
    assert kb.relative_key == obj.data.shape_keys.reference_key
    vals = {}
    for f in (FRAME - 1, FRAME, FRAME + 1):
        scene.frame_set(f)
        vals[f] = kb.value
    assert vals == {FRAME - 1: 0.0, FRAME: 1.0, FRAME + 1: 0.0}
    scene.frame_set(FRAME - 1)
    np.testing.assert_allclose(evaluated_vertices(obj, bpy.context.evaluated_depsgraph_get()), s["C"], atol=1e-6)
    scene.frame_set(FRAME)
    # recorded as a training frame, marked on the timeline
    tf = obj.facelab.training_frames
    assert len(tf) == 1 and tf[0].frame == FRAME and tf[0].shape_key == kb.name
    assert any(m.frame == FRAME for m in scene.timeline_markers)

    # running it again never overwrites: a second key appears
    assert bpy.ops.facelab.refine_lips() == {"FINISHED"}
    assert f"FL_Refine_{FRAME:04d}.001" in obj.data.shape_keys.key_blocks
    bpy.ops.ed.undo_push(message="Refine Lips")

    # undo twice restores the mesh exactly (no FaceLab keys)
    bpy.ops.ed.undo()
    bpy.ops.ed.undo()
    obj = bpy.data.objects["Face"]
    sk = obj.data.shape_keys
    assert sk is None or not any(k.name.startswith("FL_") for k in sk.key_blocks)
    np.testing.assert_allclose(evaluated_vertices(obj, bpy.context.evaluated_depsgraph_get()), s["C"], atol=1e-7)
    assert len(obj.facelab.training_frames) == 0


def test_refine_lips_bad_input_changes_nothing(tmp_path, ict, addon):
    s = scene_setup(tmp_path, ict)
    scene, obj = s["scene"], s["obj"]
    # no sketch at all
    with pytest.raises(RuntimeError, match="New Lip Sketch"):
        bpy.ops.facelab.refine_lips()
    bpy.ops.facelab.new_lip_sketch()
    cam = camera_from_blender(scene)
    write_stroke_pixels(scene.facelab.sketch, "Upper lip", FRAME, [s["up_px"]], cam)
    # only one lip drawn
    with pytest.raises(RuntimeError, match="(?i)lower lip"):
        bpy.ops.facelab.refine_lips()
    # a camera turned around, looking away from the face: the face is behind it
    write_stroke_pixels(scene.facelab.sketch, "Lower lip", FRAME, [s["lo_px"]], cam)
    scene.camera.rotation_mode = "XYZ"
    scene.camera.rotation_euler.y += np.pi
    with pytest.raises(RuntimeError, match="(?i)behind"):
        bpy.ops.facelab.refine_lips()
    scene.camera.rotation_euler.y -= np.pi
    # a stroke outside the frame
    write_stroke_pixels(scene.facelab.sketch, "Lower lip", FRAME, [s["lo_px"] + [0, 700]], cam)
    with pytest.raises(RuntimeError, match="leaves the camera frame"):
        bpy.ops.facelab.refine_lips()
    assert obj.data.shape_keys is None
    assert len(obj.facelab.training_frames) == 0
    # no camera: poll explains
    scene.camera = None
    assert not bpy.ops.facelab.refine_lips.poll()
    with pytest.raises(RuntimeError, match="scene camera"):
        bpy.ops.facelab.refine_lips()
