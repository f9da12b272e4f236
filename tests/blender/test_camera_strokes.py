"""Headless tests of the Blender camera and sketch adapters (bpy 5.0 wheel).

Checks ``facelab_addon.blender.camera`` against Blender's own
``world_to_camera_view`` and ``facelab_addon.blender.strokes`` by round trips
through Grease Pencil v3 data and through annotations made by Blender's own
``gpencil.annotate`` operator.
"""

import itertools
import os
import sys
import tempfile

if "bpy" not in sys.modules:
    os.environ["BLENDER_USER_RESOURCES"] = tempfile.mkdtemp(prefix="facelab-blender-user-")

import bpy  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from bpy_extras.object_utils import world_to_camera_view  # noqa: E402
from mathutils import Vector  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from facelab_addon.blender import compat  # noqa: E402
from facelab_addon.blender.camera import apply_camera_to_blender, camera_from_blender  # noqa: E402
from facelab_addon.blender.strokes import (  # noqa: E402
    new_lip_sketch,
    read_lip_strokes,
    write_stroke_pixels,
)
from facelab_addon.core.capture.camera import Camera  # noqa: E402
from facelab_addon.core.errors import CameraError, SketchError  # noqa: E402

pytestmark = [pytest.mark.blender, pytest.mark.usefixtures("empty_scene")]  # every test: an empty scene

TOL_PX = 0.01


def add_camera(scene, name="Cam"):
    data = bpy.data.cameras.new(name)
    obj = bpy.data.objects.new(name, data)
    scene.collection.objects.link(obj)
    scene.camera = obj
    return obj


def blender_pixels(scene, cam_obj, X, width, height):
    """Pixels of world points by Blender's own world_to_camera_view."""
    uv = np.array([world_to_camera_view(scene, cam_obj, Vector(x))[:2] for x in X])
    return np.c_[uv[:, 0] * width, (1.0 - uv[:, 1]) * height]


def points_in_front(camera, rng, n=300, depth=(0.5, 4.0), spread=1.5):
    size = np.array([camera.width, camera.height])
    px = rng.uniform(-0.2 * size, 1.2 * size, (n, 2))
    o, d = camera.rays(px)
    z = rng.uniform(*depth, n)
    return o + d * (z / (d @ camera.forward))[:, None]


# ------------------------------------------------------------------ camera
CAMERA_CASES = list(
    itertools.product(
        ["AUTO", "HORIZONTAL", "VERTICAL"],
        [(0.0, 0.0), (0.17, -0.23)],  # shift
        [(1.0, 1.0), (2.0, 1.0), (1.0, 1.5)],  # pixel aspect x, y
        [100, 50],  # resolution percentage
        [(1920, 1080), (1080, 1920), (1001, 999)],  # landscape, portrait, near-square
    )
)


