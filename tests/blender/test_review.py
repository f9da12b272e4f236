"""Review tools, headless: capture / corrected toggle restoring the artist's mutes, the correction heat
map against known offsets (world mm with object and unit scale), neighbouring sketches, stepping to
suggested / most extrapolated frames; all undoable and refusing with a reason."""

import bpy
import numpy as np
import pytest

from facelab_addon.blender import review
from facelab_addon.blender.shapekeys import add_corrective_key, key_property_bulk, key_values_bulk
from facelab_addon.names import CORRECTION_ATTR, CORRECTION_RANGE_PROP, EXTRAPOLATION_PROP, REVIEW_SAVED_PROP

from .test_ui import empty_scene, small_face

pytestmark = pytest.mark.blender


def _mutes(obj):
    return {kb.name: kb.mute for kb in obj.data.shape_keys.key_blocks}


def corrected_face(scene):
    """A 6x6 face with two FaceLab corrective keys (owned), one artist key, an FL correction modifier."""
    obj = small_face(scene)
    n = len(obj.data.vertices)
    d1 = np.zeros((n, 3))
    d1[:6, 2] = np.linspace(0.0, 0.5, 6)  # first row moves up, 0..0.5 units
    d2 = np.zeros((n, 3))
    d2[30:, 1] = 0.2
    add_corrective_key(obj, "FL_Prop_00", d1)
    add_corrective_key(obj, "FL_Prop_01", d2)
    obj.shape_key_add(name="ArtistSmile", from_mix=False)
    kbs = obj.data.shape_keys.key_blocks
    for k in ("FL_Prop_00", "FL_Prop_01", "ArtistSmile"):
        kbs[k].value = 1.0
    kbs["FL_Prop_01"].mute = True  # the artist muted this one by hand
    md = obj.modifiers.new("FL Correction", "DISPLACE")
    md.strength = 0.0
    cap = obj.modifiers.new("FL Capture (PC2)", "DISPLACE")
    cap.strength = 0.0
    return obj, d1, d2


def test_toggle_restores_exactly_the_artists_mutes(addon):
    scene = empty_scene()
    obj, _, _ = corrected_face(scene)
    before = _mutes(obj)
    md, cap = obj.modifiers["FL Correction"], obj.modifiers["FL Capture (PC2)"]
    md.show_render = False  # the artist's own modifier flags, kept too
    assert review.correction_keys(obj) == ["FL_Prop_00", "FL_Prop_01"]
    assert review.correction_modifiers(obj) == ["FL Correction"]  # the capture's modifier is never toggled
    bpy.ops.ed.undo_push(message="before")
    assert bpy.ops.facelab.review_toggle() == {"FINISHED"}
    m = _mutes(obj)
    assert m["FL_Prop_00"] and m["FL_Prop_01"] and not m["ArtistSmile"] and not m["Basis"]
    assert not md.show_viewport and not md.show_render and cap.show_viewport
    assert review.showing_capture(obj) and REVIEW_SAVED_PROP in obj
    lay = _draw_review()
    assert "Showing: the capture (corrections muted)" in lay.texts("label")
    assert ("facelab.review_toggle", "Show Corrected") in [(a[0], kw.get("text")) for mm, a, kw in lay.log
                                                           if mm == "operator"]
    # undo goes back to the corrected view
    bpy.ops.ed.undo_push(message="Compare")
    bpy.ops.ed.undo()
    obj = bpy.data.objects["Face"]
    assert _mutes(obj) == before and not review.showing_capture(obj)
    bpy.ops.facelab.review_toggle()
    assert bpy.ops.facelab.review_toggle() == {"FINISHED"}
    assert _mutes(obj) == before  # FL_Prop_01 stays muted, as the artist had it
    md = obj.modifiers["FL Correction"]
    assert md.show_viewport and not md.show_render and REVIEW_SAVED_PROP not in obj


def _draw_review():
    from .test_ui import draw

    return draw(bpy.types.FACELAB_PT_review, bpy.context)


