"""Movie Clip tracks, clip cameras, masks and contour strokes -> FaceLab pixels (hand-computed values)."""

import math

import bpy
import numpy as np
import pytest

from facelab_addon.blender import compat, masks, tracking
from facelab_addon.blender.camera import camera_from_blender
from facelab_addon.core.capture.camera import Camera
from facelab_addon.core.errors import BundleError, CameraError, SketchError

pytestmark = pytest.mark.blender

W, H = 80, 60  # footage size
NFRAMES = 6


def make_clip(tmp_path, name="plate", n=NFRAMES, size=(W, H)):
    """A PNG image sequence on disk loaded as a Movie Clip."""
    from PIL import Image

    d = tmp_path / name
    d.mkdir()
    for i in range(1, n + 1):
        img = np.zeros((size[1], size[0], 3), np.uint8)
        img[..., 0] = (30 * i) % 256
        Image.fromarray(img).save(d / f"{name}_{i:04d}.png")
    clip = bpy.data.movieclips.load(str(d / f"{name}_0001.png"))
    assert tuple(clip.size) == size
    return clip


def new_camera(name, location=(0, -1, 0), rotation=(math.pi / 2, 0, 0)):
    cam = bpy.data.objects.new(name, bpy.data.cameras.new(name))
    bpy.context.scene.collection.objects.link(cam)
    cam.location = location
    cam.rotation_euler = rotation
    return cam


@pytest.fixture
def scene(empty_scene):
    return empty_scene


def add_track(clip, name, markers, offset=(0.0, 0.0)):
    """``markers``: {clip_frame: (co_x, co_y) or (co_x, co_y, muted)}."""
    frames = sorted(markers)
    tr = clip.tracking.tracks.new(name=name, frame=frames[0])
    tr.offset = offset
    for f in frames:
        v = markers[f]
        mk = tr.markers.find_frame(f) or tr.markers.insert_frame(f)
        mk.co = v[:2]
        mk.mute = len(v) > 2 and v[2]
    return tr


# --------------------------------------------------------------------------- markers
def test_markers_pixels_missing_muted_offscreen_and_clip_start(scene, tmp_path):
    clip = make_clip(tmp_path)
    clip.frame_start = 11  # scene frame 11 shows clip frame 1
    add_track(clip, "A", {1: (0.25, 0.75), 2: (0.5, 0.5), 4: (0.1, 0.9, True), 5: (1.2, 0.5), 6: (0.5, -0.01)})
    add_track(clip, "B", {2: (0.3, 0.4), 3: (0.35, 0.45)}, offset=(0.1, -0.05))
    frames = np.arange(11, 17)  # clip frames 1..6
    px, names = tracking.read_track_markers(clip, frames)
    assert names == ["A", "B"]
    assert px.shape == (6, 2, 2)
    nan = [np.nan, np.nan]
    expect_a = [[20, 15], [40, 30], nan, nan, nan, nan]  # 3: no marker, 4: muted, 5/6: off-screen
    expect_b = [nan, [(0.3 + 0.1) * W, (1 - 0.4 + 0.05) * H], [(0.35 + 0.1) * W, (1 - 0.45 + 0.05) * H], nan, nan, nan]
    np.testing.assert_allclose(px[:, 0], expect_a, atol=1e-4)
    np.testing.assert_allclose(px[:, 1], expect_b, atol=1e-4)
    # names select and order columns; an unknown name is all NaN; frames outside the markers are NaN
    px2, names2 = tracking.read_track_markers(clip, [12, 30, 1], names=["B", "nope", "A"])
    assert names2 == ["B", "nope", "A"]
    np.testing.assert_allclose(px2[0, 0], [32, 39], atol=1e-4)
    np.testing.assert_allclose(px2[0, 2], [40, 30], atol=1e-4)
    assert np.isnan(px2[1:]).all() and np.isnan(px2[:, 1]).all()
    # a track with weight 0 ("no influence on the solve") is left out
    clip.tracking.tracks["B"].weight = 0.0
    assert np.isnan(tracking.read_track_markers(clip, frames)[0][:, 1]).all()
    assert np.isfinite(tracking.read_track_markers(clip, frames, skip_zero_weight=False)[0][1:3, 1]).all()
    clip.tracking.tracks["B"].weight = 1.0
    # margin: a marker 2 px from the border is off-screen with a 3 px margin
    add_track(clip, "C", {1: (2 / W, 0.5)})
    assert np.isfinite(tracking.read_track_markers(clip, [11], names=["C"])[0]).all()
    assert np.isnan(tracking.read_track_markers(clip, [11], names=["C"], margin=3)[0]).all()


