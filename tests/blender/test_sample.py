"""Load Sample, headless, and the whole route on it: the shipped sample builds a new scene (face with
its captured performance, camera, plate) without the ICT-FaceKit checkout; Auto Regions, Refine
Lips on a few sketched frames (the sketch traces the truth's inner-lip silhouettes, as an artist
traces the plate) and Propagate bring the held-out frames' inner lips to the truth."""

import bpy
import numpy as np
import pytest

from facelab_addon.blender.caches import evaluate_frames
from facelab_addon.blender.camera import camera_from_blender
from facelab_addon.blender.sample import ERROR_KEY, read_sample
from facelab_addon.blender.strokes import write_stroke_pixels
from facelab_addon.core.capture.camera import Camera
from facelab_addon.names import LIPS_GROUP, MOUTH_GROUP, PREFIX

pytestmark = [pytest.mark.blender, pytest.mark.slow]

N_TRAIN = 8


def _drawable(upper, lower, tol_px=2.0):
    """An artist would draw these truth contours as they are: the upper one above the lower one (where
    the truth's silhouettes cross, an artist draws where the lips meet, which the truth does not give)."""
    from facelab_addon.core.geometry.polyline import y_at

    ly = y_at(upper[:, 0], lower)
    ok = np.isfinite(ly)
    return ok.any() and bool((ly[ok] >= upper[ok, 1] - tol_px).all())


def _triangles(data):
    pv, po = data.poly_verts, data.poly_offsets
    return np.array([[pv[s], pv[s + k], pv[s + k + 1]] for s, e in zip(po[:-1], po[1:]) for k in range(1, e - s - 1)])


@pytest.fixture(scope="module")
def sample(addon):
    data = read_sample()
    bpy.ops.wm.read_factory_settings(use_empty=True)
    before = set(bpy.data.scenes)
    assert bpy.ops.facelab.load_sample() == {"FINISHED"}
    new = [s for s in bpy.data.scenes if s not in before]
    assert len(new) == 1
    return data, new[0]


def test_load_sample_builds_the_shot_in_a_new_scene(sample, monkeypatch):
    data, scene = sample
    assert "UNDO" in bpy.types.FACELAB_OT_load_sample.bl_options
    assert bpy.context.scene == scene and scene.name.startswith("FaceLab Sample")
    face = scene.facelab.face
    assert face is not None and bpy.context.view_layer.objects.active == face
    assert len(face.data.vertices) == len(data.vertices) == 4737
    keys = face.data.shape_keys.key_blocks
    assert [k.name for k in keys][1:] == [*data.expression_names, ERROR_KEY]
    assert not [k for k in keys if k.name.startswith(PREFIX)]  # FaceLab has not touched it yet
    assert (scene.frame_start, scene.frame_end) == (1, 48) and scene.render.fps == 24
    # the camera is the sample's, to the pixel
    got = camera_from_blender(scene)
    np.testing.assert_allclose(got.K, data.camera.K, atol=1e-6 * data.camera.K[0, 0])
    X = data.vertices[data.inner_lip_loop]
    np.testing.assert_allclose(got.project(X), data.camera.project(X), atol=1e-2)
    # the plate is behind it and covers the performance
    bg = scene.camera.data.background_images
    assert len(bg) == 1 and bg[0].source == "MOVIE_CLIP" and bg[0].clip.frame_duration == 48
    assert tuple(bg[0].clip.size) == (data.camera.width, data.camera.height)
    # the performance plays: frame 20 of the face is the capture (truth + lip error)
    X20 = evaluate_frames(face, [20], mute_shape_keys_prefix=())[0]
    np.testing.assert_allclose(X20, data.captured()[19], atol=2e-6)
    assert np.linalg.norm(data.captured() - data.truth(), axis=2).max() > 0.001  # a visible lip error (> 1 mm)


def test_load_sample_needs_neither_network_nor_ict(sample, monkeypatch, tmp_path):
    monkeypatch.setenv("FACELAB_ICT_DIR", str(tmp_path / "no-ict-here"))
    monkeypatch.setattr("socket.socket", None)  # any network use would fail
    n = len(bpy.data.scenes)
    assert bpy.ops.facelab.load_sample(plate=False) == {"FINISHED"}
    assert len(bpy.data.scenes) == n + 1 and not bpy.context.scene.camera.data.background_images
    bpy.context.window.scene = sample[1]


