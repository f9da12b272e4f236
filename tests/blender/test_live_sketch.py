"""Ready to draw, Snap to plate, Live Refine: headless, on the shipped sample (a face, its camera, its plate
rendered from the truth)."""

import bpy
import numpy as np
import pytest

from facelab_addon.blender.camera import camera_from_blender
from facelab_addon.blender.sample import read_sample
from facelab_addon.blender.sketch_mode import DRAW_MODE
from facelab_addon.names import SNAP_PROP, SNAP_REPORT_PROP
from facelab_addon.blender.plate import PlateError
from facelab_addon.blender.strokes import read_lip_strokes, write_stroke_pixels
from facelab_addon.names import PREFIX

pytestmark = pytest.mark.blender

FRAME = 20


def _triangles(data):
    pv, po = data.poly_verts, data.poly_offsets
    return np.array([[pv[s], pv[s + k], pv[s + k + 1]] for s, e in zip(po[:-1], po[1:]) for k in range(1, e - s - 1)])


@pytest.fixture(scope="module")
def sample(addon):
    from facelab_addon.core.lips.mouth import find_mouth
    from facelab_addon.testing import synthetic as syn

    data = read_sample()
    bpy.ops.wm.read_factory_settings(use_empty=True)
    assert bpy.ops.facelab.load_sample() == {"FINISHED"}
    scene = bpy.context.scene
    F = _triangles(data)
    mouth = find_mouth(data.vertices, F, None, near=data.vertices[data.inner_lip_loop].mean(0),
                       units_per_mm=0.001)
    truth = {}
    for f in (FRAME,):
        truth[f] = syn.lip_contours(data.truth()[f - 1], F, data.camera, mouth=mouth)
    return data, scene.name, truth


def _fresh(sample):
    """The sample scene back in Object mode with the face active and no sketch."""
    data, scene_name, truth = sample
    scene = bpy.data.scenes[scene_name]  # (an undo reloads every datablock)
    bpy.context.window.scene = scene
    if bpy.context.object is not None and bpy.context.object.mode != "OBJECT":
        bpy.ops.object.mode_set(mode="OBJECT")
    for o in [o for o in scene.objects if o.type == "GREASEPENCIL"]:
        bpy.data.objects.remove(o)
    face = scene.facelab.face
    from facelab_addon.blender.shapekeys import remove_keys
    from facelab_addon.pipeline.live_refine import remove_preview

    remove_keys(face, PREFIX)  # what an earlier test refined
    remove_preview(face)
    face.facelab.training_frames.clear()
    face.select_set(True)
    bpy.context.view_layer.objects.active = face
    for area in bpy.context.screen.areas:
        if area.type == "VIEW_3D":
            area.spaces.active.region_3d.view_perspective = "PERSP"
    scene.camera.data.show_background_images = False
    scene.frame_set(FRAME)
    return data, scene, face


def _sketch(sample, draw=False):
    """:func:`_fresh`, then New Lip Sketch (and, with ``draw``, the truth's lips drawn on it)."""
    data, scene, face = _fresh(sample)
    bpy.ops.facelab.new_lip_sketch()
    gp = scene.facelab.sketch
    up, lo = sample[2][FRAME]
    cam = camera_from_blender(scene)
    if draw:
        write_stroke_pixels(gp, "Upper lip", FRAME, [up], cam)
        write_stroke_pixels(gp, "Lower lip", FRAME, [lo], cam)
    return data, scene, face, gp, cam, (up, lo)


def _view3d_perspectives():
    return [a.spaces.active.region_3d.view_perspective for a in bpy.context.screen.areas if a.type == "VIEW_3D"]


def test_new_lip_sketch_leaves_the_artist_drawing_on_the_upper_lip(sample):
    data, scene, face = _fresh(sample)
    assert _view3d_perspectives() == ["PERSP"]
    assert bpy.ops.facelab.new_lip_sketch() == {"FINISHED"}
    gp = scene.facelab.sketch
    assert bpy.context.view_layer.objects.active == gp and gp.select_get() and not face.select_get()
    assert gp.mode == DRAW_MODE and bpy.context.mode == DRAW_MODE
    assert gp.data.layers.active.name == "Upper lip"
    assert _view3d_perspectives() == ["CAMERA"]  # the window's 3D view looks through the camera
    cam = scene.camera.data
    assert cam.show_background_images and all(bg.show_background_image for bg in cam.background_images)
    assert scene.facelab.face == face


