"""The Propagate pipeline without operators: an animated ICT capture with a systematic inner-lip
error, three frames corrected by the artist -> ``pipeline.propagate.propagate`` reproduces the
corrections on the training frames, predicts the held-out frames exactly as an independently fitted
regressor, removes most of the error, and refits from the scene on every run. Corrected OBJs over a
Mesh Cache (``add_corrected_frame``) show exactly on their frame."""

import bpy
import numpy as np
import pytest

from facelab_addon.blender import caches
from facelab_addon.blender.mesh import mesh_triangles, vertex_group_mask
from facelab_addon.blender.shapekeys import (
    add_corrective_key,
    find_fcurve,
    key_spike,
    rest_vertices,
)
from facelab_addon.core.errors import FaceLabError, RegionError
from facelab_addon.core.lips.regressor import LipRegressor
from facelab_addon.core.lips.regions import faces_in_region
from facelab_addon.names import (
    CORRECTED_PREFIX,
    EXTRAPOLATION_PROP,
    LIPS_GROUP,
    MOUTH_GROUP,
    PROPAGATE_PREFIX,
    SUGGEST_MARKER,
    TRAIN_MARKER,
)
from facelab_addon.pipeline.propagate import PropagateSettings, propagate, propagate_steps, training_input
from facelab_addon.pipeline.regions import RegionSettings, auto_regions
from facelab_addon.pipeline.training import (
    add_corrected_frame,
    record_training_frame,
    remove_training_frame,
    training_frames,
)

from ..blender.test_propagate_operator import FRAMES, SCALE, TRAIN, build

pytestmark = pytest.mark.blender

HELD = [2, 11, 24, 37]

#: The paper's maps, undamped: what the core regressor these tests compare with computes by default.
PAPER = dict(ridge="none", damping=False)


def corrected_scene(ict, train=TRAIN, keyed=False, lip_width=None):
    """The capture, Auto Regions, and the artist's sculpted corrections on ``train`` (recorded): sculpted in
    place (the capture of those frames unknown), or with ``keyed`` as FaceLab corrective keys recorded with the
    frame, as Refine Lips and Add Corrected Frame write them (the capture known)."""
    scene, obj, err, cap_w = build(ict)
    auto_regions(obj, RegionSettings(lip_width=lip_width) if lip_width else None)
    for f in train:
        scene.frame_set(f)
        kb = add_corrective_key(obj, f"FL_Refine_{f:04d}" if keyed else f"Sculpt_{f}",
                                -cap_w[np.searchsorted(FRAMES, f)] * err)
        key_spike(kb, f)
        record_training_frame(scene, obj, f, kb.name if keyed else "", "sketch" if keyed else "sculpt")
    return scene, obj, err, cap_w


def independent_prediction(obj, train, frames, model="auto"):
    """LipRegressor fitted here on ``train`` (corrected frames read with the propagated keys muted); for
    "auto" the shot (all of FRAMES: fewer than Propagate's 64-frame sample) sets the blend."""
    tris = mesh_triangles(obj.data)
    reg = LipRegressor(rest_vertices(obj), tris, faces_in_region(tris, vertex_group_mask(obj, MOUTH_GROUP)),
                       faces_in_region(tris, vertex_group_mask(obj, LIPS_GROUP)), model=model)
    corrected = caches.evaluate_frames(obj, train, mute_shape_keys_prefix=(PROPAGATE_PREFIX,))
    captured_train = caches.evaluate_frames(obj, train, mute_shape_keys_prefix=("FL_",)).astype(np.float64)
    shot = caches.evaluate_frames(obj, FRAMES, mute_shape_keys_prefix=("FL_",))
    reg.fit(training_input(captured_train, corrected, reg.interior_vertices),  # the mouth input: the capture
            captured=captured_train, shot=shot)
    captured = caches.evaluate_frames(obj, frames, mute_shape_keys_prefix=("FL_",))
    return reg.predict(captured.astype(np.float64)), reg