def test_markers_bulk_speed(scene, tmp_path):
    """100 tracks x 1000 frames read in well under a second."""
    import time

    clip = make_clip(tmp_path, n=2)
    rng = np.random.default_rng(1)
    co = rng.uniform(0.05, 0.95, (100, 1000, 2)).astype(np.float32)
    for j in range(100):
        tr = clip.tracking.tracks.new(name=f"T{j:03d}", frame=1)
        for f in range(2, 1001):
            tr.markers.insert_frame(f)
        tr.markers.foreach_set("co", co[j].ravel())
    t0 = time.perf_counter()
    px, names = tracking.read_track_markers(clip, np.arange(1, 1001))
    dt = time.perf_counter() - t0
    print(f"read 100 tracks x 1000 frames in {dt * 1e3:.1f} ms")
    assert dt < 1.0
    np.testing.assert_allclose(px[:, 7], np.c_[co[7, :, 0] * W, (1 - co[7, :, 1]) * H], atol=1e-4)


# --------------------------------------------------------------------------- cameras
def setup_camera_like_blender(scene, clip, cam_obj):
    """What Blender's Clip editor 'Setup Tracking Scene' / 'Set Scene Frames' do to the camera and render."""
    tc = clip.tracking.camera
    cam = cam_obj.data
    cam.sensor_width = tc.sensor_width
    cam.sensor_fit = "HORIZONTAL"
    cam.lens = tc.focal_length
    w, h = clip.size
    pp = tc.principal_point_pixels
    cam.shift_x = (0.5 * w - pp[0]) / w
    cam.shift_y = (0.5 * h - pp[1]) / w
    scene.render.resolution_x, scene.render.resolution_y = w, h
    scene.render.resolution_percentage = 100
    scene.render.pixel_aspect_x = tc.pixel_aspect
    scene.render.pixel_aspect_y = 1.0


def test_clip_camera_intrinsics_pose_and_agreement(scene, tmp_path):
    clip = make_clip(tmp_path)
    tc = clip.tracking.camera
    tc.sensor_width, tc.focal_length = 36.0, 50.0
    tc.principal_point_pixels = (42.0, 27.0)  # bottom-left origin
    cam_obj = new_camera("Cam", location=(0.1, -1.0, 0.05), rotation=(math.radians(85), 0.0, math.radians(4)))
    setup_camera_like_blender(scene, clip, cam_obj)
    cam, warn = tracking.clip_camera(scene, cam_obj, clip)
    f = 50.0 * W / 36.0
    np.testing.assert_allclose(cam.K, [[f, 0, 42.0], [0, f, H - 27.0], [0, 0, 1]], atol=1e-4)
    assert (cam.width, cam.height) == (W, H)
    assert warn == []
    # same camera as Blender's own camera model after Setup Tracking Scene
    bl = camera_from_blender(scene, cam_obj)
    np.testing.assert_allclose(bl.K, cam.K, atol=1e-3)
    np.testing.assert_allclose(bl.R, cam.R, atol=1e-9)
    np.testing.assert_allclose(bl.t, cam.t, atol=1e-9)
    # a point straight ahead of the camera lands on the principal point
    X = cam.center + 2.0 * cam.forward
    np.testing.assert_allclose(cam.project(X[None])[0], [42.0, H - 27.0], atol=1e-6)

    # anamorphic: fy = f * pixel_aspect, and Blender's render camera agrees (Blender's shift conversion only
    # keeps the principal point for pixel aspect 1 when it is off-centre vertically, so centre it here)
    tc.pixel_aspect = 2.0
    tc.principal_point_pixels = (42.0, H / 2)
    setup_camera_like_blender(scene, clip, cam_obj)
    cam2, warn2 = tracking.clip_camera(scene, cam_obj, clip)
    assert warn2 == []
    np.testing.assert_allclose(cam2.K[1, 1], 2 * f, atol=1e-3)
    np.testing.assert_allclose(camera_from_blender(scene, cam_obj).K, cam2.K, atol=1e-3)
    tc.pixel_aspect = 1.0
    tc.principal_point_pixels = (42.0, 27.0)
    setup_camera_like_blender(scene, clip, cam_obj)

    # disagreement and distortion are warned about (the clip wins)
    cam_obj.data.lens = 35.0
    tc.k1 = -0.05
    cam3, warn3 = tracking.clip_camera(scene, cam_obj, clip)
    np.testing.assert_allclose(cam3.K, cam.K)
    assert any("disagrees" in w and "Cam" in w for w in warn3)
    assert any("distortion" in w and "k1=-0.05" in w for w in warn3)