def test_lower_lip_is_one_click_and_back(sample):
    data, scene, face = _fresh(sample)
    bpy.ops.facelab.new_lip_sketch()
    gp = scene.facelab.sketch
    assert bpy.ops.facelab.sketch_lip_layer(lip="lower") == {"FINISHED"}
    assert gp.data.layers.active.name == "Lower lip" and gp.mode == DRAW_MODE
    assert bpy.ops.facelab.sketch_lip_layer(lip="upper") == {"FINISHED"}
    assert gp.data.layers.active.name == "Upper lip"
    # from Object mode with the face active, the button takes the artist back to drawing on that lip
    bpy.ops.object.mode_set(mode="OBJECT")
    bpy.context.view_layer.objects.active = face
    assert bpy.ops.facelab.sketch_lip_layer(lip="lower") == {"FINISHED"}
    assert bpy.context.view_layer.objects.active == gp and gp.mode == DRAW_MODE
    assert gp.data.layers.active.name == "Lower lip"


def test_lip_layer_needs_a_sketch(sample):
    data, scene, face = _fresh(sample)
    scene.facelab.sketch = None
    assert not bpy.ops.facelab.sketch_lip_layer.poll()


def test_refine_runs_from_draw_mode_and_stays_there_and_undo_restores(sample):
    from facelab_addon.blender.mesh import evaluated_vertices

    data, scene, face, gp, cam, (up, lo) = _sketch(sample, draw=True)
    X0 = evaluated_vertices(face, bpy.context.evaluated_depsgraph_get())
    bpy.ops.ed.undo_push(message="sketched")
    assert bpy.context.mode == DRAW_MODE
    assert bpy.ops.facelab.refine_lips.poll()  # was: "Switch to Object Mode to refine"
    assert bpy.ops.facelab.refine_lips() == {"FINISHED"}
    bpy.ops.ed.undo_push(message="Refine Lips")
    assert bpy.context.mode == DRAW_MODE and bpy.context.view_layer.objects.active == gp
    X1 = evaluated_vertices(face, bpy.context.evaluated_depsgraph_get())
    assert np.abs(X1 - X0).max() > 1e-4  # the lips moved (> 0.1 mm)
    assert f"FL_Refine_{FRAME:04d}" in face.data.shape_keys.key_blocks
    name = face.name
    bpy.ops.ed.undo()
    face = bpy.data.objects[name]
    assert bpy.context.object.type == "GREASEPENCIL" and bpy.context.mode == DRAW_MODE
    assert not [k for k in face.data.shape_keys.key_blocks if k.name.startswith(PREFIX)]
    np.testing.assert_allclose(evaluated_vertices(face, bpy.context.evaluated_depsgraph_get()), X0, atol=1e-7)


def _contour_error(P, truth):
    """Mean distance (px) of the points ``P`` (N,2) from the polyline ``truth`` (M,2)."""
    a, b = truth[:-1], truth[1:]
    ab = b - a
    t = np.clip(np.einsum("nmk,mk->nm", P[:, None] - a[None], ab) / np.maximum((ab * ab).sum(1), 1e-12), 0, 1)
    d = np.linalg.norm(P[:, None] - (a[None] + t[..., None] * ab[None]), axis=2)
    return d.min(1)


