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