@pytest.mark.parametrize("fit,shift,aspect,percent,resolution", CAMERA_CASES)
def test_camera_matches_world_to_camera_view(empty_scene, fit, shift, aspect, percent, resolution):
    scene = empty_scene
    cam_obj = add_camera(scene)
    cam = cam_obj.data
    cam.lens, cam.sensor_width, cam.sensor_height = 42.0, 30.0, 20.0
    cam.sensor_fit = fit
    cam.shift_x, cam.shift_y = shift
    r = scene.render
    r.resolution_x, r.resolution_y = resolution
    r.resolution_percentage = percent
    r.pixel_aspect_x, r.pixel_aspect_y = aspect
    cam_obj.location = (0.3, -4.0, 0.5)
    cam_obj.rotation_euler = (1.4, 0.1, 0.2)

    camera = camera_from_blender(scene)
    assert (camera.width, camera.height) == (resolution[0] * percent // 100, resolution[1] * percent // 100)
    rng = np.random.default_rng(0)
    X = rng.uniform(-1.5, 1.5, (200, 3))
    ref = blender_pixels(scene, cam_obj, X, camera.width, camera.height)
    assert np.abs(camera.project(X) - ref).max() < TOL_PX


def test_camera_ignores_scale_and_follows_parent(empty_scene):
    scene = empty_scene
    cam_obj = add_camera(scene)
    parent = bpy.data.objects.new("Rig", None)
    scene.collection.objects.link(parent)
    parent.location = (1.0, 2.0, -0.5)
    parent.rotation_euler = (0.3, -0.2, 1.0)
    parent.scale = (2.0, 2.0, 2.0)
    cam_obj.parent = parent
    cam_obj.location = (0.1, -3.0, 0.2)
    cam_obj.rotation_euler = (1.5, 0.0, 0.1)
    cam_obj.scale = (0.7, 0.7, 0.7)
    cam_obj.data.shift_x = 0.05
    camera = camera_from_blender(scene)
    rng = np.random.default_rng(1)
    X = points_in_front(camera, rng, depth=(2.0, 8.0))
    ref = blender_pixels(scene, cam_obj, X, camera.width, camera.height)
    assert np.abs(camera.project(X) - ref).max() < TOL_PX
    # The evaluated world matrix is used: camera centre and forward axis.
    M = np.array(cam_obj.matrix_world)
    assert np.allclose(camera.center, M[:3, 3], atol=1e-5)
    assert np.allclose(camera.forward, -M[:3, 2] / np.linalg.norm(M[:3, 2]), atol=1e-6)


@pytest.mark.parametrize("aspect", [1.0, 1.3, 0.8])
@pytest.mark.parametrize("principal_offset", [(0.0, 0.0), (140.0, -95.0), (-300.0, 210.0)])
def test_apply_camera_round_trip(empty_scene, aspect, principal_offset):
    scene = empty_scene
    W, H = 1280, 720
    f = 1500.0
    cx, cy = W / 2 + principal_offset[0], H / 2 + principal_offset[1]
    K = np.array([[f, 0, cx], [0, f * aspect, cy], [0, 0, 1.0]])
    R = Rotation.from_euler("xyz", [0.4, -0.3, 2.0]).as_matrix()
    core = Camera(K, R, np.array([0.2, -0.1, 3.0]), W, H)
    cam_obj = add_camera(scene)
    cam_obj.data.sensor_fit = "VERTICAL"  # must be overridden
    scene.render.resolution_percentage = 50
    apply_camera_to_blender(core, cam_obj, scene, sensor_width=24.0)
    rebuilt = camera_from_blender(scene)
    assert (rebuilt.width, rebuilt.height) == (W, H)
    rng = np.random.default_rng(2)
    X = points_in_front(core, rng)
    assert np.abs(rebuilt.project(X) - core.project(X)).max() < TOL_PX
    ref = blender_pixels(scene, cam_obj, X, W, H)
    assert np.abs(core.project(X) - ref).max() < TOL_PX


def test_camera_errors(empty_scene):
    scene = empty_scene
    with pytest.raises(CameraError, match="no active camera"):
        camera_from_blender(scene)
    cam_obj = add_camera(scene)
    cam_obj.data.type = "ORTHO"
    with pytest.raises(CameraError, match="Perspective"):
        camera_from_blender(scene)
    cam_obj.data.type = "PANO"
    with pytest.raises(CameraError, match="Perspective"):
        camera_from_blender(scene)
    cam_obj.data.type = "PERSP"
    cam_obj.scale = (1.0, -1.0, 1.0)
    with pytest.raises(CameraError, match="mirrored"):
        camera_from_blender(scene)
    empty = bpy.data.objects.new("Empty", None)
    scene.collection.objects.link(empty)
    with pytest.raises(CameraError, match="not a camera"):
        camera_from_blender(scene, empty)


# ------------------------------------------------------------------ sketch (Grease Pencil v3)
def face_camera(scene):
    """A 1280x720 camera 0.9 m in front of a face, principal point off-centre."""
    look = Camera.look_at((0.15, -0.9, 1.65), (0.0, 0.0, 1.6), (0, 0, 1), 50.0, 36.0, 1280, 720)
    K = np.array([[1750.0, 0.0, 700.0], [0.0, 1750.0, 330.0], [0.0, 0.0, 1.0]])
    core = Camera(K, look.R, look.t, 1280, 720)
    cam_obj = add_camera(scene)
    apply_camera_to_blender(core, cam_obj, scene)
    return cam_obj, camera_from_blender(scene)


def lip_polylines(offset=0.0):
    s = np.linspace(0.0, 1.0, 25)
    upper = [np.c_[500 + 280 * s, 380 - 40 * np.sin(np.pi * s) + offset]]
    lower = [
        np.c_[500 + 280 * s, 400 + 55 * np.sin(np.pi * s) + offset],
        np.array([[620.0, 470.0 + offset], [660.0, 474.0 + offset], [1400.0, 900.0]]),  # leaves the frame
    ]
    return upper, lower


def assert_same_polylines(got, expected):
    assert len(got) == len(expected)
    for g, e in zip(got, expected):
        assert g.shape == e.shape
        assert np.abs(g - e).max() < TOL_PX


def test_new_lip_sketch_layers_and_idempotence(empty_scene):
    scene = empty_scene
    cam_obj, camera = face_camera(scene)
    scene.frame_current = 3
    obj = new_lip_sketch(scene, cam_obj)
    gp = obj.data
    assert obj.type == "GREASEPENCIL" and obj.parent == cam_obj
    assert [layer.name for layer in gp.layers] == ["Upper lip", "Lower lip"]
    assert gp.layers.active.name == "Upper lip"
    assert all([f.frame_number for f in layer.frames] == [3] for layer in gp.layers)
    # The origin lies on the optical axis, just in front of the camera.
    bpy.context.view_layer.update()
    origin = np.array(obj.matrix_world.translation)
    assert 0 < camera.depth(origin[None])[0] < 1.0
    assert np.abs(camera.project(origin[None])[0] - camera.K[:2, 2]).max() < 1e-3

    upper, lower = lip_polylines()
    write_stroke_pixels(obj, "Upper lip", 3, upper, camera)
    write_stroke_pixels(obj, "Lower lip", 3, lower, camera)
    scene.frame_current = 7
    again = new_lip_sketch(scene, cam_obj)
    assert again == obj and len([o for o in bpy.data.objects if o.type == "GREASEPENCIL"]) == 1
    assert all([f.frame_number for f in layer.frames] == [3, 7] for layer in gp.layers)
    got = read_lip_strokes(scene, camera, 3)
    assert_same_polylines(got["upper"], upper)
    assert_same_polylines(got["lower"], lower)


def test_write_read_strokes_per_frame(empty_scene):
    scene = empty_scene
    cam_obj, camera = face_camera(scene)
    scene.frame_current = 1
    obj = new_lip_sketch(scene, cam_obj)
    up1, lo1 = lip_polylines(0.0)
    up10, lo10 = lip_polylines(17.5)
    for frame, up, lo in ((1, up1, lo1), (10, up10, lo10)):
        write_stroke_pixels(obj, "Upper lip", frame, up, camera)
        write_stroke_pixels(obj, "Lower lip", frame, lo, camera)
    for layer in obj.data.layers:
        assert [f.frame_number for f in layer.frames] == [1, 10]
        drawings = [f.drawing for f in layer.frames]
        assert drawings[0] != drawings[1]

    for frame, up, lo in ((1, up1, lo1), (5, up1, lo1), (10, up10, lo10), (30, up10, lo10)):
        got = read_lip_strokes(scene, camera, frame)
        assert_same_polylines(got["upper"], up)
        assert_same_polylines(got["lower"], lo)
    with pytest.raises(SketchError, match="'Upper lip' layer .* no strokes on frame 0"):
        read_lip_strokes(scene, camera, 0)

    # Appending keeps existing strokes; explicit object, other depth.
    extra = [np.array([[100.0, 100.0], [120.0, 130.0]])]
    write_stroke_pixels(obj, "Upper lip", 10, extra, camera, depth=2.5)
    got = read_lip_strokes(scene, camera, 10, gp_obj=obj)
    assert_same_polylines(got["upper"], up10 + extra)


def test_read_strokes_custom_layer_names_and_transform(empty_scene):
    scene = empty_scene
    cam_obj, camera = face_camera(scene)
    gp = compat.grease_pencil_data().new("Sketch")
    obj = bpy.data.objects.new("Sketch", gp)
    scene.collection.objects.link(obj)
    obj.location = (0.05, -0.5, 1.6)  # not parented; arbitrary transform
    obj.rotation_euler = (0.3, 0.2, -0.4)
    obj.scale = (1.5, 1.5, 1.5)
    gp.layers.new("UPPER contour")
    lower = gp.layers.new("lips LOWER")
    lower.translation = (0.01, 0.02, -0.03)  # layer transform
    up, lo = lip_polylines()
    write_stroke_pixels(obj, "UPPER contour", 1, up, camera, depth=0.6)
    write_stroke_pixels(obj, "lips LOWER", 1, lo, camera, depth=0.7)
    got = read_lip_strokes(scene, camera, 1)
    assert_same_polylines(got["upper"], up)
    assert_same_polylines(got["lower"], lo)


def test_sketch_errors(empty_scene):
    scene = empty_scene
    cam_obj, camera = face_camera(scene)
    with pytest.raises(SketchError, match="No lip sketch found.*New Lip Sketch"):
        read_lip_strokes(scene, camera, 1)

    obj = new_lip_sketch(scene, cam_obj)
    with pytest.raises(SketchError, match="'Upper lip' layer .* no strokes on frame 1"):
        read_lip_strokes(scene, camera, 1)
    up, lo = lip_polylines()
    write_stroke_pixels(obj, "Upper lip", 1, up, camera)
    with pytest.raises(SketchError, match="'Lower lip' layer .* no strokes on frame 1"):
        read_lip_strokes(scene, camera, 1)

    obj.data.layers.remove(obj.data.layers["Lower lip"])
    with pytest.raises(SketchError, match="no 'Lower lip' layer"):
        read_lip_strokes(scene, camera, 1)

    write_stroke_pixels(obj, "Lower lip", 1, lo, camera)
    read_lip_strokes(scene, camera, 1)  # complete again
    obj.location.z = 0.5  # camera space +z: behind the camera
    with pytest.raises(SketchError, match="behind the camera"):
        read_lip_strokes(scene, camera, 1)

    mesh = bpy.data.objects.new("NotGP", bpy.data.meshes.new("m"))
    scene.collection.objects.link(mesh)
    with pytest.raises(SketchError, match="not a Grease Pencil"):
        read_lip_strokes(scene, camera, 1, gp_obj=mesh)


def test_new_lip_sketch_needs_camera(empty_scene):
    with pytest.raises(CameraError, match="no camera"):
        new_lip_sketch(empty_scene, None)


# ------------------------------------------------------------------ annotations
def view3d_in_camera_view(scene, cam_obj):
    win = bpy.context.window_manager.windows[0]
    area = next(a for a in win.screen.areas if a.type == "VIEW_3D")
    region = next(r for r in area.regions if r.type == "WINDOW")
    space = area.spaces.active
    space.camera = cam_obj
    space.region_3d.view_perspective = "CAMERA"
    space.region_3d.view_camera_zoom = 0.0
    space.region_3d.view_camera_offset = (0.0, 0.0)
    return win, area, region


def annotate(win, area, region, scene, mice, placement):
    """Draw one annotation stroke on the active layer with Blender's own operator."""
    scene.tool_settings.annotation_stroke_placement_view3d = placement
    stroke = [
        dict(name="", mouse=m, mouse_event=m, location=(0, 0, 0), pressure=1.0, size=1.0,
             time=0.01 * i, is_start=(i == 0), x_tilt=0.0, y_tilt=0.0)
        for i, m in enumerate(mice)
    ]
    with bpy.context.temp_override(window=win, screen=win.screen, area=area, region=region):
        assert bpy.ops.gpencil.annotate(mode="DRAW", stroke=stroke, wait_for_input=False) == {"FINISHED"}


@pytest.mark.parametrize("shift", [(0.0, 0.0), (0.2, 0.1), (-0.3, -0.15)])
def test_annotation_view_placement_in_camera_view(empty_scene, shift):
    """'View' placement stores percent of the unshifted camera frame; read as true pixels.

    In camera view the camera frame stays put in the viewport while lens
    shift moves the picture, so a mouse position must give the same pixel
    for any shift. At zoom 0 the frame (horizontal fit) is half the region
    wide, centred; hence the expected pixels below.
    """
    scene = empty_scene
    cam_obj = add_camera(scene)
    cam_obj.location = (0.0, -3.0, 1.0)
    cam_obj.rotation_euler = (np.pi / 2, 0.0, 0.0)
    cam_obj.data.sensor_fit = "HORIZONTAL"
    cam_obj.data.shift_x, cam_obj.data.shift_y = shift
    scene.render.resolution_x, scene.render.resolution_y = 1920, 1080
    win, area, region = view3d_in_camera_view(scene, cam_obj)
    ann = compat.annotation_data().new("Annotations")
    compat.set_scene_annotation(scene, ann)
    cx, cy = region.width // 2, region.height // 2
    strokes = {
        "Upper lip": [(cx - 120, cy + 40), (cx + 90, cy + 60)],
        "Lower lip": [(cx - 100, cy - 30), (cx + 110, cy - 50)],
    }
    for name, mice in strokes.items():
        ann.layers.new(name, set_active=True)
        annotate(win, area, region, scene, mice, "VIEW")
        pts = np.array([p.co[:] for p in ann.layers[name].frames[0].strokes[0].points])
        assert pts.shape == (2, 3) and np.all(pts[:, 2] == 0.0)

    camera = camera_from_blender(scene)
    got = read_lip_strokes(scene, camera, 1)
    scale = camera.width / (region.width / 2.0)
    for lab, name in (("upper", "Upper lip"), ("lower", "Lower lip")):
        mice = np.array(strokes[name], dtype=float)
        expected = np.c_[camera.width / 2 + (mice[:, 0] - region.width / 2) * scale,
                         camera.height / 2 - (mice[:, 1] - region.height / 2) * scale]
        assert len(got[lab]) == 1
        assert np.abs(got[lab][0] - expected).max() < 0.05  # float32 percent storage


def test_annotation_world_points_and_frames(empty_scene):
    """'3D Cursor' placement stores world points; read through the camera, by frame."""
    scene = empty_scene
    cam_obj, camera = face_camera(scene)
    win, area, region = view3d_in_camera_view(scene, cam_obj)
    ann = compat.annotation_data().new("Annotations")
    compat.set_scene_annotation(scene, ann)
    rng = np.random.default_rng(3)
    expected = {}
    for name in ("upper lip", "LOWER lip"):
        ann.layers.new(name, set_active=True)
        for frame in (1, 10):
            scene.frame_current = frame
            mice = [(400 + 40 * i, 300 + 7 * i) for i in range(5)]
            annotate(win, area, region, scene, mice, "CURSOR")
            stroke = next(f for f in ann.layers[name].frames if f.frame_number == frame).strokes[-1]
            n = len(stroke.points)
            assert n >= 2
            px = np.c_[np.linspace(500, 800, n), rng.uniform(350, 450, n)]
            o, d = camera.rays(px)
            X = o + d * rng.uniform(0.5, 1.0, (n, 1))
            stroke.points.foreach_set("co", X.astype(np.float32).ravel())
            expected[name, frame] = px
    for frame, key_frame in ((1, 1), (4, 1), (12, 10)):
        got = read_lip_strokes(scene, camera, frame)
        assert_same_polylines(got["upper"], [expected["upper lip", key_frame]])
        assert_same_polylines(got["lower"], [expected["LOWER lip", key_frame]])

    ann.layers.remove(ann.layers["LOWER lip"])
    with pytest.raises(SketchError, match="no 'Lower lip' layer"):
        read_lip_strokes(scene, camera, 1)


def test_grease_pencil_object_wins_over_annotation(empty_scene):
    scene = empty_scene
    cam_obj, camera = face_camera(scene)
    ann = compat.annotation_data().new("Annotations")
    compat.set_scene_annotation(scene, ann)
    ann.layers.new("Upper lip")
    ann.layers.new("Lower lip")
    obj = new_lip_sketch(scene, cam_obj)
    up, lo = lip_polylines()
    write_stroke_pixels(obj, "Upper lip", 1, up, camera)
    write_stroke_pixels(obj, "Lower lip", 1, lo, camera)
    got = read_lip_strokes(scene, camera, 1)
    assert_same_polylines(got["upper"], up)
    assert_same_polylines(got["lower"], lo)
    # without the Grease Pencil object the (stroke-less) annotation is read instead, and refused
    bpy.data.objects.remove(obj)
    with pytest.raises(SketchError, match="no strokes"):
        read_lip_strokes(scene, camera, 1)


def test_one_sketch_per_camera_and_the_views_of_a_frame(empty_scene):
    from facelab_addon.blender.sketch_views import sketch_views
    from facelab_addon.blender.strokes import SKETCH_CAMERA_PROP, sketch_camera

    scene = empty_scene
    cam_a, camera_a = face_camera(scene)
    cam_b = add_camera(scene, "Witness")
    witness = Camera.look_at((-0.3, -0.8, 1.4), (0.0, 0.0, 1.6), (0, 0, 1), 50.0, 36.0, 1280, 720)
    apply_camera_to_blender(witness, cam_b, scene)
    scene.camera = cam_a
    scene.frame_current = 5
    sk_a = new_lip_sketch(scene, cam_a)
    sk_b = new_lip_sketch(scene, cam_b)
    assert sk_a.name == "FL_LipSketch" and sk_b.name == "FL_LipSketch.Witness" and sk_a != sk_b
    assert sketch_camera(sk_a) == cam_a and sketch_camera(sk_b) == cam_b and sk_b[SKETCH_CAMERA_PROP] == cam_b
    assert new_lip_sketch(scene, cam_b) == sk_b  # again: the witness camera's own sketch
    camera_b = camera_from_blender(scene, cam_b)
    up, lo = lip_polylines()
    for gp, cam in ((sk_a, camera_a), (sk_b, camera_b)):
        write_stroke_pixels(gp, "Upper lip", 5, up, cam)
        write_stroke_pixels(gp, "Lower lip", 5, lo, cam)
    assert [(g.name, c.name) for g, c in sketch_views(scene, 5)] == [("FL_LipSketch", "Cam"),
                                                                      ("FL_LipSketch.Witness", "Witness")]
    assert sketch_views(scene, 6) == []  # drawings held from frame 5 are not views of frame 6
    # each sketch reads back as the pixels drawn in its own camera
    assert_same_polylines(read_lip_strokes(scene, camera_b, 5, gp_obj=sk_b)["upper"], up)
    # a sketch without the property belongs to the camera it is parented to
    del sk_b[SKETCH_CAMERA_PROP]
    assert sketch_camera(sk_b) == cam_b