def test_heat_map_is_the_correction_in_world_millimetres(addon):
    scene = empty_scene()
    obj, d1, d2 = corrected_face(scene)
    obj.data.shape_keys.key_blocks["FL_Prop_01"].mute = False
    obj.scale = (2.0, 2.0, 2.0)  # world space: twice the local offsets
    scene.unit_settings.scale_length = 0.01  # a scene unit is a centimetre
    key_values_bulk(obj, ["FL_Prop_00"], [1, 10], [[0.0], [1.0]])  # keyed: half way on frame 5.5 ...
    scene.frame_set(4)  # value (4-1)/9 = 1/3
    bpy.context.view_layer.update()
    assert bpy.ops.facelab.correction_heatmap() == {"FINISHED"}
    expected = np.linalg.norm(d1 / 3 + d2, axis=1) * 2 * 0.01 * 1e3
    attr = obj.data.color_attributes[CORRECTION_ATTR]
    assert attr.domain == "POINT" and obj.data.color_attributes.active_color.name == CORRECTION_ATTR
    got = review.correction_magnitude(obj, bpy.context.evaluated_depsgraph_get(), metres_per_unit=0.01)
    np.testing.assert_allclose(got, expected, atol=1e-4)
    rng = list(obj.data[CORRECTION_RANGE_PROP])
    assert rng[0] == 0.0 and rng[1] == pytest.approx(expected.max(), abs=1e-4) and rng[2] == 4
    col = np.empty(4 * len(expected), np.float32)
    attr.data.foreach_get("color", col)
    col = col.reshape(-1, 4)
    np.testing.assert_allclose(col[np.argmax(expected)], review.heat_colors([1.0], 1.0)[0], atol=1e-6)  # red
    np.testing.assert_allclose(col[expected == 0], np.tile(review.HEAT_STOPS[0, 1:].tolist() + [1.0],
                                                           ((expected == 0).sum(), 1)), atol=1e-6)  # grey
    assert not any(kb.mute for kb in obj.data.shape_keys.key_blocks)  # the mutes are as before
    lay = _draw_review()
    assert f"Heat map (frame 4): grey 0 mm - red {expected.max():.2f} mm" in lay.texts("label")
    # while the capture is shown, the heat map still measures the correction
    bpy.ops.facelab.review_toggle()
    np.testing.assert_allclose(review.correction_magnitude(obj, bpy.context.evaluated_depsgraph_get(),
                                                           metres_per_unit=0.01), expected, atol=1e-4)
    assert all(obj.data.shape_keys.key_blocks[k].mute for k in ("FL_Prop_00", "FL_Prop_01"))
    # a fixed scale: 1 mm full red
    bpy.ops.facelab.review_toggle()
    assert bpy.ops.facelab.correction_heatmap(max_mm=1.0) == {"FINISHED"}
    assert obj.data[CORRECTION_RANGE_PROP][1] == 1.0
    # no correction on frame 1 (key value 0 there and FL_Prop_01 muted): a warning, all grey
    obj.data.shape_keys.key_blocks["FL_Prop_01"].mute = True
    scene.frame_set(1)
    assert bpy.ops.facelab.correction_heatmap() == {"FINISHED"}
    attr = obj.data.color_attributes[CORRECTION_ATTR]
    attr.data.foreach_get("color", col.ravel())
    assert np.allclose(col[:, :3], review.HEAT_STOPS[0, 1:])