def test_snap_to_plate_brings_jittered_strokes_onto_the_rendered_lip_line(sample):
    from facelab_addon.testing.route import jitter_stroke

    data, scene, face, gp, cam, (up, lo) = _sketch(sample)
    rng = np.random.default_rng(3)
    drawn = {"upper": jitter_stroke(up, 3.0, rng), "lower": jitter_stroke(lo, 3.0, rng)}
    write_stroke_pixels(gp, "Upper lip", FRAME, [drawn["upper"]], cam)
    write_stroke_pixels(gp, "Lower lip", FRAME, [drawn["lower"]], cam)
    plain = read_lip_strokes(scene, cam, FRAME, gp_obj=gp)
    assert SNAP_REPORT_PROP not in gp  # off by default
    gp[SNAP_PROP] = True
    snapped = read_lip_strokes(scene, cam, FRAME, gp_obj=gp)
    report = gp[SNAP_REPORT_PROP]
    n = len(drawn["upper"]) + len(drawn["lower"])
    moved = sum(int(np.any(a != b)) for lab in ("upper", "lower") for a, b in zip(snapped[lab][0], plain[lab][0]))
    assert report.startswith(f"snapped {moved} of {n} points"), report
    # the lower lip's inner edge (lit lip against the dark mouth) is on the plate: the stroke lands on it
    before = _contour_error(plain["lower"][0], lo)
    after = _contour_error(snapped["lower"][0], lo)
    on_edge = np.any(snapped["lower"][0] != plain["lower"][0], axis=1)
    assert on_edge.mean() > 0.7 and np.median(after[on_edge]) < 0.4, (on_edge.mean(), np.median(after[on_edge]))
    assert before.mean() > 1.5 and after.mean() < 0.35 * before.mean(), (before.mean(), after.mean())
    before, after = before.mean(), after.mean()
    print(f"upper {_contour_error(plain['upper'][0], up).mean():.2f} -> "
          f"{_contour_error(snapped['upper'][0], up).mean():.2f} px; lower {before:.2f} -> {after:.2f} px; {report}")
    # the strokes drawn are untouched: reading without snapping gives them back
    again = read_lip_strokes(scene, cam, FRAME, gp_obj=gp, snap=False)
    np.testing.assert_allclose(again["upper"][0], plain["upper"][0], atol=1e-6)
    # Refine Lips and Live Refine read them snapped
    from facelab_addon.pipeline.live_refine import LiveRefine

    live = LiveRefine(scene, face, sketch=gp)
    np.testing.assert_allclose(live.views()[0].lower[0], snapped["lower"][0], atol=1e-9)
    live.discard()
    del gp[SNAP_REPORT_PROP]
    assert bpy.ops.facelab.refine_lips() == {"FINISHED"}
    assert gp[SNAP_REPORT_PROP] == report


def _select_strokes(gp, layer_name, frame, which):
    """Select (in the drawing's point selection) the points of the strokes ``which`` (indices) only."""
    layer = next(lay for lay in gp.data.layers if lay.name.lower() == layer_name.lower())
    d = layer.get_frame_at(frame).drawing
    offsets = np.empty(len(d.curve_offsets), np.int32)
    d.curve_offsets.foreach_get("value", offsets)
    sel = d.attributes.get(".selection") or d.attributes.new(".selection", "BOOLEAN", "POINT")
    vals = np.zeros(int(offsets[-1]), bool)
    for i in which:
        vals[offsets[i]:offsets[i + 1]] = True
    sel.data.foreach_set("value", vals)
    return d


