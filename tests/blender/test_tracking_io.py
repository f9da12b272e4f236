"""Headless: marker pixels -> plates + Movie Clip with tracks (tracking_io) -> read back by blender/tracking.py."""

import bpy
import numpy as np
import pytest

from facelab_addon.blender.camera import apply_camera_to_blender
from facelab_addon.blender.tracking import View, clip_intrinsics, read_track_markers, read_views
from facelab_addon.blender.tracking_io import add_tracks, clip_from_pixels, write_dot_plates
from facelab_addon.core.capture.camera import Camera
from facelab_addon.core.errors import CameraError, FaceLabError

pytestmark = pytest.mark.blender

W, H, T, M = 320, 240, 4, 7


def _setup(tmp_path):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    rng = np.random.default_rng(1)
    cam = Camera.look_at([0.05, 0.02, 0.4], [0.0, 0.0, 0.0], [0.0, 1.0, 0.0], 30.0, 36.0, W, H)
    X = rng.uniform(-0.05, 0.05, (T, M, 3))
    px = np.stack([cam.project(X[t]) for t in range(T)])
    px[2, 3] = np.nan  # untracked on one frame
    return cam, px


def test_plates_clip_and_tracks_round_trip(tmp_path):
    cam, px = _setup(tmp_path)
    first = write_dot_plates(tmp_path / "plates", px, (W, H), prefix="cam", radius=3)
    assert first.name == "cam_0001.png" and len(list((tmp_path / "plates").glob("cam_*.png"))) == T
    from PIL import Image

    img = np.asarray(Image.open(tmp_path / "plates" / "cam_0002.png"))
    assert img.shape == (H, W, 3)
    x, y = np.round(px[1, 0]).astype(int)
    assert (img[y, x] == 20).all()  # a dot under the marker
    assert (img[0, 0] == [92, 92, 96]).all()  # background elsewhere (the corner is far from every marker)
    assert np.isfinite(px[:, :, 0]).all(axis=1).sum() == T - 1

    scene = bpy.context.scene
    names = [f"T{j}" for j in range(M)]
    clip = clip_from_pixels(first, px, cam, names=names, scene_frame_start=10, name="Helmet")
    assert clip.name == "Helmet" and tuple(clip.size) == (W, H) and clip.frame_start == 10
    K, w, h = clip_intrinsics(clip)
    np.testing.assert_allclose(K, cam.K, rtol=1e-5, atol=1e-3)
    # FaceLab's reader gets the pixels back on the scene frames 10.. (float32 marker storage)
    got, got_names = read_track_markers(clip, np.arange(10, 10 + T), names=names)
    assert got_names == names
    assert np.isnan(got[2, 3]).all()
    ok = np.isfinite(px)
    np.testing.assert_allclose(got[ok], px[ok], atol=2e-3)
    # and the solve's view reader gives the same camera (pose from the camera object, K from the clip)
    cam_obj = bpy.data.objects.new("Cam", bpy.data.cameras.new("Cam"))
    scene.collection.objects.link(cam_obj)
    apply_camera_to_blender(cam, cam_obj, scene)
    vd = read_views(scene, [View(cam_obj, clip)], np.arange(10, 10 + T))
    c = vd.cameras[0]
    np.testing.assert_allclose(c.K, cam.K, rtol=1e-5, atol=1e-3)
    np.testing.assert_allclose(c.R, cam.R, atol=1e-5)
    np.testing.assert_allclose(c.t, cam.t, atol=1e-6)
    np.testing.assert_allclose(vd.markers[0, 0], px[0], atol=2e-3)


def test_bad_input(tmp_path):
    cam, px = _setup(tmp_path)
    first = write_dot_plates(tmp_path / "p", px, (W, H))
    with pytest.raises(FaceLabError, match=r"\(frames, markers, 2\)"):
        clip_from_pixels(first, px[..., 0], cam)
    with pytest.raises(FaceLabError, match="does not exist"):
        clip_from_pixels(tmp_path / "nope_0001.png", px, cam)
    with pytest.raises(FaceLabError, match="has 4 frames but the tracks have 6"):
        clip_from_pixels(first, np.concatenate([px, px[:2]]), cam)
    small = Camera.look_at([0.0, 0.0, 0.4], [0.0, 0.0, 0.0], [0.0, 1.0, 0.0], 30.0, 36.0, W // 2, H // 2)
    with pytest.raises(CameraError, match="is 320x240 px but the camera's image is 160x120"):
        clip_from_pixels(first, px, small)
    clip = bpy.data.movieclips.load(str(first))
    with pytest.raises(FaceLabError, match="2 track names for 7 markers"):
        add_tracks(clip, px, names=["a", "b"])