def test_auto_regions_refine_propagate_on_the_sample_close_the_lips(sample):
    from facelab_addon.blender.mesh import vertex_group_mask
    from facelab_addon.core.lips.mouth import find_mouth
    from facelab_addon.core.lips.regions import faces_in_region
    from facelab_addon.core.lips.suggest import suggest_frames
    from facelab_addon.testing import synthetic as syn

    data, scene = sample
    bpy.context.window.scene = scene
    face = scene.facelab.face
    F = _triangles(data)
    truth, captured = data.truth(), data.captured()
    frames = data.frames

    assert bpy.ops.facelab.auto_regions() == {"FINISHED"}
    assert face.vertex_groups.get(MOUTH_GROUP) and face.vertex_groups.get(LIPS_GROUP)

    # the artist traces the plate (the truth) on frames FaceLab would suggest
    mouth = find_mouth(data.vertices, F, None, near=data.vertices[data.inner_lip_loop].mean(0),
                       units_per_mm=0.001)
    cam = Camera(data.camera.K, data.camera.R, data.camera.t, data.camera.width, data.camera.height)
    bcam = camera_from_blender(scene)
    mouth_faces = faces_in_region(F, vertex_group_mask(face, MOUTH_GROUP))
    ranked = [int(frames[i]) for i in suggest_frames(captured, 3 * N_TRAIN, rest_vertices=data.vertices, faces=F,
                                                     mouth_faces=mouth_faces)]
    train = []
    for f in ranked:
        if len(train) == N_TRAIN:
            break
        try:
            upper, lower = syn.lip_contours(truth[f - 1], F, cam, mouth=mouth)
        except Exception:
            continue
        if not _drawable(upper, lower):
            continue
        scene.frame_set(f)
        bpy.context.view_layer.objects.active = face
        assert bpy.ops.facelab.new_lip_sketch() == {"FINISHED"}
        write_stroke_pixels(scene.facelab.sketch, "Upper lip", f, [upper], bcam)
        write_stroke_pixels(scene.facelab.sketch, "Lower lip", f, [lower], bcam)
        bpy.context.view_layer.objects.active = face
        assert bpy.ops.facelab.refine_lips() == {"FINISHED"}
        train.append(f)
    assert len(train) == N_TRAIN
    bpy.context.view_layer.objects.active = face
    assert bpy.ops.facelab.propagate() == {"FINISHED"}

    result = evaluate_frames(face, frames, mute_shape_keys_prefix=())
    lips = np.linalg.norm(data.capture_error, axis=1) > 2e-4  # where the capture is off by more than 0.2 mm
    held = np.setdiff1d(frames, train) - frames[0]

    def rms_mm(X, idx=held):
        return 1e3 * np.sqrt((np.linalg.norm(X[idx] - truth[idx], axis=2)[:, lips] ** 2).mean())

    before, after = rms_mm(captured), rms_mm(result)
    tr = np.array(train) - frames[0]
    train_before, train_after = rms_mm(captured, tr), rms_mm(result, tr)
    print(f"inner-lip RMS vs truth: sketched frames {train_before:.3f} -> {train_after:.3f} mm, "
          f"held-out frames {before:.3f} -> {after:.3f} mm")
    assert train_after < 0.35 * train_before, (train_before, train_after)  # Refine Lips matched the sketches
    assert before > 0.3, before
    assert after < 0.65 * before, (before, after)  # measured: 0.49 -> 0.28 mm (8 sketched frames of 48)


def test_undo_takes_the_sample_back(addon):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.ed.undo_push(message="before")
    assert bpy.ops.facelab.load_sample(plate=False) == {"FINISHED"}
    bpy.ops.ed.undo_push(message="Load Sample")  # headless: the UI would push it
    assert len(bpy.data.scenes) == 2 and "Face" in bpy.data.objects
    bpy.ops.ed.undo()
    assert len(bpy.data.scenes) == 1 and "Face" not in bpy.data.objects