def test_snap_is_a_per_stroke_choice(sample):
    from facelab_addon.blender.strokes import stroke_snap_choices
    from facelab_addon.testing.route import jitter_stroke

    data, scene, face, gp, cam, (up, lo) = _sketch(sample)
    rng = np.random.default_rng(5)
    k = len(lo) // 2
    halves = [jitter_stroke(lo[:k + 1], 3.0, rng), jitter_stroke(lo[k:], 3.0, rng)]  # the lower lip in 2 strokes
    write_stroke_pixels(gp, "Upper lip", FRAME, [jitter_stroke(up, 3.0, rng)], cam)
    write_stroke_pixels(gp, "Lower lip", FRAME, halves, cam)
    plain = read_lip_strokes(scene, cam, FRAME, gp_obj=gp)
    assert SNAP_REPORT_PROP not in gp  # nothing asks for snapping yet
    # Snap Selected Strokes on the first half only, the sketch's option off: that stroke alone is read snapped
    d = _select_strokes(gp, "Lower lip", FRAME, [0])
    assert bpy.ops.facelab.snap_selected_strokes(choice="ON") == {"FINISHED"}
    np.testing.assert_array_equal(stroke_snap_choices(d), [1, 0])
    got = read_lip_strokes(scene, cam, FRAME, gp_obj=gp)
    first = _contour_error(got["lower"][0], lo)
    assert first.mean() < 0.5 * _contour_error(plain["lower"][0], lo).mean(), first.mean()
    np.testing.assert_array_equal(got["lower"][1], plain["lower"][1])
    np.testing.assert_array_equal(got["upper"][0], plain["upper"][0])
    n = len(plain["lower"][0])
    assert gp[SNAP_REPORT_PROP].startswith("snapped ") and f" of {n} points" in gp[SNAP_REPORT_PROP]
    # the sketch's option on, the first half set to Never: every other stroke is snapped, that one is not
    assert bpy.ops.facelab.snap_selected_strokes(choice="OFF") == {"FINISHED"}
    gp[SNAP_PROP] = True
    got = read_lip_strokes(scene, cam, FRAME, gp_obj=gp)
    np.testing.assert_array_equal(got["lower"][0], plain["lower"][0])
    assert np.any(got["lower"][1] != plain["lower"][1]) and np.any(got["upper"][0] != plain["upper"][0])
    # back to As Sketch: the first half follows the option again; snap=False still reads all as drawn
    assert bpy.ops.facelab.snap_selected_strokes(choice="SKETCH") == {"FINISHED"}
    got = read_lip_strokes(scene, cam, FRAME, gp_obj=gp)
    assert np.any(got["lower"][0] != plain["lower"][0])
    none = read_lip_strokes(scene, cam, FRAME, gp_obj=gp, snap=False)
    for lab in ("upper", "lower"):
        for a, b in zip(none[lab], plain[lab]):
            np.testing.assert_array_equal(a, b)
    # no stroke selected: the operator says so and changes nothing
    _select_strokes(gp, "Lower lip", FRAME, [])
    _select_strokes(gp, "Upper lip", FRAME, [])
    assert bpy.ops.facelab.snap_selected_strokes(choice="ON") == {"CANCELLED"}
    np.testing.assert_array_equal(stroke_snap_choices(d), [0, 0])
    # nothing snapped any more: no stale report
    gp[SNAP_PROP] = False
    read_lip_strokes(scene, cam, FRAME, gp_obj=gp)
    assert SNAP_REPORT_PROP not in gp
    # during Live Refine the preview follows a stroke's new choice at once
    from facelab_addon.ui import ops_live

    assert bpy.ops.facelab.live_refine() == {"FINISHED"}
    try:
        before = ops_live.session().views()[0].lower[0].copy()
        np.testing.assert_array_equal(before, plain["lower"][0])
        X0 = ops_live.session().preview_vertices().copy()
        _select_strokes(gp, "Lower lip", FRAME, [0])
        assert bpy.ops.facelab.snap_selected_strokes(choice="ON") == {"FINISHED"}
        after = ops_live.session().views()[0].lower[0]
        assert _contour_error(after, lo).mean() < 0.5 * _contour_error(before, lo).mean()
        assert np.abs(ops_live.session().preview_vertices() - X0).max() > 0
    finally:
        assert bpy.ops.facelab.live_refine_discard() == {"FINISHED"}


def _write_movie(path, files):
    """An H.264 movie of the image files, written by Blender's FFmpeg (a scene of its own, removed again)."""
    sc = bpy.data.scenes.new("movie writer")
    try:
        seq = sc.sequence_editor_create()
        strips = seq.strips if hasattr(seq, "strips") else seq.sequences
        st = strips.new_image("p", str(files[0]), 1, 1)
        for f in files[1:]:
            st.elements.append(f.name)
        r = sc.render
        r.resolution_x, r.resolution_y = st.elements[0].orig_width, st.elements[0].orig_height
        r.resolution_percentage = 100
        sc.frame_start, sc.frame_end = 1, len(files)
        if hasattr(r.image_settings, "media_type"):  # Blender 5.0+
            r.image_settings.media_type = "VIDEO"
        r.image_settings.file_format = "FFMPEG"
        r.ffmpeg.format, r.ffmpeg.codec, r.ffmpeg.constant_rate_factor = "MPEG4", "H264", "PERC_LOSSLESS"
        r.use_sequencer = True
        sc.view_settings.view_transform = "Standard"
        r.filepath = str(path)
        with bpy.context.temp_override(scene=sc):
            bpy.ops.render.render(animation=True, scene=sc.name)
    finally:
        bpy.data.scenes.remove(sc)