def test_clip_camera_bad_input(scene, tmp_path):
    clip = make_clip(tmp_path)
    cam_obj = new_camera("Cam")
    with pytest.raises(CameraError, match="no Movie Clip.*Views"):
        tracking.clip_camera(scene, cam_obj, None)
    empty = bpy.data.objects.new("E", None)
    with pytest.raises(CameraError, match="camera object"):
        tracking.clip_camera(scene, empty, clip)
    clip.tracking.camera.sensor_width = 0.0  # (Blender keeps the focal length > 0)
    with pytest.raises(CameraError, match="no camera calibration.*sensor width 0"):
        tracking.clip_camera(scene, cam_obj, clip)
    from types import SimpleNamespace

    missing = SimpleNamespace(name="gone", filepath="//gone/x_0001.png", size=(0, 0))  # what Blender reports
    with pytest.raises(CameraError, match="no readable footage"):
        tracking.clip_size(missing)


def test_read_views_union_of_tracks_and_moving_camera(scene, tmp_path):
    c1, c2 = make_clip(tmp_path, "left"), make_clip(tmp_path, "right")
    for c in (c1, c2):
        c.tracking.camera.sensor_width, c.tracking.camera.focal_length = 36.0, 40.0
    add_track(c1, "nose", {1: (0.5, 0.5), 2: (0.5, 0.55)})
    add_track(c1, "chin", {1: (0.5, 0.2)})
    add_track(c2, "cheek_L", {2: (0.7, 0.5)})
    add_track(c2, "nose", {1: (0.4, 0.5)})
    k1, k2 = new_camera("K1", (-0.2, -1, 0)), new_camera("K2", (0.2, -1, 0))
    face = bpy.data.objects.new("Face", bpy.data.meshes.new("Face"))
    scene.collection.objects.link(face)
    views = [tracking.View(k1, c1), tracking.View(k2, c2)]
    vd = tracking.read_views(scene, views, [1, 2], check_static=face)
    assert vd.names == ["nose", "chin", "cheek_L"]
    assert vd.markers.shape == (2, 2, 3, 2)
    np.testing.assert_allclose(vd.markers[0, 0, 0], [40, 30])
    np.testing.assert_allclose(vd.markers[0, 1, 0], [32, 30])
    np.testing.assert_allclose(vd.markers[1, 1, 2], [56, 30])
    assert np.isnan(vd.markers[1, 0, 1]).all() and np.isnan(vd.markers[0, 1, 2]).all()
    np.testing.assert_allclose(vd.cameras[1].center, [0.2, -1, 0], atol=1e-6)
    # a camera that moves relative to the face is refused, naming it
    k2.keyframe_insert("location", frame=1)
    k2.location.x = 0.3
    k2.keyframe_insert("location", frame=2)
    with pytest.raises(CameraError, match="'K2' moves relative to the face"):
        tracking.read_views(scene, views, [1, 2], check_static=face)
    with pytest.raises(CameraError, match="No solve views"):
        tracking.read_views(scene, [], [1])


def test_clip_bundles_needs_a_solve(scene, tmp_path):
    clip = make_clip(tmp_path)
    add_track(clip, "A", {1: (0.5, 0.5)})
    with pytest.raises(BundleError, match="Solve Camera Motion"):
        tracking.clip_bundles(clip)


