"""The artist's loop on the shipped sample (sketch -> Refine Lips -> Propagate -> refine more frames -> Propagate
again): a training frame keeps exactly what the viewport showed after Refine Lips (or a sculpt marked with Mark
Training Frame) through later Propagate runs, Refine twice, Review's Show Capture and a save and reload; each
round of the README loop lowers the held-out error. Sketches trace the sample's truth (``testing.loop``)."""

import dataclasses

import bpy
import numpy as np
import pytest

from facelab_addon.blender import review
from facelab_addon.blender.shapekeys import add_corrective_key, key_spike
from facelab_addon.core.errors import FaceLabError
from facelab_addon.pipeline import refine as refine_module
from facelab_addon.pipeline.bake import bake
from facelab_addon.pipeline.propagate import PropagateSettings, propagate
from facelab_addon.testing.loop import refine_frame, run_loop, sample_face, save_and_reload, shown_frames

pytestmark = pytest.mark.blender

TOL_MM = 0.01  # the bound on how far a training frame may move from what the viewport showed
FIRST = (11, 37, 44)


def _mm(a, b):
    """Largest vertex distance (mm) between two (V,3) sample frames (metres)."""
    return float(np.linalg.norm(np.asarray(a) - np.asarray(b), axis=1).max() * 1e3)


@pytest.fixture
def solved(monkeypatch):
    """Records every Refine Lips solve's result, world positions (V,3): what the viewport shows after Refine."""
    out = []
    real = refine_module.refine_lips_views

    def spy(*args, **kw):
        res = real(*args, **kw)
        out.append(np.array(res[0] if isinstance(res, tuple) else res))
        return res

    monkeypatch.setattr(refine_module, "refine_lips_views", spy)
    return out


def _world(face, X):
    M = np.array(face.obj.matrix_world)
    return X @ M[:3, :3].T + M[:3, 3]


def _round_one(face):
    """Refine the README's first frames and Propagate; their shapes right after Refine."""
    shapes = {f: refine_frame(face, f) for f in FIRST}
    assert all(s is not None for s in shapes.values())
    propagate(face.scene, face.obj, face.frames, PropagateSettings())
    return shapes


@pytest.mark.slow
def test_refine_after_propagate_keeps_the_fix(addon, solved):
    face = sample_face()
    first = _round_one(face)
    f = 41
    propagated = shown_frames(face, [f])[0]
    assert _mm(propagated, face.capture[f - 1]) > 0.05  # Propagate corrected frame 41 before it is refined
    shown = refine_frame(face, f)
    assert _mm(_world(face, shown), solved[-1]) < TOL_MM  # right after Refine: the refined shape, no more
    propagate(face.scene, face.obj, face.frames, PropagateSettings())
    assert _mm(shown_frames(face, [f])[0], shown) < TOL_MM  # and after the next Propagate, the same
    for g, s in first.items():  # the earlier training frames too
        assert _mm(shown_frames(face, [g])[0], s) < TOL_MM


@pytest.mark.slow
def test_refine_twice_on_one_frame(addon, solved):
    face = sample_face()
    _round_one(face)
    f = 41
    refine_frame(face, f)
    first_key = [t.shape_key for t in face.obj.facelab.training_frames if t.frame == f]
    shown = refine_frame(face, f)  # again, on the refined frame
    assert _mm(_world(face, shown), solved[-1]) < TOL_MM
    records = [t.shape_key for t in face.obj.facelab.training_frames if t.frame == f]
    assert len(first_key) == 1 and len(records) == 1 and records != first_key  # the newer correction alone
    keys = face.obj.data.shape_keys.key_blocks
    assert first_key[0] in keys  # the older key is kept, never deleted ...
    face.scene.frame_set(f)
    assert keys[first_key[0]].value == 0.0  # ... but no longer adds on the frame
    propagate(face.scene, face.obj, face.frames, PropagateSettings())
    assert _mm(shown_frames(face, [f])[0], shown) < TOL_MM


def test_sculpt_on_a_propagated_frame_then_mark_training_frame(addon):
    face = sample_face()
    _round_one(face)
    f = 30
    propagated = shown_frames(face, [f])[0]
    assert _mm(propagated, face.capture[f - 1]) > 0.05  # the frame shows Propagate's correction
    # the artist sculpts the lips on this frame in a key of their own, keyed on the frame
    obj = face.obj
    sculpt = obj.shape_key_add(name="MySculpt", from_mix=False)
    co = np.empty(3 * len(obj.data.vertices), np.float32)
    sculpt.data.foreach_get("co", co)
    co = co.reshape(-1, 3)
    co[face.lips, 2] += 3e-4  # 0.3 mm up
    sculpt.data.foreach_set("co", co.ravel())
    key_spike(sculpt, f)
    face.scene.frame_set(f)
    seen = shown_frames(face, [f])[0]
    bpy.context.view_layer.objects.active = obj
    assert bpy.ops.facelab.mark_training_frame() == {"FINISHED"}
    assert _mm(shown_frames(face, [f])[0], seen) < TOL_MM
    propagate(face.scene, face.obj, face.frames, PropagateSettings())
    assert _mm(shown_frames(face, [f])[0], seen) < TOL_MM