def test_snap_reads_a_movie_clip_frame_by_frame(sample, tmp_path):
    from facelab_addon.blender.plate import plate_file, plate_pixels
    from facelab_addon.blender.sketch_snap import plate_image, snap_to_plate
    from facelab_addon.testing.route import jitter_stroke

    if not bpy.app.build_options.codec_ffmpeg:
        pytest.skip("this Blender has no FFmpeg")
    data, scene, face, gp, cam, (up, lo) = _sketch(sample)
    cam_obj = scene.camera
    seq_clip = cam_obj.data.background_images[0].clip
    files = [plate_file(cam_obj, f) for f in range(FRAME - 3, FRAME + 1)]
    movie = tmp_path / "plate.mp4"
    _write_movie(movie, files)
    clip = bpy.data.movieclips.load(str(movie))
    assert clip.source == "MOVIE"
    try:
        cam_obj.data.background_images[0].clip = clip
        clip.frame_start = FRAME - 3  # the movie's first frame is the sequence's frame FRAME - 3
        got = plate_image(cam_obj, FRAME)
        ref = [plate_pixels(f)[..., :3] for f in files]
        assert got.shape[:2] == ref[-1].shape[:2]
        both = np.vstack([up, lo])
        (x0, y0), (x1, y1) = (both.min(0) - 20).astype(int), (both.max(0) + 20).astype(int)
        d = [float(np.abs(got[y0:y1, x0:x1, :3] - r[y0:y1, x0:x1]).mean()) for r in ref]  # around the mouth
        assert d[-1] < 0.01 and d[-1] < 0.6 * min(d[:-1]), d  # the frame shown, not its neighbours
        # the movie's frame snaps as the image sequence's does
        rng = np.random.default_rng(11)
        drawn = {"upper": [jitter_stroke(up, 3.0, rng)], "lower": [jitter_stroke(lo, 3.0, rng)]}
        from_movie, report = snap_to_plate(cam_obj, cam, FRAME, drawn)
        assert report.startswith("snapped ")
        cam_obj.data.background_images[0].clip = seq_clip
        from_seq, _ = snap_to_plate(cam_obj, cam, FRAME, drawn)
        before = _contour_error(drawn["lower"][0], lo).mean()
        after = _contour_error(from_movie["lower"][0], lo).mean()
        assert after < 0.35 * before, (before, after)
        assert np.median(np.linalg.norm(from_movie["lower"][0] - from_seq["lower"][0], axis=1)) < 0.1
        cam_obj.data.background_images[0].clip = clip
        with pytest.raises(PlateError, match="no frame for scene frame"):
            plate_image(cam_obj, FRAME + 5)
    finally:
        cam_obj.data.background_images[0].clip = seq_clip
        bpy.data.movieclips.remove(clip)


# --------------------------------------------------------------------------- Live Refine
def _half(P, first=True):
    k = len(P) // 2
    return P[: k + 1] if first else P[k:]


def test_live_refine_stroke_by_stroke_then_accept_is_a_refine(sample):
    from facelab_addon.blender.caches import evaluate_frames
    from facelab_addon.blender.mesh import evaluated_vertices
    from facelab_addon.blender.ownership import key_matches, owned_keys
    from facelab_addon.pipeline.live_refine import PREVIEW_KEY, LiveRefine

    data, scene, face, gp, cam, (up, lo) = _sketch(sample)
    X0 = evaluated_vertices(face, bpy.context.evaluated_depsgraph_get())
    bpy.ops.ed.undo_push(message="before Live Refine")
    live = LiveRefine(scene, face, sketch=gp)
    # first strokes: half of each lip
    write_stroke_pixels(gp, "Upper lip", FRAME, [_half(up)], cam)
    write_stroke_pixels(gp, "Lower lip", FRAME, [_half(lo)], cam)
    u1 = live.update()
    keys = face.data.shape_keys
    kb = keys.key_blocks[PREVIEW_KEY]
    assert kb.value == 1.0 and u1.n_free > 0 and u1.max_move > 1e-4
    X1 = evaluated_vertices(face, bpy.context.evaluated_depsgraph_get())
    np.testing.assert_allclose(X1, live.preview_vertices(), atol=1e-6)  # the preview shows the solve
    # nothing else reads the preview: not FaceLab's recorded output, no training frame, not the capture
    assert PREVIEW_KEY not in owned_keys(face) and len(face.facelab.training_frames) == 0
    assert key_matches(keys, PREVIEW_KEY, (PREFIX,))
    np.testing.assert_allclose(evaluate_frames(face, [FRAME], mute_shape_keys_prefix=(PREFIX,))[0], X0, atol=1e-6)
    # the other halves: the preview follows
    write_stroke_pixels(gp, "Upper lip", FRAME, [_half(up, False)], cam)
    write_stroke_pixels(gp, "Lower lip", FRAME, [_half(lo, False)], cam)
    live.update()
    X2 = live.preview_vertices()
    assert np.abs(X2 - X1).max() > 1e-5
    region = live.region()
    moved = np.linalg.norm(X2 - X0, axis=1) > 1e-9
    assert moved.any() and not (moved & ~region).any()  # only the drawn region moves
    # Accept: a Refine of the same strokes, the preview gone
    r = live.accept()
    assert PREVIEW_KEY not in face.data.shape_keys.key_blocks
    assert r.shape_key == f"FL_Refine_{FRAME:04d}" and r.shape_key in owned_keys(face)
    assert [t.frame for t in face.facelab.training_frames] == [FRAME]
    X3 = evaluated_vertices(face, bpy.context.evaluated_depsgraph_get())
    d_px = np.abs(cam.project(X3) - cam.project(X2)).max()
    assert d_px < 0.05, d_px  # the preview is what Refine makes
    with pytest.raises(Exception, match="closed"):
        live.update()
    # undo after Accept restores the frame
    bpy.ops.ed.undo_push(message="Accept")
    name = face.name
    bpy.ops.ed.undo()
    face = bpy.data.objects[name]
    assert not [k for k in face.data.shape_keys.key_blocks if k.name.startswith(PREFIX)]
    assert len(face.facelab.training_frames) == 0
    np.testing.assert_allclose(evaluated_vertices(face, bpy.context.evaluated_depsgraph_get()), X0, atol=1e-7)


