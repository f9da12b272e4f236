"""Load Plate, headless: an image sequence written here (crops of ``skimage.data.astronaut``) becomes
a Movie Clip behind the scene camera, added beside the artist's own background; the scene takes the
footage's frame range and resolution; a calibrated clip's lens makes the Blender camera project
exactly like the calibration; bad footage is refused with the scene untouched."""

import bpy
import numpy as np
import pytest

from facelab_addon.blender import plate as plate_io
from facelab_addon.blender.camera import camera_from_blender, new_camera_object
from facelab_addon.blender.tracking_io import set_clip_calibration
from facelab_addon.core.capture.camera import Camera
from facelab_addon.core.errors import CameraError
from facelab_addon.pipeline.plate import PlateSettings, load_plate

pytestmark = pytest.mark.blender

W, H, T = 96, 64, 7


@pytest.fixture(scope="module")
def sequence(tmp_path_factory):
    """T PNG frames (W x H, the astronaut's face drifting right), plate_0001.png ..."""
    from PIL import Image
    from skimage.data import astronaut

    img = astronaut()
    d = tmp_path_factory.mktemp("plate")
    for t in range(T):
        crop = img[40:40 + 4 * H:4, 120 + 3 * t:120 + 3 * t + 4 * W:4]
        Image.fromarray(np.ascontiguousarray(crop)).save(d / f"plate_{t + 1:04d}.png")
    return d


def scene_with_camera():
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    cam = Camera.look_at(np.array([0.0, 0.0, 1.0]), np.zeros(3), np.array([0.0, 1.0, 0.0]), 35.0, 36.0, 640, 480)
    new_camera_object(scene, cam)
    scene.render.fps, scene.frame_start, scene.frame_end = 30, 10, 500
    return scene


def test_load_plate_operator_adds_a_background_and_matches_the_scene(addon, sequence):
    scene = scene_with_camera()
    cam = scene.camera.data
    own = bpy.data.images.new("artist's reference", 8, 8)
    bg0 = cam.background_images.new()
    bg0.image = own
    assert bpy.ops.facelab.load_plate(filepath=str(sequence / "plate_0001.png"), frame_start=5) == {"FINISHED"}
    assert "UNDO" in bpy.types.FACELAB_OT_load_plate.bl_options
    assert len(cam.background_images) == 2 and cam.background_images[0].image == own  # the artist's one is kept
    bg = cam.background_images[1]
    clip = bg.clip
    assert bg.source == "MOVIE_CLIP" and clip is not None and cam.show_background_images
    assert tuple(clip.size) == (W, H) and clip.frame_duration == T and clip.source == "SEQUENCE"
    assert (scene.frame_start, scene.frame_end) == (5, 5 + T - 1)
    assert (scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage) == (W, H, 100)
    assert scene.render.fps == 30  # an image sequence has no frame rate: the scene keeps its own
    assert scene.active_clip == clip
    # a second plate is added, never swapped in for the first
    assert bpy.ops.facelab.load_plate(filepath=str(sequence)) == {"FINISHED"}  # a folder: its first image
    assert len(cam.background_images) == 3 and cam.background_images[1].clip == clip


def test_lens_from_a_calibrated_clip_reproduces_the_calibration(addon, sequence):
    scene = scene_with_camera()
    R = scene.camera.matrix_world.copy()
    K = np.array([[130.0, 0.0, 51.5], [0.0, 130.0, 29.0], [0.0, 0.0, 1.0]])  # principal point off-centre
    calib = Camera(K, np.eye(3), np.zeros(3), W, H)
    clip = bpy.data.movieclips.load(str(sequence / "plate_0001.png"))
    assert not plate_io.clip_lens_is_set(clip)  # Blender's 24 mm default: not a lens
    set_clip_calibration(clip, calib, sensor_width=23.5)
    assert plate_io.clip_lens_is_set(clip)
    r = load_plate(scene, settings=PlateSettings(), clip=clip)
    assert r.reused and "lens" in r.changed and r.changed["lens"]["sensor_mm"] == pytest.approx(23.5)
    got = camera_from_blender(scene)
    assert (got.width, got.height) == (W, H)
    np.testing.assert_allclose(got.K, K, atol=1e-3)
    assert np.allclose(np.array(scene.camera.matrix_world), np.array(R))  # the pose is the artist's
    # and through the operator, by the clip's name, with the lens left alone when asked
    scene.camera.data.lens = 77.0
    assert bpy.ops.facelab.load_plate(clip=clip.name, lens_from_clip=False) == {"FINISHED"}
    assert scene.camera.data.lens == pytest.approx(77.0)


def test_an_uncalibrated_clip_leaves_the_lens_and_says_so(addon, sequence):
    scene = scene_with_camera()
    lens = scene.camera.data.lens
    r = load_plate(scene, sequence / "plate_0001.png")
    assert scene.camera.data.lens == lens and "lens" not in r.changed
    assert any("tracking camera is not set" in s for s in r.skipped)
    assert any("image sequence has none" in s for s in r.skipped)


def _state(scene):
    return (len(bpy.data.movieclips), len(scene.camera.data.background_images) if scene.camera else None,
            scene.frame_start, scene.frame_end, scene.render.resolution_x)


@pytest.mark.parametrize("what, message", [
    ("missing", "does not exist; check the path"),
    ("text", "is not footage Blender reads (.txt)"),
    ("empty_dir", "holds no image Blender reads"),
    ("nothing", "No footage given"),
    ("broken", "could not decode any frame"),
])
def test_bad_footage_is_refused_and_the_scene_is_untouched(addon, sequence, tmp_path, what, message):
    scene = scene_with_camera()
    path = {"missing": tmp_path / "plate_0001.png", "text": tmp_path / "notes.txt", "empty_dir": tmp_path,
            "nothing": "", "broken": tmp_path / "clip.mp4"}[what]
    if what == "text":
        path.write_text("not a movie")
    if what == "broken":
        path.write_bytes(b"\0" * 64)
    before = _state(scene)
    with pytest.raises(plate_io.PlateError, match=message.replace("(", r"\(").replace(")", r"\)")):
        load_plate(scene, path)
    assert _state(scene) == before
    with pytest.raises(RuntimeError, match=message.split(" (")[0]):  # the operator reports the same message
        bpy.ops.facelab.load_plate(filepath=str(path))
    assert _state(scene) == before


def test_no_camera_is_refused(addon, sequence):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    with pytest.raises(CameraError, match="add the camera the footage was shot with"):
        load_plate(scene, sequence / "plate_0001.png")
    assert len(bpy.data.movieclips) == 0
    assert not bpy.types.FACELAB_OT_load_plate.poll(bpy.context)


def test_undo_takes_the_plate_back(addon, sequence):
    scene = scene_with_camera()
    bpy.ops.ed.undo_push(message="before")
    assert bpy.ops.facelab.load_plate(filepath=str(sequence / "plate_0001.png")) == {"FINISHED"}
    bpy.ops.ed.undo_push(message="Load Plate")  # headless: the UI would push it
    assert len(bpy.context.scene.camera.data.background_images) == 1 and bpy.context.scene.frame_end == T
    bpy.ops.ed.undo()
    scene = bpy.context.scene
    assert len(scene.camera.data.background_images) == 0
    assert (scene.frame_start, scene.frame_end, scene.render.resolution_x) == (10, 500, 640)