def test_clip_bundles_and_intrinsics_agree_with_blenders_camera_solve(scene, tmp_path):
    """Blender's own solver (libmv) on synthetic tracks with an off-centre principal point: its bundles, seen by its
    reconstructed cameras through FaceLab's clip intrinsics, land on the markers FaceLab reads."""

    w, h, n = 320, 240, 12
    clip = make_clip(tmp_path, n=n, size=(w, h))
    tc = clip.tracking.camera
    tc.sensor_width, tc.focal_length = 36.0, 30.0
    tc.principal_point_pixels = (w / 2 + 12.0, h / 2 - 7.0)  # bottom-left origin
    K, _, _ = tracking.clip_intrinsics(clip)
    rng = np.random.default_rng(0)
    X = rng.uniform([-1, -1, 4], [1, 1, 7], (24, 3))
    for j in range(len(X)):
        tr = clip.tracking.tracks.new(name=f"P{j:02d}", frame=1)
        for k in range(2, n + 1):
            tr.markers.insert_frame(k)
        co = []
        for k in range(n):
            th = 0.03 * k
            R = np.array([[np.cos(th), 0, np.sin(th)], [0, 1, 0], [-np.sin(th), 0, np.cos(th)]])
            p = Camera(K, R, [-0.15 * k, 0.02 * k, 0.0], w, h).project(X[j][None])[0]
            co.append([p[0] / w, 1 - p[1] / h])
        tr.markers.foreach_set("co", np.array(co, np.float32).ravel())
    obj = clip.tracking.objects.active
    obj.keyframe_a, obj.keyframe_b = 1, n
    win = bpy.context.window_manager.windows[0]
    area = win.screen.areas[-1]
    area.type = "CLIP_EDITOR"
    space = area.spaces.active
    space.clip = clip
    region = next(r for r in area.regions if r.type == "WINDOW")
    with bpy.context.temp_override(window=win, area=area, region=region, space_data=space):
        assert bpy.ops.clip.solve_camera() == {"FINISHED"}
    assert obj.reconstruction.is_valid
    P, names = tracking.clip_bundles(clip)
    assert P.shape == (24, 3) and names == [f"P{j:02d}" for j in range(24)]
    px, _ = tracking.read_track_markers(clip, np.arange(1, n + 1))
    for rc in obj.reconstruction.cameras:
        M = np.array(rc.matrix, dtype=np.float64)  # camera to reconstruction space, Blender camera axes
        R = (M[:3, :3] @ np.diag([1.0, -1.0, -1.0])).T
        cam = Camera(K, R, -R @ M[:3, 3], w, h)
        np.testing.assert_allclose(cam.project(P), px[rc.frame - 1], atol=0.05)


# --------------------------------------------------------------------------- contours
def test_curve_names():
    cases = {
        "Upper lip": "mouth_upper", "Lower lip": "mouth_lower", "mouth_upper": "mouth_upper",
        "Lip.Lower": "mouth_lower", "eyelid_left_upper": "eyelid_left_upper", "Eyelid.L upper": "eyelid_left_upper",
        "lid_R_bottom": "eyelid_right_lower", "eyelidRightUpper": "eyelid_right_upper",
        "left lower eyelid": "eyelid_left_lower", "Layer": None, "upper": None, "Eyelid upper": None,
        "lip upper lower": None, "Eyelid L R upper": None,
    }
    for k, v in cases.items():
        assert masks.curve_name(k) == v, k


def test_mask_to_pixels_and_bezier(tmp_path, scene):
    clip = make_clip(tmp_path)  # 80 x 60: mask y is scaled by 60/80 about 0.5
    px = masks.mask_to_pixels([[0.5, 0.5], [0.25, 0.8], [1.0, 0.125]], clip)
    # v = 0.8 -> frame v = 0.3 * 80/60 + 0.5 = 0.9 -> y = 6; v = 0.125 -> 0 -> y = 60
    np.testing.assert_allclose(px, [[40, 30], [20, 6], [80, 60]], atol=1e-9)
    # Bezier: handles at thirds give the straight line; a curved segment's midpoint is (P0+3P1+3P2+P3)/8
    co = np.array([[0.0, 0.0], [3.0, 0.0]])
    line = masks.bezier_polyline(co, co - [1, 0], co + [1, 0], False, resolution=4)
    np.testing.assert_allclose(line, [[0, 0], [0.75, 0], [1.5, 0], [2.25, 0], [3, 0]], atol=1e-12)
    left = np.array([[0.0, 0.0], [3.0, 2.0]])
    right = np.array([[0.0, 2.0], [3.0, 0.0]])
    curve = masks.bezier_polyline(co, left, right, False, resolution=2)
    np.testing.assert_allclose(curve[1], (co[0] + 3 * right[0] + 3 * left[1] + co[1]) / 8)
    closed = masks.bezier_polyline(co, co, co, True, resolution=2)
    assert len(closed) == 5 and np.allclose(closed[-1], co[0])


