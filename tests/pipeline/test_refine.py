"""The Refine pipeline without operators: an ICT face with a 2.5 mm inner-lip gap, a camera and a
Grease Pencil sketch of the true lip silhouettes -> ``pipeline.refine.refine`` puts the lips on the
strokes, writes one keyed corrective key and records the training frame; bad input changes nothing."""

import bpy
import numpy as np
import pytest

from facelab_addon.blender.camera import camera_from_blender
from facelab_addon.blender.mesh import evaluated_vertices, mesh_triangles
from facelab_addon.blender.strokes import new_lip_sketch, write_stroke_pixels
from facelab_addon.core.errors import CameraError, SketchError
from facelab_addon.core.geometry.silhouette import contour_distance
from facelab_addon.names import REFINE_PREFIX, TRAIN_MARKER
from facelab_addon.pipeline.refine import RefineResult, RefineSettings, refine

from ..blender.test_refine_operator import FRAME, scene_setup

pytestmark = pytest.mark.blender


def sketched(tmp_path, ict, lower=True):
    s = scene_setup(tmp_path, ict)
    scene = s["scene"]
    gp = new_lip_sketch(scene, scene.camera)
    cam = camera_from_blender(scene)
    write_stroke_pixels(gp, "Upper lip", FRAME, [s["up_px"]], cam)
    if lower:
        write_stroke_pixels(gp, "Lower lip", FRAME, [s["lo_px"]], cam)
    return s, gp, cam


def silhouette_px(X, s, cam):
    F = mesh_triangles(s["obj"].data)
    fm = s["face_mask"]
    return np.r_[contour_distance(X, F, cam, s["up_px"], +1, candidates=fm),
                 contour_distance(X, F, cam, s["lo_px"], -1, candidates=fm)]


def test_refine_puts_the_lips_on_the_sketch(tmp_path, ict, addon):
    s, gp, cam = sketched(tmp_path, ict)
    scene, obj = s["scene"], s["obj"]
    scene.frame_set(FRAME - 3)  # the pipeline goes to the frame itself
    r = refine(scene, obj, FRAME, RefineSettings(), sketch=gp)
    assert isinstance(r, RefineResult) and scene.frame_current == FRAME

    X = evaluated_vertices(obj, bpy.context.evaluated_depsgraph_get())
    assert silhouette_px(s["C"], s, cam).mean() > 4.0  # the injected gap, in pixels
    assert silhouette_px(X, s, cam).mean() < 1.0  # on the strokes
    lip = np.linalg.norm(s["C"] - s["T"], axis=1) > 1e-6
    rms = lambda Y: np.sqrt((np.linalg.norm(Y - s["T"], axis=1)[lip] ** 2).mean())  # noqa: E731
    assert rms(X) < 0.7 * rms(s["C"])  # closer to the truth in 3D
    assert np.abs(X - s["C"])[~s["face_mask"]].max() < 1e-4  # the FL_fixed group stays (0.1 mm, soft constraint)
    assert r.fixed_source == "vertex group 'FL_fixed'" and r.note == ""

    # the result describes the key it wrote: the displacement it reports is the key's
    kb = obj.data.shape_keys.key_blocks[r.shape_key]
    assert r.shape_key == f"{REFINE_PREFIX}{FRAME:04d}" and r.frame == FRAME
    d = np.array([p.co[:] for p in kb.data]) - np.array([p.co[:] for p in obj.data.shape_keys.reference_key.data])
    moved = np.linalg.norm(d, axis=1)
    assert 1000 < int((moved > 1e-6).sum()) <= r.moved_vertices  # float32 key storage drops sub-µm moves
    assert r.max_move == pytest.approx(moved.max(), rel=1e-5)
    assert 0.0005 < r.max_move < 0.005  # about the 1.25 mm per-lip gap, in metres
    # keyed 1 on the frame and 0 on its neighbours; recorded as a training frame with a marker
    vals = {}
    for f in (FRAME - 1, FRAME, FRAME + 1):
        scene.frame_set(f)
        vals[f] = kb.value
    assert vals == {FRAME - 1: 0.0, FRAME: 1.0, FRAME + 1: 0.0}
    tf = obj.facelab.training_frames
    assert [(t.frame, t.shape_key, t.source) for t in tf] == [(FRAME, r.shape_key, "sketch")]
    assert [m.frame for m in scene.timeline_markers if m.name.startswith(TRAIN_MARKER)] == [FRAME]
    # again: a second key, never an overwrite
    assert refine(scene, obj, FRAME, sketch=gp).shape_key == f"{REFINE_PREFIX}{FRAME:04d}.001"


def test_refine_settings_are_the_preferences_defaults():
    from facelab_addon.ui import prefs

    s = RefineSettings()
    assert {k: getattr(s, k) for k in prefs.DEFAULTS} == prefs.DEFAULTS and s.fixed_group == "FL_fixed"