def prop_keys(obj):
    return [kb.name for kb in obj.data.shape_keys.key_blocks if kb.name.startswith(PROPAGATE_PREFIX)]


def test_propagate_reproduces_the_training_corrections_and_predicts(ict, addon):
    scene, obj, err, cap_w = corrected_scene(ict)
    corrected = caches.evaluate_frames(obj, TRAIN, mute_shape_keys_prefix=(PROPAGATE_PREFIX,))

    r = propagate(scene, obj, FRAMES, PropagateSettings(suggestions=2, **PAPER))
    assert r.keys == prop_keys(obj) and 1 <= r.rank <= 10
    assert r.training == TRAIN and list(r.frames) == list(FRAMES) and r.note == ""
    # training frames show exactly the artist's correction (the propagated correction is zero there)
    np.testing.assert_allclose(caches.evaluate_frames(obj, TRAIN, mute_shape_keys_prefix=()), corrected, atol=1e-7)
    # held-out frames: the regressor's prediction, within the 0.01 mm compression tolerance (+ float32)
    got = caches.evaluate_frames(obj, HELD, mute_shape_keys_prefix=())
    assert np.abs(got - independent_prediction(obj, TRAIN, HELD, "whole")[0]).max() < 1e-5 + 1e-6
    # sculpted in place, the training frames' capture is unknown: "auto" is the whole-motion model, and says so
    assert r.whole_weight == 1.0 and "sculpted in place" in r.model
    # and closer to the truth (the capture minus the injected error) than the capture
    i = np.searchsorted(FRAMES, HELD)
    captured = caches.evaluate_frames(obj, HELD, mute_shape_keys_prefix=("FL_",))
    truth = captured - cap_w[i, None, None] * err
    lips = vertex_group_mask(obj, LIPS_GROUP)
    e = lambda X: np.linalg.norm(X - truth, axis=2)[:, lips].mean()  # noqa: E731
    assert e(got) < 0.5 * e(captured), (e(captured), e(got))
    # the extrapolation score it returns is the one keyed on the object; ~0 on training frames
    fc = find_fcurve(obj, f'["{EXTRAPOLATION_PROP}"]')
    keyed = np.array([fc.evaluate(f) for f in FRAMES])
    np.testing.assert_array_equal(keyed, r.extrapolation.astype(np.float32))
    assert np.abs(r.extrapolation[np.searchsorted(FRAMES, TRAIN)]).max() < 1e-3
    # the suggested frames are the markers, never a training frame
    markers = [m.frame for m in scene.timeline_markers if m.name.startswith(SUGGEST_MARKER)]
    assert len(r.suggested) == 2 and sorted(markers) == sorted(r.suggested) and not set(r.suggested) & set(TRAIN)


