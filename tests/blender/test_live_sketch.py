"""Ready to draw, Snap to plate, Live Refine: headless, on the shipped sample (a face, its camera, its plate
rendered from the truth)."""

import bpy
import numpy as np
import pytest

from facelab_addon.blender.camera import camera_from_blender
from facelab_addon.blender.sample import read_sample
from facelab_addon.blender.sketch_mode import DRAW_MODE
from facelab_addon.blender.sketch_snap import SNAP_PROP, SNAP_REPORT_PROP
from facelab_addon.blender.strokes import read_lip_strokes, write_stroke_pixels
from facelab_addon.names import PREFIX

pytestmark = pytest.mark.blender

FRAME = 20


def _triangles(data):
    pv, po = data.poly_verts, data.poly_offsets
    return np.array([[pv[s], pv[s + k], pv[s + k + 1]] for s, e in zip(po[:-1], po[1:]) for k in range(1, e - s - 1)])


@pytest.fixture(scope="module")
def sample(addon):
    from facelab_addon.testing import synthetic as syn

    data = read_sample()
    bpy.ops.wm.read_factory_settings(use_empty=True)
    assert bpy.ops.facelab.load_sample() == {"FINISHED"}
    scene = bpy.context.scene
    F = _triangles(data)
    mouth = syn.find_mouth(data.vertices, F, None, near=data.vertices[data.inner_lip_loop].mean(0),
                           units_per_mm=0.001)
    truth = {}
    for f in (FRAME,):
        truth[f] = syn.lip_contours(data.truth()[f - 1], F, data.camera, mouth=mouth)
    return data, scene.name, truth


def _fresh(sample):
    """The sample scene back in Object mode with the face active and no sketch."""
    data, scene_name, truth = sample
    scene = bpy.data.scenes[scene_name]  # (an undo reloads every datablock)
    bpy.context.window.scene = scene
    if bpy.context.object is not None and bpy.context.object.mode != "OBJECT":
        bpy.ops.object.mode_set(mode="OBJECT")
    for o in [o for o in scene.objects if o.type == "GREASEPENCIL"]:
        bpy.data.objects.remove(o)
    face = scene.facelab.face
    face.select_set(True)
    bpy.context.view_layer.objects.active = face
    for area in bpy.context.screen.areas:
        if area.type == "VIEW_3D":
            area.spaces.active.region_3d.view_perspective = "PERSP"
    scene.camera.data.show_background_images = False
    scene.frame_set(FRAME)
    return data, scene, face


def _view3d_perspectives():
    return [a.spaces.active.region_3d.view_perspective for a in bpy.context.screen.areas if a.type == "VIEW_3D"]


def test_new_lip_sketch_leaves_the_artist_drawing_on_the_upper_lip(sample):
    data, scene, face = _fresh(sample)
    assert _view3d_perspectives() == ["PERSP"]
    assert bpy.ops.facelab.new_lip_sketch() == {"FINISHED"}
    gp = scene.facelab.sketch
    assert bpy.context.view_layer.objects.active == gp and gp.select_get() and not face.select_get()
    assert gp.mode == DRAW_MODE and bpy.context.mode == DRAW_MODE
    assert gp.data.layers.active.name == "Upper lip"
    assert _view3d_perspectives() == ["CAMERA"]  # the window's 3D view looks through the camera
    cam = scene.camera.data
    assert cam.show_background_images and all(bg.show_background_image for bg in cam.background_images)
    assert scene.facelab.face == face


def test_lower_lip_is_one_click_and_back(sample):
    data, scene, face = _fresh(sample)
    bpy.ops.facelab.new_lip_sketch()
    gp = scene.facelab.sketch
    assert bpy.ops.facelab.sketch_lip_layer(lip="lower") == {"FINISHED"}
    assert gp.data.layers.active.name == "Lower lip" and gp.mode == DRAW_MODE
    assert bpy.ops.facelab.sketch_lip_layer(lip="upper") == {"FINISHED"}
    assert gp.data.layers.active.name == "Upper lip"
    # from Object mode with the face active, the button takes the artist back to drawing on that lip
    bpy.ops.object.mode_set(mode="OBJECT")
    bpy.context.view_layer.objects.active = face
    assert bpy.ops.facelab.sketch_lip_layer(lip="lower") == {"FINISHED"}
    assert bpy.context.view_layer.objects.active == gp and gp.mode == DRAW_MODE
    assert gp.data.layers.active.name == "Lower lip"


def test_lip_layer_needs_a_sketch(sample):
    data, scene, face = _fresh(sample)
    scene.facelab.sketch = None
    assert not bpy.ops.facelab.sketch_lip_layer.poll()