@pytest.mark.slow
def test_show_capture_during_refine_and_propagate(addon, solved, tmp_path):
    # reference: Refine 41 and Propagate with Review off
    ref = sample_face()
    _round_one(ref)
    refine_frame(ref, 41)
    propagate(ref.scene, ref.obj, ref.frames, PropagateSettings())
    expected = shown_frames(ref)

    face = sample_face()
    _round_one(face)
    review.show_capture(face.obj)
    with pytest.raises(FaceLabError, match="Show Corrected"):  # never a bake of the capture reported as done
        bake(face.obj, face.frames, tmp_path / "never_written.pc2")
    shown = refine_frame(face, 41)
    assert _mm(_world(face, shown), solved[-1]) < TOL_MM  # the viewport shows the refined shape
    assert not review.showing_capture(face.obj)  # Refine ended Show Capture: every correction shows with it
    review.show_capture(face.obj)
    assert max(_mm(a, b) for a, b in zip(shown_frames(face), face.capture)) < 1e-3  # the new key is muted too
    propagate(face.scene, face.obj, face.frames, PropagateSettings())
    assert not review.showing_capture(face.obj)  # never the capture with Propagate's newest keys alone
    got = shown_frames(face)
    assert _mm(got[40], shown) < TOL_MM
    # Propagate trained on the corrections, not on the capture Review showed: the shot is the reference's
    assert max(_mm(a, b) for a, b in zip(got, expected)) < 1e-3
    review.show_capture(face.obj)  # and Show Capture mutes every key Propagate wrote
    assert max(_mm(a, b) for a, b in zip(shown_frames(face), face.capture)) < 1e-3


def test_propagate_while_review_shows_the_capture_shows_the_result(addon):
    face = sample_face()
    for f in FIRST:
        refine_frame(face, f)
    review.show_capture(face.obj)
    propagate(face.scene, face.obj, face.frames, PropagateSettings())
    seen = shown_frames(face)
    assert not review.showing_capture(face.obj)
    for f in FIRST:  # the training frames show their fix with Propagate's output: no mix of muted and new keys
        assert _mm(seen[f - 1], face.capture[f - 1]) > 0.05
    review.show_corrected(face.obj)  # nothing left to restore
    assert max(_mm(a, b) for a, b in zip(shown_frames(face), seen)) < 1e-6


def test_refine_under_show_capture_over_another_facelab_correction(addon, solved):
    """A training frame is measured from the frame without FaceLab's lip corrections whatever Review shows: with
    another FaceLab correction on the face (a Solve key), Refine under Show Capture gives the frame the shape it
    solved once the corrections show again."""
    face = sample_face()
    obj = face.obj
    d = np.zeros((len(obj.data.vertices), 3))
    d[face.lips, 2] = 3e-4  # 0.3 mm
    add_corrective_key(obj, "FL_Solve_00", d).value = 1.0
    review.show_capture(obj)
    refine_frame(face, 41)
    review.show_corrected(obj)
    assert _mm(_world(face, shown_frames(face, [41])[0]), solved[-1]) < TOL_MM


def test_sculpt_on_a_refined_frame_then_mark_training_frame_again(addon):
    face = sample_face()
    _round_one(face)
    f = 41
    refined = refine_frame(face, f)
    (old,) = [t.shape_key for t in face.obj.facelab.training_frames if t.frame == f]
    obj = face.obj
    sculpt = obj.shape_key_add(name="MySculpt", from_mix=False)  # the artist's sculpt on top, keyed on the frame
    co = np.empty(3 * len(obj.data.vertices), np.float32)
    sculpt.data.foreach_get("co", co)
    co = co.reshape(-1, 3)
    co[face.lips, 2] += 3e-4
    sculpt.data.foreach_set("co", co.ravel())
    key_spike(sculpt, f)
    face.scene.frame_set(f)
    seen = shown_frames(face, [f])[0]
    assert _mm(seen, refined) > 0.2
    bpy.context.view_layer.objects.active = obj
    bpy.ops.ed.undo_push(message="before Mark")
    assert bpy.ops.facelab.mark_training_frame() == {"FINISHED"}
    bpy.ops.ed.undo_push(message="Mark Training Frame")  # headless: the UI would push it
    records = [t for t in obj.facelab.training_frames if t.frame == f]
    assert len(records) == 1 and records[0].shape_key not in ("", old) and records[0].source == "marked"
    keys = obj.data.shape_keys.key_blocks
    assert old in keys and keys[old].value == 0.0  # the refined key is kept, off on the frame
    assert _mm(shown_frames(face, [f])[0], seen) < TOL_MM
    bpy.ops.ed.undo()  # back to the refined training frame
    face = dataclasses.replace(face, scene=bpy.context.scene, obj=bpy.context.scene.facelab.face)
    face.scene.frame_set(f)
    assert [t.shape_key for t in face.obj.facelab.training_frames if t.frame == f] == [old]
    assert _mm(shown_frames(face, [f])[0], seen) < TOL_MM  # the sculpt key is still on, over the refined shape
    bpy.context.view_layer.objects.active = face.obj
    assert bpy.ops.facelab.mark_training_frame() == {"FINISHED"}  # and again, then a round of the loop
    propagate(face.scene, face.obj, face.frames, PropagateSettings())
    assert _mm(shown_frames(face, [f])[0], seen) < TOL_MM  # the marked shape holds through Propagate


