"""Propagate on the ICT face (issue 13, part C): an artist's key named like FaceLab's survives every
run, a negative start frame is honoured, a cancel (or a failure) on a Mesh Cache puts the modifier
back in Overwrite, and a broken frame is named by its scene frame, not by a list index."""

import bpy
import numpy as np
import pytest

from facelab_addon.blender import caches
from facelab_addon.blender.ownership import owned_keys
from facelab_addon.blender.shapekeys import add_corrective_key, find_fcurve, key_spike
from facelab_addon.core.errors import MeshError
from facelab_addon.names import EXTRAPOLATION_PROP, OWNED_KEYS_PROP, PROPAGATE_PREFIX
from facelab_addon.pipeline import propagate as propagate_module
from facelab_addon.pipeline.propagate import propagate, propagate_steps
from facelab_addon.pipeline.regions import auto_regions
from facelab_addon.pipeline.steps import StepJob
from facelab_addon.pipeline.training import record_training_frame

from .test_propagate_operator import FRAMES, SCALE

pytestmark = pytest.mark.blender


def corrected(ict):
    """``corrected_scene`` of the pipeline tests with the face as the active object (for the operators)."""
    from ..pipeline.test_propagate import corrected_scene

    scene, obj, err, _ = corrected_scene(ict)
    bpy.context.view_layer.objects.active = obj
    return scene, obj, err


def coords(obj, name):
    c = np.empty(len(obj.data.vertices) * 3, np.float32)
    obj.data.shape_keys.key_blocks[name].data.foreach_get("co", c)
    return c


@pytest.mark.slow
def test_artist_key_named_like_facelabs_survives_propagate(ict, addon):
    scene, obj, err = corrected(ict)
    fix = obj.shape_key_add(name="FL_Prop_MyFix", from_mix=False)  # the artist's own, in the Shape Keys panel
    c = coords(obj, "FL_Prop_MyFix")
    c[:30] += 0.001
    fix.data.foreach_set("co", c)
    assert "FL_Prop_MyFix" not in owned_keys(obj)
    for _ in range(2):  # the second run replaces FaceLab's keys, never the artist's
        assert bpy.ops.facelab.propagate(suggestions=0) == {"FINISHED"}
        ours = owned_keys(obj, PROPAGATE_PREFIX)
        assert ours and all(n.startswith("FL_Prop_") and n[8:].isdigit() for n in ours)
        np.testing.assert_array_equal(coords(obj, "FL_Prop_MyFix"), c)
    names = obj.data.shape_keys.key_blocks.keys()
    assert sorted(n for n in names if n.startswith(PROPAGATE_PREFIX)) == sorted(ours + ["FL_Prop_MyFix"])
    assert set(ours) <= set(obj.data.shape_keys[OWNED_KEYS_PROP])


def test_negative_start_frame_is_honoured(ict, addon):
    scene, obj, err = corrected(ict)
    assert bpy.ops.facelab.propagate(frame_start=-4, frame_end=int(FRAMES[-1]), suggestions=0) == {"FINISHED"}
    fc = find_fcurve(obj, f'["{EXTRAPOLATION_PROP}"]')
    keyed = [kp.co[0] for kp in fc.keyframe_points]
    assert keyed[0] == -4 and keyed[-1] == FRAMES[-1] and len(keyed) == len(FRAMES) + 5


@pytest.mark.slow
def test_broken_frame_is_named_by_its_scene_frame(ict, addon, monkeypatch):
    scene, obj, err = corrected(ict)
    read = propagate_module.CaptureReader.read  # Propagate streams the capture through a CaptureReader

    def nan_on_frame_12(reader, frames):
        X = read(reader, frames)
        X[np.asarray(frames) == 12] = np.nan
        return X

    monkeypatch.setattr(propagate_module.CaptureReader, "read", nan_on_frame_12)
    keys_before = list(obj.data.shape_keys.key_blocks.keys())
    with pytest.raises(MeshError, match=r"captured face has NaN or infinite coordinates on frame 12;"):
        propagate(scene, obj, FRAMES)
    assert list(obj.data.shape_keys.key_blocks.keys()) == keys_before  # nothing written