@pytest.mark.slow
def test_auto_model_from_three_frames_on_a_wide_lip_band(ict, addon):
    """Three corrected frames recorded with their keys (as Refine Lips writes them) on a 0.2 mouth-width lip
    band: the whole-motion model cannot learn the band's expression motion from 3 frames (92 % of the capture's
    error left), the correction model can (5 %); "auto" picks it from the training frames and the shot (6 %),
    keeps every training correction exactly (extrapolation 0 there), matches the core regressor, and reports
    the blend. Model "Correction" is refused, with the way out, when a frame was sculpted in place."""
    scene, obj, err, cap_w = corrected_scene(ict, keyed=True, lip_width=0.2)
    corrected = caches.evaluate_frames(obj, TRAIN, mute_shape_keys_prefix=(PROPAGATE_PREFIX,))
    held = [f for f in FRAMES if f not in TRAIN]
    i = np.searchsorted(FRAMES, held)
    captured = caches.evaluate_frames(obj, held, mute_shape_keys_prefix=("FL_",))
    truth = captured - cap_w[i, None, None] * err
    lips = vertex_group_mask(obj, LIPS_GROUP)
    e0 = np.linalg.norm(captured - truth, axis=2)[:, lips].mean()
    e = lambda X: np.linalg.norm(X - truth, axis=2)[:, lips].mean() / e0  # noqa: E731
    got = {}
    for model in ("whole", "auto"):
        r = propagate(scene, obj, FRAMES, PropagateSettings(suggestions=0, model=model, **PAPER))
        got[model] = caches.evaluate_frames(obj, held, mute_shape_keys_prefix=())
        np.testing.assert_allclose(caches.evaluate_frames(obj, TRAIN, mute_shape_keys_prefix=()), corrected, atol=1e-7)
        assert np.abs(r.extrapolation[np.searchsorted(FRAMES, TRAIN)]).max() < 1e-3
    assert e(got["whole"]) > 0.8, e(got["whole"])
    assert e(got["auto"]) < 0.1, e(got["auto"])
    assert r.model.startswith("auto: ") and r.whole_weight < 0.1, (r.model, r.whole_weight)
    expect, reg = independent_prediction(obj, TRAIN, held, "auto")
    assert reg.whole_weight == pytest.approx(r.whole_weight, abs=1e-5)  # the shot read as float32 there
    assert np.abs(got["auto"] - expect).max() < 1e-5 + 1e-6
    # a frame sculpted in place has no known capture: "Correction" is refused before anything changes
    key_spike(add_corrective_key(obj, "Sculpt_24", -cap_w[np.searchsorted(FRAMES, 24)] * err), 24)
    record_training_frame(scene, obj, 24, "", "sculpt")
    with pytest.raises(FaceLabError, match=r"sculpted in place.*\[24\].*Whole Motion|\[24\].*sculpted in place"):
        propagate_steps(scene, obj, FRAMES, PropagateSettings(model="correction"))


@pytest.mark.slow
def test_propagate_refits_from_the_scene_every_run(ict, addon):
    """Adding or removing a training frame gives the model fitted on exactly the frames now recorded."""
    scene, obj, err, cap_w = corrected_scene(ict)
    propagate(scene, obj, FRAMES, PropagateSettings(suggestions=0, **PAPER))
    f = 24
    scene.frame_set(f)
    key_spike(add_corrective_key(obj, f"Sculpt_{f}", -cap_w[np.searchsorted(FRAMES, f)] * err), f)
    record_training_frame(scene, obj, f, "", "sculpt")
    r = propagate(scene, obj, FRAMES, PropagateSettings(suggestions=0, **PAPER))
    assert r.training == sorted(TRAIN + [f]) and r.keys == prop_keys(obj)
    held = [2, 11, 37]
    got = caches.evaluate_frames(obj, held, mute_shape_keys_prefix=())
    assert np.abs(got - independent_prediction(obj, r.training, held, "whole")[0]).max() < 1e-5 + 1e-6

    # remove frame 5 from the list: its marker goes, and the model no longer learns from it
    i = [t.frame for t in obj.facelab.training_frames].index(5)
    assert remove_training_frame(scene, obj, i) == (5, "")
    assert 5 not in [m.frame for m in scene.timeline_markers if m.name.startswith(TRAIN_MARKER)]
    assert training_frames(obj) == [18, 24, 31]
    r = propagate(scene, obj, FRAMES, PropagateSettings(suggestions=0, **PAPER))
    assert r.training == [18, 24, 31]
    got = caches.evaluate_frames(obj, held, mute_shape_keys_prefix=())
    assert np.abs(got - independent_prediction(obj, r.training, held, "whole")[0]).max() < 1e-5 + 1e-6
    assert not any("." in k for k in prop_keys(obj))  # replaced, never duplicated