def test_live_refine_keeps_its_solver_between_strokes_and_rebuilds_for_new_settings(sample):
    from dataclasses import replace

    from facelab_addon.core.lips.sketch import refine_lips_views
    from facelab_addon.pipeline.live_refine import LiveRefine

    data, scene, face, gp, cam, (up, lo) = _sketch(sample, draw=True)
    live = LiveRefine(scene, face, sketch=gp)

    def full_refine():  # the same strokes and settings solved from scratch, as Accept's Refine solves them
        w = live.problem.weld
        V, tris, fixed, lips, rest = live.problem.solver_face()
        X = refine_lips_views(V, tris, live.views(), live.refine_settings().params(), fixed=fixed, lips=lips,
                              rest_vertices=rest)
        return X if w is None else live.problem.capture + w.uncompact(X - V)

    u1 = live.update()
    X1 = live.preview_vertices()
    assert u1.rebuilt and np.abs(X1 - full_refine()).max() <= 1e-9 * np.abs(X1).max()
    u2 = live.update()  # nothing the solve reads changed: the kept system, the same preview
    assert not u2.rebuilt and np.abs(live.preview_vertices() - X1).max() <= 1e-9 * np.abs(X1).max()
    live.settings = replace(live.settings, smooth_reach=0.2)  # new settings: a new solver
    u3 = live.update()
    X3 = live.preview_vertices()
    assert u3.rebuilt and np.abs(X3 - X1).max() > 1e-6
    assert np.abs(X3 - full_refine()).max() <= 1e-9 * np.abs(X3).max()
    live.discard()


def test_live_refine_discard_leaves_nothing(sample):
    from facelab_addon.blender.mesh import evaluated_vertices
    from facelab_addon.pipeline.live_refine import LiveRefine

    data, scene, face, gp, cam, (up, lo) = _sketch(sample)
    names = [k.name for k in face.data.shape_keys.key_blocks]
    X0 = evaluated_vertices(face, bpy.context.evaluated_depsgraph_get())
    live = LiveRefine(scene, face, sketch=gp)
    write_stroke_pixels(gp, "Upper lip", FRAME, [up], cam)
    write_stroke_pixels(gp, "Lower lip", FRAME, [lo], cam)
    live.update()
    live.discard()
    assert [k.name for k in face.data.shape_keys.key_blocks] == names
    assert len(face.facelab.training_frames) == 0 and "facelab_live_basis" not in face
    np.testing.assert_allclose(evaluated_vertices(face, bpy.context.evaluated_depsgraph_get()), X0, atol=1e-7)


def test_live_refine_on_a_face_without_keys_removes_the_basis_it_made(sample):
    from facelab_addon.blender.scene import new_mesh_object
    from facelab_addon.pipeline.live_refine import LiveRefine

    data, scene, face = _fresh(sample)
    pv, po = data.poly_verts, data.poly_offsets
    plain = new_mesh_object("Plain", data.captured()[FRAME - 1], poly_verts=pv, poly_offsets=po)
    bpy.ops.facelab.new_lip_sketch()
    gp = scene.facelab.sketch
    up, lo = sample[2][FRAME]
    cam = camera_from_blender(scene)
    write_stroke_pixels(gp, "Upper lip", FRAME, [up], cam)
    write_stroke_pixels(gp, "Lower lip", FRAME, [lo], cam)
    live = LiveRefine(scene, plain, sketch=gp)
    live.update()
    assert plain.data.shape_keys is not None
    live.discard()
    assert plain.data.shape_keys is None
    bpy.data.objects.remove(plain)