def clip_editor(clip, mask):
    """Turn an area of the (background) window into a Clip editor in mask mode, for mask operators."""
    win = bpy.context.window_manager.windows[0]
    area = win.screen.areas[-1]
    area.type = "CLIP_EDITOR"
    space = area.spaces.active
    space.clip, space.mode, space.mask = clip, "MASK", mask
    region = next(r for r in area.regions if r.type == "WINDOW")
    return dict(window=win, area=area, region=region, space_data=space)


def set_points(spline, co, left=None, right=None):
    for i, p in enumerate(spline.points):
        p.handle_left_type = p.handle_right_type = "FREE"
        p.co = co[i]
        p.handle_left = co[i] if left is None else left[i]
        p.handle_right = co[i] if right is None else right[i]
        p.select = True


def test_mask_polylines_static_and_shape_keyed(tmp_path, scene):
    clip = make_clip(tmp_path)
    mask = bpy.data.masks.new("Roto")
    mask.frame_start, mask.frame_end = 1, 5
    up = mask.layers.new(name="Upper lip")
    sp = up.splines.new()
    sp.points.add(2)  # 3 points
    co = np.array([[0.25, 0.5], [0.5, 0.575], [0.75, 0.5]])
    set_points(sp, co, left=co - [0.05, 0], right=co + [0.05, 0])
    ignored = mask.layers.new(name="Roto garbage")
    ignored.splines.new()
    lid = mask.layers.new(name="Eyelid R lower")
    sp2 = lid.splines.new()
    sp2.points.add(1)
    ctx = clip_editor(clip, mask)
    # animate the eyelid with mask shape keys on frames 1 and 5 (as a rotoscoper does)
    mask.layers.active = lid
    for f, c in ((1, [[0.6, 0.6], [0.7, 0.6]]), (5, [[0.6, 0.7], [0.7, 0.8]])):
        scene.frame_set(f)
        set_points(sp2, c)
        with bpy.context.temp_override(**ctx):
            assert bpy.ops.mask.shape_key_insert() == {"FINISHED"}
    scene.frame_set(3)
    dg = bpy.context.evaluated_depsgraph_get()
    got = masks.mask_polylines(mask, clip, depsgraph=dg, resolution=4)
    assert set(got) == {"mouth_upper", "eyelid_right_lower"}
    (upper,) = got["mouth_upper"]
    assert upper.shape == (2 * 4 + 1, 2)
    s = 80 / 60
    expect_ctrl = np.c_[co[:, 0] * W, (1 - ((co[:, 1] - 0.5) * s + 0.5)) * H]  # (20,30) (40,24) (60,30)
    np.testing.assert_allclose(expect_ctrl, [[20, 30], [40, 24], [60, 30]])
    np.testing.assert_allclose(upper[[0, 4, 8]], expect_ctrl, atol=1e-4)
    mid = (co[0] + 3 * (co[0] + [0.05, 0]) + 3 * (co[1] - [0.05, 0]) + co[1]) / 8
    np.testing.assert_allclose(upper[2], [mid[0] * W, (1 - ((mid[1] - 0.5) * s + 0.5)) * H], atol=1e-4)
    # frame 3 is halfway between the shape keys: y = 0.65 / 0.75 mask -> frame v 0.7 / 0.8333
    (lower,) = got["eyelid_right_lower"]
    np.testing.assert_allclose(lower[[0, -1]], [[48, (1 - (0.15 * s + 0.5)) * H], [56, (1 - (0.2 * s + 0.5)) * H]],
                               atol=1e-3)
    np.testing.assert_allclose(lower[[0, -1]], [[48, 18], [56, 14]], atol=1e-3)
    # a hidden layer is not read
    lid.hide = True
    assert set(masks.mask_polylines(mask, clip, depsgraph=dg)) == {"mouth_upper"}
    lid.hide = False
    # points parented to a track are refused with an explanation
    add_track(clip, "mouth_corner", {1: (0.3, 0.5)})
    p = sp.points[0]
    p.parent.id_type, p.parent.id = "MOVIECLIP", clip
    p.parent.parent, p.parent.sub_parent = "Camera", "mouth_corner"
    with pytest.raises(SketchError, match="parented to track 'mouth_corner'.*shape keys"):
        masks.mask_polylines(mask, clip, depsgraph=dg)


