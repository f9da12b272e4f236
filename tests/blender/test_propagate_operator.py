"""Headless end to end: an animated ICT capture with a systematic inner-lip error,
a few corrected frames, Auto Regions, Propagate -> corrective keys on the timeline."""

import bpy
import numpy as np
import pytest

from facelab_addon.blender import caches
from facelab_addon.blender.mesh import mesh_triangles, vertex_group_mask
from facelab_addon.blender.shapekeys import add_corrective_key, key_spike, key_values_bulk
from facelab_addon.core.lips.regressor import LipRegressor
from facelab_addon.core.lips.regions import faces_in_region
from facelab_addon.testing.scenes import build_ict_face_scene
from facelab_addon.testing.weights import CYCLIC_MOUTH_CHANNELS, cyclic_mouth_weights

pytestmark = pytest.mark.blender

SCALE = 0.01  # metres
EXPR = list(CYCLIC_MOUTH_CHANNELS)
FRAMES = np.arange(1, 41)
TRAIN = [5, 18, 31]


def lip_capture_error(ict):
    """(V,3) systematic capture error in metres: the inner lips pulled apart (up to 0.8 mm per lip).

    The realistic error shape of ``testing.synthetic.lip_error_weights``, faded to zero before the border
    of the lip region Auto Regions proposes (that border is held by the Poisson solve).
    """
    from facelab_addon.core.geometry.geodesic import geodesic_distance
    from facelab_addon.core.lips.mouth import find_mouth
    from facelab_addon.core.lips.regions import auto_regions, region_border
    from facelab_addon.testing import synthetic as syn

    fixed = ~ict.part_vertex_mask("M_Face")
    mouth = find_mouth(ict.neutral, ict.faces, fixed, loop=syn.ICT_MOUTH_LOOP)
    w, side = syn.lip_error_weights(ict.neutral, ict.faces, fixed, mouth=mouth)
    # fade to zero before the border of the lip region Auto Regions will propose (the border is held)

    _, lip_mask = auto_regions(ict.neutral, ict.faces)
    d = geodesic_distance(ict.neutral, ict.faces, region_border(ict.faces, faces_in_region(ict.faces, lip_mask)))
    fade = np.clip(d / (0.35 * np.nanmax(np.where(lip_mask, d, np.nan))), 0, 1) * lip_mask
    err = np.zeros_like(ict.neutral)
    err[:, 1] = side * w * fade * 0.08 * SCALE
    return err


def build(ict):
    """The animated capture: EXPR keyed with ``cyclic_mouth_weights`` on FRAMES, plus a keyed CaptureError.

    The error fails to close the lips as jawOpen falls (an artist's key): value ``1 - 1.5 * jawOpen``.
    """
    fs = build_ict_face_scene(ict, EXPR, weights=cyclic_mouth_weights(FRAMES), frames=FRAMES, scale=SCALE)
    err = lip_capture_error(ict)
    add_corrective_key(fs.obj, "CaptureError", err)
    cap_w = 1.0 - 1.5 * cyclic_mouth_weights(FRAMES)[:, 0]
    key_values_bulk(fs.obj, ["CaptureError"], FRAMES, cap_w[:, None])
    return fs.scene, fs.obj, err, cap_w


def paper_settings(scene):
    """The shot's Propagate settings set to the paper's maps, undamped (the core regressor's defaults)."""
    from facelab_addon.pipeline.propagate import PropagateSettings
    from facelab_addon.pipeline.shot_settings import ensure_initialized, entry_for

    ensure_initialized(scene, entry_for(PropagateSettings))
    scene.facelab_propagate.ridge, scene.facelab_propagate.damping = "none", False