def test_influence_in_mm_sets_the_free_region_through_the_face_mouth_width(sample):
    from facelab_addon.pipeline.live_refine import LiveRefine, influence_to_mouth_widths

    data, scene, face, gp, cam, (up, lo) = _sketch(sample, draw=True)
    regions = {}
    for mm in (2.0, 8.0):
        live = LiveRefine(scene, face, sketch=gp, influence_mm=mm)
        u = live.update()
        # metres scene: mm = free_radius x mouth width (m) x 1000
        assert u.free_radius == pytest.approx(mm / (live.mouth_width * 1000.0))
        assert u.influence_mm == pytest.approx(mm)
        assert live.refine_settings().free_radius == pytest.approx(u.free_radius)
        # the free region reaches about `mm` from the lips the sketch matched, and no farther
        regions[mm] = live.region()
        live.discard()
    assert regions[2.0].sum() < regions[8.0].sum() and not (regions[2.0] & ~regions[8.0]).any()
    assert influence_to_mouth_widths(5.0, 0.05, 1000.0) == pytest.approx(0.1)  # 5 mm of a 50 mm mouth
    assert influence_to_mouth_widths(5.0, 5.0, 10.0) == pytest.approx(0.1)  # centimetre units


def test_live_refine_operators_drive_a_session_stroke_by_stroke(sample):
    from facelab_addon.blender.mesh import evaluated_vertices
    from facelab_addon.pipeline.live_refine import PREVIEW_KEY
    from facelab_addon.ui import ops_live

    data, scene, face, gp, cam, (up, lo) = _sketch(sample)
    assert not bpy.ops.facelab.live_refine_accept.poll() and not bpy.ops.facelab.live_refine_update.poll()
    scene.facelab_live.influence_mm = 6.0
    assert bpy.ops.facelab.live_refine() == {"FINISHED"}  # from Draw mode; no stroke yet: waiting
    assert "waiting" in ops_live.LIVE["message"] and PREVIEW_KEY not in face.data.shape_keys.key_blocks
    assert ops_live.on_depsgraph_update in bpy.app.handlers.depsgraph_update_post
    write_stroke_pixels(gp, "Upper lip", FRAME, [up], cam)
    write_stroke_pixels(gp, "Lower lip", FRAME, [lo], cam)
    ops_live.on_depsgraph_update(scene)  # what Blender calls after the stroke (headless: by hand)
    assert PREVIEW_KEY in face.data.shape_keys.key_blocks and "Influence 6.0 mm" in ops_live.LIVE["message"]
    P = ops_live.influence_points()
    assert len(P) == ops_live.session().region().sum() > 0
    n6 = len(P)
    scene.facelab_live.influence_mm = 3.0  # the Influence updates the preview live
    assert 0 < len(ops_live.influence_points()) < n6 and "Influence 3.0 mm" in ops_live.LIVE["message"]
    X = ops_live.session().preview_vertices()
    assert bpy.ops.facelab.live_refine_accept() == {"FINISHED"}
    assert ops_live.session() is None and ops_live.on_depsgraph_update not in bpy.app.handlers.depsgraph_update_post
    assert PREVIEW_KEY not in face.data.shape_keys.key_blocks
    assert f"FL_Refine_{FRAME:04d}" in face.data.shape_keys.key_blocks
    d = cam.project(evaluated_vertices(face, bpy.context.evaluated_depsgraph_get())) - cam.project(X)
    assert np.abs(d).max() < 0.05
    assert bpy.context.mode == DRAW_MODE  # the artist is still drawing
    # Discard: nothing left
    n_keys = len(face.data.shape_keys.key_blocks)
    assert bpy.ops.facelab.live_refine() == {"FINISHED"}
    assert PREVIEW_KEY in face.data.shape_keys.key_blocks
    assert bpy.ops.facelab.live_refine_discard() == {"FINISHED"}
    assert len(face.data.shape_keys.key_blocks) == n_keys and ops_live.session() is None