def test_sketch_and_annotation_polylines(tmp_path, scene):
    from facelab_addon.blender.strokes import new_lip_sketch, write_stroke_pixels

    cam_obj = new_camera("Cam")
    scene.camera = cam_obj
    scene.render.resolution_x, scene.render.resolution_y = W, H
    cam = camera_from_blender(scene, cam_obj)
    scene.frame_set(4)
    gp = new_lip_sketch(scene, cam_obj)
    lid = [[10.0, 20.0], [20.0, 18.0], [30.0, 20.0]]
    write_stroke_pixels(gp, "Eyelid L upper", 4, [lid], cam)
    write_stroke_pixels(gp, "Upper lip", 4, [[[30, 40], [40, 38]], [[50, 40], [40.5, 38]]], cam)  # 2nd reversed
    dg = bpy.context.evaluated_depsgraph_get()
    got = masks.sketch_polylines(gp, cam, 4, depsgraph=dg)
    assert set(got) == {"eyelid_left_upper", "mouth_upper"}
    np.testing.assert_allclose(got["eyelid_left_upper"][0], lid, atol=2e-3)
    chained = masks.chain_polylines(got["mouth_upper"])
    np.testing.assert_allclose(chained, [[30, 40], [40, 38], [40.5, 38], [50, 40]], atol=2e-3)
    assert masks.sketch_polylines(gp, cam, 5, depsgraph=dg) == {}  # exact keyframes only...
    assert set(masks.sketch_polylines(gp, cam, 5, depsgraph=dg, hold=True)) == {"eyelid_left_upper", "mouth_upper"}
    # (the scene annotation goes through the same strokes.py helpers, tested in test_camera_strokes.py)


def test_read_curves_per_view(tmp_path, scene):
    pytest.importorskip("facelab_addon.core.solve.contour_loops")
    from facelab_addon.blender.strokes import write_stroke_pixels

    clip = make_clip(tmp_path)
    cam_obj = new_camera("Cam")
    scene.render.resolution_x, scene.render.resolution_y = W, H
    cam = camera_from_blender(scene, cam_obj)
    mask = bpy.data.masks.new("Roto")
    mask.frame_start, mask.frame_end = 2, 3
    sp = mask.layers.new(name="mouth_lower").splines.new()
    sp.points.add(1)
    set_points(sp, [[0.25, 0.5], [0.75, 0.5]])
    gp = bpy.data.objects.new("Lids", compat.grease_pencil_data().new("Lids"))
    scene.collection.objects.link(gp)
    gp.location = cam.center + 0.5 * cam.forward
    write_stroke_pixels(gp, "eyelid_right_upper", 3, [[[10, 10], [20, 12]]], cam)
    views = [tracking.View(cam_obj, clip, mask=mask, sketch=gp)]
    curves, stats = masks.read_curves(scene, views, [cam], [1, 2, 3], resolution=2)
    assert [len(c) for c in curves] == [0, 1, 2]
    assert stats == {"frames_with_curves": 2, "by_name": {"mouth_lower": 2, "eyelid_right_upper": 1}}
    c = {k.name: k for k in curves[2]}
    assert c["mouth_lower"].camera == 0
    np.testing.assert_allclose(c["mouth_lower"].pixels[[0, -1]], [[20, 30], [60, 30]], atol=1e-4)
    np.testing.assert_allclose(c["eyelid_right_upper"].pixels, [[10, 10], [20, 12]], atol=2e-3)