@pytest.mark.slow
def test_cancel_and_failure_on_a_mesh_cache_leave_the_modifier_as_it_was(ict, addon, tmp_path, monkeypatch):
    from ..pipeline.test_propagate import pc2_capture_face

    cap = pc2_capture_face(ict, tmp_path)
    scene, face, md, frames, capture, pc2 = cap.scene, cap.face, cap.md, cap.frames, cap.capture, cap.pc2
    auto_regions(face)
    record_training_frame(scene, face, 9, "", "sculpt")
    assert md.deform_mode == "OVERWRITE"

    job = StepJob(propagate_steps(scene, face, frames))  # what the modal operator drives
    for _ in range(3):
        assert job.step()
    assert md.deform_mode == "INTEGRATE"  # switched on the first step, so keys would show
    job.cancel()  # Esc
    assert md.deform_mode == "OVERWRITE" and [m.name for m in face.modifiers] == ["Capture"]
    assert not face.data.shape_keys or not owned_keys(face, PROPAGATE_PREFIX)

    def fails(reader, fr):
        raise MeshError("cache broke half way")

    steps = propagate_steps(scene, face, frames)
    next(steps)
    monkeypatch.setattr(propagate_module.CaptureReader, "read", fails)
    with pytest.raises(MeshError, match="half way"):
        for _ in steps:
            pass
    assert md.deform_mode == "OVERWRITE" and md.filepath == str(pc2) and md.show_viewport
    np.testing.assert_allclose(caches.evaluate_frames(face, [5], mute_shape_keys_prefix=())[0], capture[4],
                               atol=1e-6)  # the capture plays as before


@pytest.mark.slow
def test_a_neutral_training_frame_is_refused_naming_its_scene_frame(ict, addon):
    """The issue's case 1 through the operator: a lip fix sculpted on a still, neutral face as the only
    training frame used to move the lips by kilometres on other frames; now Propagate refuses, names the
    scene frame and says what to do, and writes nothing."""
    from facelab_addon.testing.scenes import build_ict_face_scene

    from .test_propagate_operator import EXPR, lip_capture_error

    fs = build_ict_face_scene(ict, EXPR, weights=np.zeros((len(FRAMES), len(EXPR))), frames=FRAMES, scale=SCALE)
    scene, obj = fs.scene, fs.obj
    auto_regions(obj)
    scene.frame_set(12)
    key_spike(add_corrective_key(obj, "Sculpt_12", 0.3 * lip_capture_error(ict)), 12)
    record_training_frame(scene, obj, 12, "", "sculpt")
    bpy.context.view_layer.objects.active = obj
    before = obj.data.shape_keys.key_blocks.keys()
    with pytest.raises(RuntimeError, match=r"do not move the mouth.*frame 12.*Add corrected frames where the mouth"):
        bpy.ops.facelab.propagate(suggestions=0)
    assert obj.data.shape_keys.key_blocks.keys() == before


@pytest.mark.slow
def test_an_artist_key_named_like_facelabs_is_read_as_part_of_the_capture(ict, addon):
    """Reading the capture mutes FaceLab's recorded output only: the artist's own ``FL_Prop_MyFix``
    shows in what Propagate reads, while a key FaceLab wrote is left out."""
    scene, obj, err = corrected(ict)
    fix = obj.shape_key_add(name="FL_Prop_MyFix", from_mix=False)
    c = coords(obj, "FL_Prop_MyFix")
    c.reshape(-1, 3)[:30] += 0.001  # the first 30 vertices
    fix.data.foreach_set("co", c)
    f = int(FRAMES[0])
    fix.value = 0.0
    base = caches.read_captured_frames(obj, [f])[0]
    fix.value = 1.0
    with_fix = caches.read_captured_frames(obj, [f])[0]
    moved = np.abs(with_fix - base).max(axis=1)
    np.testing.assert_allclose(moved[:30], 0.001, atol=2e-6)
    assert moved[30:].max() < 1e-7
    # FaceLab's own key with the same prefix is muted when the capture is read
    ours = add_corrective_key(obj, f"{PROPAGATE_PREFIX}00", np.full((len(obj.data.vertices), 3), 0.002))
    from facelab_addon.blender.ownership import own_key

    own_key(ours)
    ours.value = 1.0
    np.testing.assert_allclose(caches.read_captured_frames(obj, [f])[0], with_fix, atol=1e-7)