def test_a_training_key_muted_by_hand_is_refused(addon):
    face = sample_face()
    for f in FIRST:
        refine_frame(face, f)
    kb = face.obj.data.shape_keys.key_blocks[face.obj.facelab.training_frames[0].shape_key]
    kb.mute = True
    with pytest.raises(FaceLabError, match="muted"):
        propagate(face.scene, face.obj, face.frames, PropagateSettings())


@pytest.mark.slow
def test_the_readme_loop_improves_each_round(addon):
    face = sample_face()
    loop = run_loop(face, settings=PropagateSettings(suggestions=6), total=12)
    rounds = loop["rounds"]
    held = [r["held_out_rms_mm"] for r in rounds]
    print("held-out RMS per round (mm):", [round(h, 4) for h in held], "order", loop["order"])
    assert len(rounds) >= 3
    assert all(b <= a + 1e-4 for a, b in zip(held, held[1:])), held
    assert max(r["max_training_drift_mm"] for r in rounds) < TOL_MM
    one = run_loop(sample_face(), settings=PropagateSettings(), plan=[rounds[-1]["training"]])
    assert held[-1] <= 1.1 * one["rounds"][-1]["held_out_rms_mm"], (held[-1], one["rounds"][-1])


@pytest.mark.slow
def test_save_and_reload_between_rounds_changes_nothing(addon, tmp_path):
    plan = [list(FIRST), [41, 7]]
    straight = run_loop(sample_face(), plan=plan)
    X = shown_frames(straight["face"])
    reloaded = run_loop(sample_face(), plan=plan, between=save_and_reload(tmp_path / "loop.blend"))
    Y = shown_frames(reloaded["face"])
    assert max(_mm(a, b) for a, b in zip(X, Y)) < 1e-3
    assert reloaded["rounds"][-1]["max_training_drift_mm"] < TOL_MM


def test_undo_of_a_refine_after_propagate_gives_the_propagated_frame_back(addon):
    face = sample_face()
    _round_one(face)
    f = 41
    propagated = shown_frames(face, [f])[0]
    bpy.ops.ed.undo_push(message="before Refine")
    shown = refine_frame(face, f)
    bpy.ops.ed.undo_push(message="Refine Lips")  # headless: the UI would push it
    assert _mm(shown, propagated) > 0.05
    bpy.ops.ed.undo()
    face = dataclasses.replace(face, scene=bpy.context.scene, obj=bpy.context.scene.facelab.face)
    face.scene.frame_set(f)
    assert _mm(shown_frames(face, [f])[0], propagated) < 1e-3  # Propagate's correction is back on the frame
    assert f not in {t.frame for t in face.obj.facelab.training_frames}
    shown = refine_frame(face, f)  # and the loop goes on from there
    propagate(face.scene, face.obj, face.frames, PropagateSettings())
    assert _mm(shown_frames(face, [f])[0], shown) < TOL_MM


def test_refine_on_a_propagated_frame_solves_from_the_capture(addon, solved):
    """The drawing alone decides a refined frame: Refine on a frame Propagate corrected gives what it gives on the
    bare capture (Review's Show Capture on), so a propagated error the sketch does not show is not carried into
    the training frame."""
    f = 41
    ref = sample_face()
    _round_one(ref)
    review.show_capture(ref.obj)
    from_capture = refine_frame(ref, f)
    review.show_corrected(ref.obj)
    face = sample_face()
    _round_one(face)
    assert _mm(shown_frames(face, [f])[0], face.capture[f - 1]) > 0.05  # the frame shows Propagate's correction
    on_propagated = refine_frame(face, f)
    assert _mm(on_propagated, from_capture) < TOL_MM
    assert _mm(_world(face, on_propagated), solved[-1]) < TOL_MM  # and the viewport shows that refined shape