def test_refine_runs_from_draw_mode_and_stays_there_and_undo_restores(sample):
    from facelab_addon.blender.mesh import evaluated_vertices

    data, scene, face = _fresh(sample)
    bpy.ops.facelab.new_lip_sketch()
    gp = scene.facelab.sketch
    up, lo = sample[2][FRAME]
    cam = camera_from_blender(scene)
    write_stroke_pixels(gp, "Upper lip", FRAME, [up], cam)
    write_stroke_pixels(gp, "Lower lip", FRAME, [lo], cam)
    X0 = evaluated_vertices(face, bpy.context.evaluated_depsgraph_get())
    bpy.ops.ed.undo_push(message="sketched")
    assert bpy.context.mode == DRAW_MODE
    assert bpy.ops.facelab.refine_lips.poll()  # was: "Switch to Object Mode to refine"
    assert bpy.ops.facelab.refine_lips() == {"FINISHED"}
    bpy.ops.ed.undo_push(message="Refine Lips")
    assert bpy.context.mode == DRAW_MODE and bpy.context.view_layer.objects.active == gp
    X1 = evaluated_vertices(face, bpy.context.evaluated_depsgraph_get())
    assert np.abs(X1 - X0).max() > 1e-4  # the lips moved (> 0.1 mm)
    assert f"FL_Refine_{FRAME:04d}" in face.data.shape_keys.key_blocks
    name = face.name
    bpy.ops.ed.undo()
    face = bpy.data.objects[name]
    assert bpy.context.object.type == "GREASEPENCIL" and bpy.context.mode == DRAW_MODE
    assert not [k for k in face.data.shape_keys.key_blocks if k.name.startswith(PREFIX)]
    np.testing.assert_allclose(evaluated_vertices(face, bpy.context.evaluated_depsgraph_get()), X0, atol=1e-7)


def _contour_error(P, truth):
    """Mean distance (px) of the points ``P`` (N,2) from the polyline ``truth`` (M,2)."""
    a, b = truth[:-1], truth[1:]
    ab = b - a
    t = np.clip(np.einsum("nmk,mk->nm", P[:, None] - a[None], ab) / np.maximum((ab * ab).sum(1), 1e-12), 0, 1)
    d = np.linalg.norm(P[:, None] - (a[None] + t[..., None] * ab[None]), axis=2)
    return d.min(1)


def test_snap_to_plate_brings_jittered_strokes_onto_the_rendered_lip_line(sample):
    from facelab_addon.testing.route import jitter_stroke

    data, scene, face = _fresh(sample)
    bpy.ops.facelab.new_lip_sketch()
    gp = scene.facelab.sketch
    up, lo = sample[2][FRAME]
    cam = camera_from_blender(scene)
    rng = np.random.default_rng(3)
    drawn = {"upper": jitter_stroke(up, 3.0, rng), "lower": jitter_stroke(lo, 3.0, rng)}
    write_stroke_pixels(gp, "Upper lip", FRAME, [drawn["upper"]], cam)
    write_stroke_pixels(gp, "Lower lip", FRAME, [drawn["lower"]], cam)
    plain = read_lip_strokes(scene, cam, FRAME, gp_obj=gp)
    assert SNAP_REPORT_PROP not in gp  # off by default
    gp[SNAP_PROP] = True
    snapped = read_lip_strokes(scene, cam, FRAME, gp_obj=gp)
    report = gp[SNAP_REPORT_PROP]
    n = len(drawn["upper"]) + len(drawn["lower"])
    moved = sum(int(np.any(a != b)) for lab in ("upper", "lower") for a, b in zip(snapped[lab][0], plain[lab][0]))
    assert report.startswith(f"snapped {moved} of {n} points"), report
    # the lower lip's inner edge (lit lip against the dark mouth) is on the plate: the stroke lands on it
    before = _contour_error(plain["lower"][0], lo).mean()
    after = _contour_error(snapped["lower"][0], lo).mean()
    assert before > 1.5 and after < 0.6, (before, after)
    print(f"upper {_contour_error(plain['upper'][0], up).mean():.2f} -> "
          f"{_contour_error(snapped['upper'][0], up).mean():.2f} px; lower {before:.2f} -> {after:.2f} px; {report}")
    # the strokes drawn are untouched: reading without snapping gives them back
    again = read_lip_strokes(scene, cam, FRAME, gp_obj=gp, snap=False)
    np.testing.assert_allclose(again["upper"][0], plain["upper"][0], atol=1e-6)