@pytest.mark.slow
def test_heat_map_of_a_propagated_correction_matches_the_injected_error(ict, addon):
    """After Propagate on the ICT capture, the heat map of a held-out frame is the size of the lip error
    it removes (the truth), to within the regression's residual."""
    from facelab_addon.blender.shapekeys import key_spike

    from .test_propagate_operator import FRAMES, TRAIN, build, paper_settings

    scene, obj, err, cap_w = build(ict)
    for f, w in zip(TRAIN, cap_w[np.searchsorted(FRAMES, TRAIN)]):
        scene.frame_set(f)
        key_spike(add_corrective_key(obj, f"Sculpt_{f}", -w * err), f)
        bpy.ops.facelab.mark_training_frame()
    bpy.ops.facelab.auto_regions()
    paper_settings(scene)  # the undamped correction: the whole injected error
    assert bpy.ops.facelab.propagate(suggestions=3) == {"FINISHED"}
    assert obj.animation_data.action.name == "FL_Extrapolation"  # the object's action, named for what it keys
    f = 24
    scene.frame_set(f)
    assert bpy.ops.facelab.correction_heatmap() == {"FINISHED"}
    mag = review.correction_magnitude(obj, bpy.context.evaluated_depsgraph_get(), metres_per_unit=1.0)
    truth = np.linalg.norm(cap_w[np.searchsorted(FRAMES, f)] * err, axis=1) * 1e3  # err is in metres
    lips = truth > 0
    assert truth.max() > 0.3
    # (the regression's residual on this held-out frame is ~18 % of the error it removes)
    assert np.abs(mag - truth)[lips].mean() < 0.25 * truth[lips].mean(), (mag[lips].mean(), truth[lips].mean())
    assert np.corrcoef(mag[lips], truth[lips])[0, 1] > 0.9
    from facelab_addon.blender.mesh import vertex_group_mask

    assert mag[~vertex_group_mask(obj, "FL_lips")].max() < 1e-3  # nothing outside the predicted region moves
    assert obj.data[CORRECTION_RANGE_PROP][1] == pytest.approx(mag.max(), rel=1e-5)
    # stepping through what Propagate left: suggestions in order, then the most extrapolated frame
    sug = sorted(m.frame for m in scene.timeline_markers if m.name.startswith("FL suggest"))
    scene.frame_set(0)
    for want in sug + sug[:1]:
        assert bpy.ops.facelab.next_suggested_frame() == {"FINISHED"} and scene.frame_current == want
    frames, score = review.keyed_extrapolation(obj)
    assert bpy.ops.facelab.most_extrapolated_frame() == {"FINISHED"}
    best = scene.frame_current
    assert best not in TRAIN and score[frames == best][0] == score[~np.isin(frames, TRAIN)].max()


def test_step_to_frames_and_onion_skin(addon):
    scene = empty_scene()
    obj = small_face(scene)
    with pytest.raises(RuntimeError, match="FL suggest"):
        bpy.ops.facelab.next_suggested_frame()
    with pytest.raises(RuntimeError, match="Propagate first"):
        bpy.ops.facelab.most_extrapolated_frame()
    for f in (30, 12):
        scene.timeline_markers.new(f"FL suggest {f}", frame=f)
    scene.timeline_markers.new("shot start", frame=5)  # not FaceLab's
    scene.frame_set(1)
    got = []
    for _ in range(3):
        bpy.ops.facelab.next_suggested_frame()
        got.append(scene.frame_current)
    assert got == [12, 30, 12]
    frames = np.arange(1, 21)
    score = np.where(frames == 7, 0.95, np.where(frames == 15, 0.8, 0.1))
    obj[EXTRAPOLATION_PROP] = 0.0
    key_property_bulk(obj, f'["{EXTRAPOLATION_PROP}"]', frames, score)
    assert bpy.ops.facelab.most_extrapolated_frame() == {"FINISHED"} and scene.frame_current == 7
    scene.frame_set(7)
    bpy.ops.facelab.mark_training_frame()  # frame 7 is corrected now: the next worst is 15
    assert bpy.ops.facelab.most_extrapolated_frame() == {"FINISHED"} and scene.frame_current == 15
    assert review.most_extrapolated_frame([3], [0.2], {3}) is None

    # neighbouring sketches: onion skinning on the lip sketch's layers
    with pytest.raises(RuntimeError, match="No lip sketch yet"):
        bpy.ops.facelab.sketch_onion_skin()
    cam = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    scene.collection.objects.link(cam)
    scene.camera = cam
    bpy.ops.facelab.new_lip_sketch()
    gp = scene.facelab.sketch
    assert gp.hide_render  # a drawing aid, never rendered
    assert bpy.ops.facelab.sketch_onion_skin(before=3, after=1, opacity=0.25) == {"FINISHED"}
    assert all(layer.use_onion_skinning for layer in gp.data.layers) and len(gp.data.layers) == 2
    assert (gp.data.ghost_before_range, gp.data.ghost_after_range, gp.data.onion_mode) == (3, 1, "RELATIVE")
    assert gp.data.onion_factor == pytest.approx(0.25)
    assert bpy.ops.facelab.sketch_onion_skin(show=False) == {"FINISHED"}
    assert not any(layer.use_onion_skinning for layer in gp.data.layers)
    for op in ("review_toggle", "correction_heatmap", "sketch_onion_skin", "next_suggested_frame",
               "most_extrapolated_frame"):
        assert {"REGISTER", "UNDO"} <= getattr(bpy.types, "FACELAB_OT_" + op).bl_options