def test_undo_during_live_refine_ends_it_and_drops_the_preview(sample):
    from facelab_addon.pipeline.live_refine import PREVIEW_KEY
    from facelab_addon.ui import ops_live

    data, scene, face, gp, cam, (up, lo) = _sketch(sample, draw=True)
    bpy.ops.ed.undo_push(message="drawn")
    assert bpy.ops.facelab.live_refine() == {"FINISHED"}
    bpy.ops.ed.undo_push(message="a stroke while live")  # a state holding the preview key
    bpy.ops.ed.undo()
    bpy.ops.ed.redo()  # back to the state with the preview: the handler ends the session and drops it
    assert ops_live.session() is None
    assert PREVIEW_KEY not in bpy.context.scene.facelab.face.data.shape_keys.key_blocks


def test_plate_file_follows_the_clip_and_image_sequences_frame_by_frame(sample):
    from pathlib import Path

    from facelab_addon.blender.plate import PlateError, plate_file, plate_pixels

    data, scene, face = _fresh(sample)
    cam = scene.camera
    clip = cam.data.background_images[0].clip
    assert plate_file(cam, 20).name == "plate_0020.jpg"
    start = clip.frame_start
    try:
        clip.frame_start = 11  # the footage's first frame shows on scene frame 11
        assert plate_file(cam, 20).name == "plate_0010.jpg"
        with pytest.raises(PlateError, match="no image for frame 60"):
            plate_file(cam, 60)
    finally:
        clip.frame_start = start
    px = plate_pixels(plate_file(cam, 20))
    assert px.shape[:2] == (data.camera.height, data.camera.width)
    # the plate's top rows are the image's top (Blender stores rows bottom-up)
    from PIL import Image

    ref = np.asarray(Image.open(plate_file(cam, 20)), dtype=np.float64) / 255
    assert np.abs(px[..., :3] - ref).mean() < 0.02
    # the same footage as an Image sequence behind another camera
    other = bpy.data.objects.new("Seq cam", cam.data.copy())
    scene.collection.objects.link(other)
    other.data.background_images.clear()
    bg = other.data.background_images.new()
    img = bpy.data.images.load(str(Path(plate_file(cam, 1))))
    img.source = "SEQUENCE"
    bg.image = img
    iu = bg.image_user
    iu.frame_start, iu.frame_offset, iu.frame_duration = 1, 0, 48
    assert plate_file(other, 7).name == "plate_0007.jpg"
    iu.frame_start, iu.frame_offset = 3, 2  # from scene frame 3, starting at the third image
    assert plate_file(other, 7).name == "plate_0007.jpg" and plate_file(other, 3).name == "plate_0003.jpg"
    iu.frame_duration = 4  # held on its last image after 4 frames, as Blender shows it
    assert plate_file(other, 20).name == "plate_0006.jpg"
    iu.use_cyclic = True
    assert plate_file(other, 8).name == "plate_0004.jpg"
    img.source = "FILE"
    assert plate_file(other, 7).name == "plate_0001.jpg"  # a still is the plate of every frame
    assert plate_file(face, 7) is None  # not a camera
    bpy.data.objects.remove(other)


def test_live_refine_on_a_mirrored_face_previews_what_accept_writes(sample):
    """A face mirrored by its object scale (-1 in x, as an artist flips an import): the preview solves on the
    world winding Refine uses, so Accept writes what the preview showed."""
    from facelab_addon.blender.mesh import evaluated_vertices
    from facelab_addon.pipeline.live_refine import LiveRefine

    data, scene, face = _fresh(sample)
    face.scale.x = -face.scale.x
    try:
        bpy.context.view_layer.update()
        bpy.ops.facelab.new_lip_sketch()
        gp = scene.facelab.sketch
        cam = camera_from_blender(scene)
        up, lo = sample[2][FRAME]  # the sample's face is symmetric: its mirror image keeps these lip lines
        write_stroke_pixels(gp, "Upper lip", FRAME, [up], cam)
        write_stroke_pixels(gp, "Lower lip", FRAME, [lo], cam)
        live = LiveRefine(scene, face, sketch=gp)
        u = live.update()
        assert u.max_move > 1e-5
        X_preview = live.preview_vertices()
        live.accept()
        X = evaluated_vertices(face, bpy.context.evaluated_depsgraph_get())
        d_px = np.abs(cam.project(X) - cam.project(X_preview)).max()
        assert d_px < 0.05, d_px
    finally:
        face.scale.x = -face.scale.x