@pytest.mark.slow
def test_propagate_end_to_end(ict, addon):
    scene, obj, err, cap_w = build(ict)
    artist_keys = {kb.name: np.array([d.co[:] for d in kb.data]) for kb in obj.data.shape_keys.key_blocks}

    # Auto Regions writes the two vertex groups (and refuses to overwrite them silently)
    assert bpy.ops.facelab.auto_regions() == {"FINISHED"}
    mouth, lips = vertex_group_mask(obj, "FL_mouth"), vertex_group_mask(obj, "FL_lips")
    tris = mesh_triangles(obj.data)
    assert mouth.sum() > 100 and lips.sum() > 100
    assert not np.intersect1d(faces_in_region(tris, mouth), faces_in_region(tris, lips)).size  # share only a border
    with pytest.raises(RuntimeError, match="already exist"):
        bpy.ops.facelab.auto_regions()

    # the artist corrects a few frames by sculpting (a key that cancels the error there) and marks them
    i = np.searchsorted(FRAMES, TRAIN)
    for f, w in zip(TRAIN, cap_w[i]):
        scene.frame_set(f)
        kb = add_corrective_key(obj, f"Sculpt_{f}", -w * err)
        key_spike(kb, f)
        assert bpy.ops.facelab.mark_training_frame() == {"FINISHED"}
    paper_settings(scene)  # compared with the core regressor's defaults below
    assert bpy.ops.facelab.propagate(suggestions=2) == {"FINISHED"}

    key = obj.data.shape_keys
    prop = [kb.name for kb in key.key_blocks if kb.name.startswith("FL_Prop_")]
    assert 1 <= len(prop) <= 10
    # the artist's keys are untouched
    for name, co in artist_keys.items():
        np.testing.assert_array_equal(np.array([d.co[:] for d in key.key_blocks[name].data]), co)

    # independent computation of the regressor's prediction at held-out frames
    tris = mesh_triangles(obj.data)
    rest = np.array([d.co[:] for d in key.reference_key.data], dtype=np.float64)
    captured = caches.evaluate_frames(obj, FRAMES, mute_shape_keys_prefix=("FL_",))
    corrected = caches.evaluate_frames(obj, TRAIN, mute_shape_keys_prefix=("FL_Prop_",))
    reg = LipRegressor(rest, tris, faces_in_region(tris, mouth), faces_in_region(tris, lips))
    reg.fit(corrected)
    held = [2, 11, 24, 37]
    expect = reg.predict(captured[np.searchsorted(FRAMES, held)].astype(np.float64))
    got = caches.evaluate_frames(obj, held, mute_shape_keys_prefix=())
    tol = 1e-5 + 1e-6  # 0.01 mm in metres, plus float32 storage
    assert np.abs(got - expect).max() < tol, np.abs(got - expect).max()
    # and it does correct: closer to the truth than the capture
    truth = captured[np.searchsorted(FRAMES, held)] - cap_w[np.searchsorted(FRAMES, held), None, None] * err
    e_cap = np.linalg.norm(captured[np.searchsorted(FRAMES, held)] - truth, axis=2)[:, lips].mean()
    e_fix = np.linalg.norm(got - truth, axis=2)[:, lips].mean()
    assert e_fix < 0.5 * e_cap, (e_cap, e_fix)  # 3 training frames: measured 65 % lower
    # the shape-key fast path reads the same capture as frame-by-frame evaluation
    from facelab_addon.blender.shapekeys import shape_key_sequence

    np.testing.assert_allclose(shape_key_sequence(obj, FRAMES, skip_prefixes=("FL_",)), captured, atol=1e-7)

    # training frames show exactly the artist's correction (propagation is zero there)
    at_train = caches.evaluate_frames(obj, TRAIN, mute_shape_keys_prefix=())
    np.testing.assert_allclose(at_train, corrected, atol=1e-7)
    # extrapolation keyed on the object: 0 on training frames; suggestions marked
    scene.frame_set(TRAIN[1])
    assert abs(obj["FL_extrapolation"]) < 1e-3  # float32 round-off between the two read paths
    assert sum(m.name.startswith("FL suggest") for m in scene.timeline_markers) == 2

    # one more training frame, propagate again: only FaceLab's own keys are replaced
    f = 24
    scene.frame_set(f)
    kb = add_corrective_key(obj, f"Sculpt_{f}", -cap_w[np.searchsorted(FRAMES, f)] * err)
    key_spike(kb, f)
    bpy.ops.facelab.mark_training_frame()
    assert bpy.ops.facelab.propagate(suggestions=0) == {"FINISHED"}
    names = [kb.name for kb in obj.data.shape_keys.key_blocks]
    assert all(n in names for n in artist_keys) and all(f"Sculpt_{t}" in names for t in TRAIN + [24])
    assert not any(n.startswith("FL_Prop_") and "." in n for n in names)  # replaced, not duplicated
    assert not any(m.name.startswith("FL suggest") for m in scene.timeline_markers)


def test_propagate_bad_input(ict, addon):
    scene, obj, err, cap_w = build(ict)
    # no training frames: poll explains
    assert not bpy.ops.facelab.propagate.poll()
    scene.frame_set(5)
    bpy.ops.facelab.mark_training_frame()
    # no regions yet
    with pytest.raises(RuntimeError, match="FL_mouth"):
        bpy.ops.facelab.propagate()
    # overlapping regions
    for g in ("FL_mouth", "FL_lips"):
        obj.vertex_groups.new(name=g).add(list(range(6000, 7000)), 1.0, "REPLACE")
    with pytest.raises(RuntimeError, match="(?i)overlap"):
        bpy.ops.facelab.propagate()
    assert not any(kb.name.startswith("FL_Prop_") for kb in obj.data.shape_keys.key_blocks)