@pytest.mark.slow
def test_refine_bad_input_changes_nothing(tmp_path, ict, addon):
    s, gp, cam = sketched(tmp_path, ict, lower=False)
    scene, obj = s["scene"], s["obj"]
    markers = len(scene.timeline_markers)
    with pytest.raises(SketchError, match="(?i)lower lip"):
        refine(scene, obj, FRAME, sketch=gp)
    with pytest.raises(SketchError, match="no strokes"):
        refine(scene, obj, FRAME - 5, sketch=gp)  # before the sketch's first keyframe
    write_stroke_pixels(gp, "Lower lip", FRAME, [s["lo_px"] + [0, 700]], cam)
    with pytest.raises(SketchError, match="leaves the camera frame"):
        refine(scene, obj, FRAME, sketch=gp)
    scene.camera = None
    with pytest.raises(CameraError, match="camera"):
        refine(scene, obj, FRAME, sketch=gp)
    assert obj.data.shape_keys is None and len(obj.facelab.training_frames) == 0
    assert len(scene.timeline_markers) == markers
    np.testing.assert_allclose(evaluated_vertices(obj, bpy.context.evaluated_depsgraph_get()), s["C"], atol=1e-7)


@pytest.mark.slow
def test_refine_with_regions_moves_only_the_inside_of_fl_lips(tmp_path, ict, addon):
    from facelab_addon.blender.mesh import set_vertex_group
    from facelab_addon.core.lips.regions import auto_regions
    from facelab_addon.names import LIPS_GROUP, MOUTH_GROUP

    s, gp, cam = sketched(tmp_path, ict)
    scene, obj = s["scene"], s["obj"]
    mouth, lips = auto_regions(ict.neutral, s["F"])  # Auto Regions on the rest pose
    set_vertex_group(obj, MOUTH_GROUP, mouth)
    set_vertex_group(obj, LIPS_GROUP, lips)
    r = refine(scene, obj, FRAME, RefineSettings(), sketch=gp)
    assert r.lips_region and r.cameras == [scene.camera.name]
    X = evaluated_vertices(obj, bpy.context.evaluated_depsgraph_get())
    moved = np.linalg.norm(X - s["C"], axis=1)
    assert moved[mouth].max() < 1e-7 and moved[~lips].max() < 1e-7  # FL_mouth and the rest: untouched
    assert moved[lips].max() > 0.0005  # the lips moved (1.25 mm gap per lip)
    assert silhouette_px(X, s, cam).mean() < 1.5
    # without the regions option the same face (the first correction muted) moves beyond FL_lips
    obj.data.shape_keys.key_blocks[r.shape_key].mute = True
    r2 = refine(scene, obj, FRAME, RefineSettings(use_regions=False), sketch=gp)
    kb = obj.data.shape_keys.key_blocks
    d = np.array([p.co[:] for p in kb[r2.shape_key].data]) - np.array([p.co[:] for p in kb[0].data])
    assert not r2.lips_region and np.linalg.norm(d, axis=1)[~lips].max() > 1e-5


@pytest.mark.slow
def test_refine_uses_every_camera_sketched_on_the_frame(tmp_path, ict, addon):
    from facelab_addon.blender.camera import new_camera_object
    from facelab_addon.core.capture.camera import Camera
    from facelab_addon.core.lips.mouth import find_mouth
    from facelab_addon.testing import synthetic as S

    s, gp, cam = sketched(tmp_path, ict)
    scene, obj, T, F = s["scene"], s["obj"], s["T"], s["F"]
    fixed = ~s["face_mask"]
    mouth = find_mouth(T, F, fixed, units_per_mm=0.001)
    e = np.radians(20.0)
    below = Camera.look_at(mouth.center + 0.40 * (np.cos(e) * mouth.forward - np.sin(e) * mouth.up), mouth.center,
                           mouth.up, 50, 36, 1920, 1080)
    main_cam = scene.camera
    cam_b = new_camera_object(scene, below, "Below", make_active=False)
    gp_b = new_lip_sketch(scene, cam_b)
    assert gp_b != gp
    cb = camera_from_blender(scene, cam_b)
    up_b, lo_b = S.lip_contours(T, F, cb, mouth=mouth)
    write_stroke_pixels(gp_b, "Upper lip", FRAME, [up_b], cb)
    write_stroke_pixels(gp_b, "Lower lip", FRAME, [lo_b], cb)
    scene.camera = main_cam
    r = refine(scene, obj, FRAME, RefineSettings(), sketch=gp)
    assert r.cameras == [main_cam.name, "Below"]
    X = evaluated_vertices(obj, bpy.context.evaluated_depsgraph_get())
    assert silhouette_px(X, s, cam).mean() < 1.0  # on the sketch in the main view
    fm = s["face_mask"]
    dist_b = np.r_[contour_distance(X, F, cb, up_b, +1, candidates=fm), contour_distance(X, F, cb, lo_b, -1, candidates=fm)]
    assert np.median(dist_b) < 1.5  # and in the second one
    # one camera only: the single-view route
    r1 = refine(scene, obj, FRAME, RefineSettings(all_views=False), sketch=gp)
    assert r1.cameras == [main_cam.name]