def test_propagate_refuses_bad_input_before_any_step(ict, addon):
    scene, obj, err, cap_w = build(ict)
    with pytest.raises(RegionError, match=MOUTH_GROUP):
        propagate_steps(scene, obj, FRAMES)  # raised by the call itself, before a step runs
    auto_regions(obj)
    with pytest.raises(FaceLabError, match="No training frame"):
        propagate_steps(scene, obj, FRAMES)
    record_training_frame(scene, obj, 31, "", "sculpt")
    with pytest.raises(FaceLabError, match="outside the range"):
        propagate_steps(scene, obj, np.arange(1, 21))
    # a sketch's training frame whose key was deleted does not count
    obj.facelab.training_frames[0].source, obj.facelab.training_frames[0].shape_key = "sketch", "FL_Refine_0031"
    assert training_frames(obj) == []
    assert obj.data.shape_keys is not None and not prop_keys(obj)
    assert not any(m.name.startswith(SUGGEST_MARKER) for m in scene.timeline_markers)


def pc2_capture_face(ict, tmp_path, n_frames=16):
    """The first ``n_frames`` of the keyed capture of ``build`` baked to a PC2 and played by a Mesh Cache
    (Overwrite) on a fresh ICT face in a new scene (frames 1..n).

    Returns a namespace: ``scene``, ``face``, ``md`` (the modifier), ``frames`` (n,) of the source
    animation, ``capture`` (n,V,3) as baked, ``truth`` (n,V,3) the capture without its error, ``pc2``
    (the file)."""
    from types import SimpleNamespace

    from facelab_addon.blender.scene import new_mesh_object
    from facelab_addon.core.capture.pointcache_writer import write_pc2

    scene, obj, err, cap_w = build(ict)
    frames = FRAMES[:n_frames]
    capture = caches.evaluate_frames(obj, frames, mute_shape_keys_prefix=())
    truth = caches.evaluate_frames(obj, frames, mute_shape_keys_prefix=("CaptureError",))
    pc2 = write_pc2(tmp_path / "capture.pc2", capture, start=1.0)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 1, n_frames
    face = new_mesh_object("Face", ict.neutral * SCALE, poly_verts=ict.poly_verts, poly_offsets=ict.poly_offsets)
    md = face.modifiers.new("Capture", "MESH_CACHE")
    md.cache_format, md.filepath, md.frame_start = "PC2", str(pc2), 1.0
    bpy.context.view_layer.objects.active = face
    return SimpleNamespace(scene=scene, face=face, md=md, frames=frames, capture=capture, truth=truth, pc2=pc2)


@pytest.mark.slow
def test_corrected_frame_over_a_mesh_cache(ict, addon, tmp_path):
    """A corrected face (an OBJ's vertices) on frame 9 of a PC2 capture: the cache is switched to
    Integrate, the key is mapped through the cache surface, and frame 9 shows the corrected face."""
    cap = pc2_capture_face(ict, tmp_path)
    scene, face, md, capture, truth = cap.scene, cap.face, cap.md, cap.capture, cap.truth
    assert md.deform_mode == "OVERWRITE"

    c = add_corrected_frame(scene, face, 9, truth[8])
    assert md.deform_mode == "INTEGRATE" and c.shape_key == f"{CORRECTED_PREFIX}0009"
    got = caches.evaluate_frames(face, [8, 9, 10], mute_shape_keys_prefix=())
    assert np.abs(got[1] - truth[8]).max() < 1e-5  # the corrected face, through the cache surface
    np.testing.assert_allclose(got[[0, 2]], capture[[7, 9]], atol=1e-6)  # neighbours: the capture
    assert c.max_offset == pytest.approx(np.linalg.norm(truth[8] - capture[8], axis=1).max(), rel=0.05)
    assert [(t.frame, t.shape_key, t.source) for t in face.facelab.training_frames] == [(9, c.shape_key, "sculpt")]
    with pytest.raises(FaceLabError, match="vertices"):
        add_corrected_frame(scene, face, 3, truth[2][:-1])
