"""Headless end to end for Bhat et al. 2013 in Blender: an ICT face rig, a helmet stereo pair, one Movie Clip per
camera with tracks = the truth's projected surface points, inner-lip contours as a shape-keyed Mask (view 1) and a
Grease Pencil sketch (view 2) -> Bind Tracks -> Solve Performance (keyed weights = truth, correctives keyed) ->
Retarget to a wide-mouthed creature; plus the bad-input messages."""

import time

import bpy
import numpy as np
import pytest

from facelab_addon.blender import compat
from facelab_addon.blender.camera import apply_camera_to_blender
from facelab_addon.blender.scene import new_mesh_object
from facelab_addon.blender.shapekeys import key_values_bulk
from facelab_addon.blender.strokes import write_stroke_pixels
from facelab_addon.testing.capture_sim import helmet_cameras, sample_markers
from facelab_addon.testing.scenes import build_ict_face_scene, keyed_empties
from facelab_addon.testing.synthetic import ICT_MOUTH_LOOP

pytestmark = pytest.mark.blender

SCALE = 0.01  # ICT centimetres -> metres
EXPR = ["jawOpen", "mouthSmile_L", "mouthSmile_R", "mouthFunnel", "mouthPucker", "browInnerUp_L"]
EXTRA = "cheekPuff_L"  # not in the rig: out of the rig's span, for the corrective
T = 5  # frames 0..4; frame 0 is the neutral (bind frame)
W_TRUTH = np.array([
    [0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
    [0.45, 0.3, 0.0, 0.0, 0.2, 0.5],
    [0.2, 0.0, 0.5, 0.3, 0.0, 0.0],
    [0.3, 0.2, 0.2, 0.0, 0.0, 0.3],
    [0.1, 0.5, 0.4, 0.0, 0.3, 0.0],
])
EXTRA_W = np.array([0.0, 0.0, 0.0, 0.7, 0.7])
SIZE = (540, 960)
N_MASK_POINTS = 24


def _resample(P, n):
    """n points equally spaced by arc length along a polyline."""
    s = np.r_[0, np.cumsum(np.linalg.norm(np.diff(P, axis=0), axis=1))]
    u = np.linspace(0, s[-1], n)
    return np.c_[np.interp(u, s, P[:, 0]), np.interp(u, s, P[:, 1])]


def _clip(tmp_path, name, cam):
    from PIL import Image

    d = tmp_path / name
    d.mkdir()
    img = Image.fromarray(np.zeros((SIZE[1], SIZE[0], 3), np.uint8))
    for i in range(1, T + 1):
        img.save(d / f"{name}_{i:04d}.png")
    clip = bpy.data.movieclips.load(str(d / f"{name}_0001.png"))
    clip.frame_start = 0  # scene frame 0 = clip frame 1
    tc = clip.tracking.camera
    tc.sensor_width = 36.0
    tc.focal_length = cam.K[0, 0] * 36.0 / SIZE[0]
    tc.principal_point_pixels = (cam.K[0, 2], SIZE[1] - cam.K[1, 2])
    return clip


def _clip_editor(clip, mask):
    win = bpy.context.window_manager.windows[0]
    area = win.screen.areas[-1]
    area.type = "CLIP_EDITOR"
    space = area.spaces.active
    space.clip, space.mode, space.mask = clip, "MASK", mask
    return dict(window=win, area=area, region=next(r for r in area.regions if r.type == "WINDOW"), space_data=space)


def _px_to_mask(px):
    """Inverse of masks.mask_to_pixels for the portrait SIZE (x is scaled about 0.5 by W/H)."""
    W, H = SIZE
    u, v = px[:, 0] / W, 1.0 - px[:, 1] / H
    return np.c_[(u - 0.5) * (W / H) + 0.5, v]


def build(ict, tmp_path):
    fs = build_ict_face_scene(ict, EXPR, frame_range=(0, T - 1), scale=SCALE, fixed_group=True, select=False)
    scene, obj, neutral, D = fs.scene, fs.obj, fs.neutral, fs.deltas
    extra = (ict.expressions[EXTRA] - ict.neutral) * SCALE
    truth = neutral[None] + np.einsum("ts,svd->tvd", W_TRUTH, D) + EXTRA_W[:, None, None] * extra[None]

    cams = helmet_cameras(center=np.array([0.0, -1.0, 8.0]) * SCALE, cm=SCALE, focal_px=600.0, width=SIZE[0],
                          height=SIZE[1])
    skin = ict.part_face_mask("M_Face")
    excl = np.concatenate([neutral[ICT_MOUTH_LOOP], neutral[ict.part_vertex_mask("M_ScleraLeft", "M_ScleraRight")]])
    markers = sample_markers(neutral, ict.faces, cams, skin, n=50, seed=3, exclude=excl, exclude_radius=0.009)
    X = markers.evaluate(truth)  # (T,M,3)
    views = []
    s = scene.facelab_solve
    for c, cam in enumerate(cams):
        cam_obj = bpy.data.objects.new(f"Cam{c}", bpy.data.cameras.new(f"Cam{c}"))
        scene.collection.objects.link(cam_obj)
        apply_camera_to_blender(cam, cam_obj, scene)
        clip = _clip(tmp_path, f"cam{c}", cam)
        for j in range(len(markers)):
            tr = clip.tracking.tracks.new(name=f"M{j:02d}", frame=1)
            for f in range(2, T + 1):
                tr.markers.insert_frame(f)
            px = cam.project(X[:, j])
            tr.markers.foreach_set("co", np.c_[px[:, 0] / SIZE[0], 1 - px[:, 1] / SIZE[1]].astype(np.float32).ravel())
        v = s.views.add()
        v.camera, v.clip = cam_obj, clip
        views.append((cam_obj, clip, cam))
    scene.camera = views[0][0]
    return scene, obj, cams, markers, truth, views


def add_contours(ict, scene, obj, views, truth, cams):
    """Inner-lip contours of the truth: a shape-keyed Mask over clip 1, Grease Pencil strokes in camera 2."""
    from facelab_addon.core.solve.contour_loops import contour_loops
    from facelab_addon.testing.contour_truth import synthetic_tracked_curves

    fixed = ~ict.part_vertex_mask("M_Face")
    eyeballs = {"left": np.flatnonzero(ict.part_vertex_mask("M_ScleraLeft")),
                "right": np.flatnonzero(ict.part_vertex_mask("M_ScleraRight"))}
    for side, ids in eyeballs.items():
        obj.vertex_groups.new(name=f"FL_eyeball_{side}").add(ids.tolist(), 1.0, "REPLACE")
    loops = contour_loops(truth[0], ict.faces, fixed=fixed, mouth_loop=ICT_MOUTH_LOOP, eyeballs=eyeballs)
    curves = [synthetic_tracked_curves(truth[t], ict.faces, cams, loops,
                                       names=["mouth_upper", "mouth_lower", "eyelid_left_upper", "eyelid_left_lower"])
              for t in range(T)]
    s = scene.facelab_solve
    mask = bpy.data.masks.new("Lips")
    mask.frame_start, mask.frame_end = 0, T - 1
    layers = {n: mask.layers.new(name=n) for n in ("Upper lip", "Lower lip")}
    splines = {}
    for n, lay in layers.items():
        sp = lay.splines.new()
        sp.points.add(N_MASK_POINTS - 1)
        splines[n] = sp
    ctx = _clip_editor(views[0][1], mask)
    gp = bpy.data.objects.new("Lips2", compat.grease_pencil_data().new("Lips2"))
    scene.collection.objects.link(gp)
    gp.location = cams[1].center + 0.05 * cams[1].forward
    got = {}
    for t in range(T):
        scene.frame_set(t)
        by = {(c.name, c.camera): c.pixels for c in curves[t]}
        for n, key in (("Upper lip", "mouth_upper"), ("Lower lip", "mouth_lower")):
            P = _resample(by[key, 0], N_MASK_POINTS)
            co = _px_to_mask(P).astype(np.float32).ravel()
            sp = splines[n]
            for attr in ("co", "handle_left", "handle_right"):
                sp.points.foreach_set(attr, co)
            for p in sp.points:
                p.select = True
            got[t, key, 0] = P
            write_stroke_pixels(gp, n, t, [by[key, 1]], cams[1])
            got[t, key, 1] = by[key, 1]
        for n, key in (("Eyelid L upper", "eyelid_left_upper"), ("Eyelid L lower", "eyelid_left_lower")):
            if (key, 1) in by:
                write_stroke_pixels(gp, n, t, [by[key, 1]], cams[1])
                got[t, key, 1] = by[key, 1]
        for lay in mask.layers:
            mask.layers.active = lay
            with bpy.context.temp_override(**ctx):
                assert bpy.ops.mask.shape_key_insert() == {"FINISHED"}
    s.views[0].mask = mask
    s.views[1].sketch = gp
    return got


@pytest.mark.slow
def test_solve_and_retarget_end_to_end(ict, addon, tmp_path):
    t_start = time.perf_counter()
    scene, obj, cams, markers, truth, views = build(ict, tmp_path)
    got_curves = add_contours(ict, scene, obj, views, truth, cams)
    bpy.context.view_layer.objects.active = obj
    obj.select_set(True)
    scene.facelab.face = obj
    s = scene.facelab_solve

    # the contours read back from Blender are the ones drawn
    from facelab_addon.blender.masks import read_curves
    from facelab_addon.blender.tracking import View, read_views

    vws = [View(v.camera, v.clip, v.mask, v.sketch) for v in s.views]
    vd = read_views(scene, vws, [2])
    np.testing.assert_allclose(vd.markers[0, 0], cams[0].project(markers.evaluate(truth[2])), atol=2e-3)
    curves, stats = read_curves(scene, vws, vd.cameras, [2, 3], resolution=1)
    assert {k: v for k, v in stats["by_name"].items() if k.startswith("mouth")} == {"mouth_upper": 4, "mouth_lower": 4}
    print("curves read:", stats)
    c = {(k.name, k.camera): k.pixels for k in curves[0]}
    np.testing.assert_allclose(c["mouth_upper", 0], got_curves[2, "mouth_upper", 0], atol=2e-3)
    np.testing.assert_allclose(c["mouth_lower", 1], got_curves[2, "mouth_lower", 1], atol=2e-3)

    # artist animation on a rig key: must survive the solve
    key = obj.data.shape_keys
    key_values_bulk(obj, ["jawOpen"], [0, 4], [[0.0], [0.9]])
    artist_action = key.animation_data.action

    # ---- Bind Tracks on the neutral frame: every marker lands on its truth surface point
    scene.frame_set(2)
    assert bpy.ops.facelab.bind_tracks(frame=0) == {"FINISHED"}
    b = obj.facelab_solve.bindings
    assert len(b) == len(markers) and obj.facelab_solve.bind_frame == 0
    from facelab_addon.blender.bindings import read_bindings
    from facelab_addon.core.capture.markers import SurfacePoints

    names, bv, bb = read_bindings(obj, "MARKER")
    assert names == [f"M{j:02d}" for j in range(len(markers))]
    np.testing.assert_allclose(SurfacePoints(bv, bb).evaluate(truth[0]), markers.evaluate(truth[0]), atol=2e-6)

    # ---- Solve Performance (the pipeline the operator runs, for its per-frame numbers)
    from facelab_addon.blender.actions import curve_values as _curve_values
    from facelab_addon.names import SOLVE_ACTION
    from facelab_addon.pipeline.solve import solve_performance
    from facelab_addon.pipeline.shot_settings import solve_settings

    t0 = time.perf_counter()
    r = solve_performance(scene, obj, solve_settings(scene))
    t_solve = time.perf_counter() - t0
    per_frame = r.core.info["frames"]
    print("contour points per frame:", [f.get("contour_points") for f in per_frame])
    assert all(f["contour_points"] > 0 for f in per_frame)  # the mask / sketch contours were fitted

    act = key.animation_data.action
    assert act is not artist_action and act.name == SOLVE_ACTION  # the artist's action is kept...
    assert artist_action.use_fake_user and artist_action.name in bpy.data.actions
    W = _curve_values(key, EXPR, np.arange(T))
    print("weight error per frame:", np.abs(W - W_TRUTH).max(axis=1))
    assert np.abs(W[:3] - W_TRUTH[:3]).max() < 0.04  # in the rig's span, up to the contour fit (see markers only below)
    assert (W >= -1).all() and (W <= 1).all()  # (frames 3-4: the rig explains cheekPuff partly by mouthPucker)
    sk = [kb.name for kb in key.key_blocks if kb.name.startswith("FL_Solve_")]
    assert sk, "no corrective keys"
    CW = _curve_values(key, sk, np.arange(T))
    assert np.abs(CW[3:]).max() > 0.1  # keyed where the truth leaves the rig's span

    # the corrective brings the markers onto the truth (out-of-subspace frames)
    from facelab_addon.blender.caches import evaluate_frames

    Vs = evaluate_frames(obj, np.arange(T), mute_shape_keys_prefix=())
    Vb = evaluate_frames(obj, np.arange(T), mute_shape_keys_prefix=("FL_Solve_",))
    for t in (3, 4):
        e_with = np.linalg.norm(cams[0].project(markers.evaluate(Vs[t])) - cams[0].project(markers.evaluate(truth[t])),
                                axis=1)
        e_without = np.linalg.norm(cams[0].project(markers.evaluate(Vb[t]))
                                   - cams[0].project(markers.evaluate(truth[t])), axis=1)
        print(f"frame {t}: marker px error without corrective {e_without.mean():.3f}, with {e_with.mean():.3f}")
        assert e_with.mean() < 0.5 * e_without.mean()

    # re-running replaces only FaceLab's own keys, in its own action
    others = [kb.name for kb in key.key_blocks if not kb.name.startswith("FL_Solve_")]
    n_actions = len(bpy.data.actions)
    assert bpy.ops.facelab.solve_performance() == {"FINISHED"}
    assert [kb.name for kb in key.key_blocks if not kb.name.startswith("FL_Solve_")] == others
    assert sorted(kb.name for kb in key.key_blocks if kb.name.startswith("FL_Solve_")) == sorted(sk)
    assert len(bpy.data.actions) == n_actions and key.animation_data.action is act
    # markers only: the weights of the frames in the rig's span are recovered exactly
    s.use_contours = False
    assert bpy.ops.facelab.solve_performance() == {"FINISHED"}
    W_m = _curve_values(key, EXPR, np.arange(T))
    print("markers only: weight error per frame:", np.abs(W_m - W_TRUTH).max(axis=1))
    assert np.abs(W_m[:3] - W_TRUTH[:3]).max() < 1e-4
    s.use_contours = True
    W = W_m

    # ---- Retarget to a creature with a wider mouth (same topology)
    from facelab_addon.testing.creature import widen_mouth

    neutral = truth[0]
    cre = new_mesh_object("Creature", widen_mouth(neutral, neutral[ICT_MOUTH_LOOP].mean(0), factor=1.5),
                          poly_verts=ict.poly_verts, poly_offsets=ict.poly_offsets)
    s.creature = cre
    t0 = time.perf_counter()
    assert bpy.ops.facelab.retarget() == {"FINISHED"}
    t_ret = time.perf_counter() - t0
    ck = cre.data.shape_keys
    assert [kb.name for kb in ck.key_blocks if not kb.name.startswith("FL_")][1:] == EXPR
    np.testing.assert_allclose(_curve_values(ck, EXPR, np.arange(T)), W, atol=1e-6)  # weights copied
    rk = [kb.name for kb in ck.key_blocks if kb.name.startswith("FL_Retarget_")]
    assert rk and np.abs(_curve_values(ck, rk, np.arange(T))).max() > 0
    # the transferred jawOpen moves the creature's chin (away from the widened mouth) like the actor's
    d_actor = np.array([p.co[:] for p in key.key_blocks["jawOpen"].data]) - neutral
    far = np.linalg.norm(neutral - neutral[ICT_MOUTH_LOOP].mean(0), axis=1) > 0.035
    chin = int(np.argmax(np.linalg.norm(d_actor, axis=1) * far * ict.part_vertex_mask("M_Face")))
    cre_rest = np.array([v.co[:] for v in cre.data.vertices])
    d_cre = np.array([p.co[:] for p in ck.key_blocks["jawOpen"].data])[chin] - cre_rest[chin]
    print("chin jawOpen delta actor", d_actor[chin], "creature", d_cre)
    assert np.linalg.norm(d_actor[chin]) > 0.005
    assert np.linalg.norm(d_cre - d_actor[chin]) < 0.2 * np.linalg.norm(d_actor[chin])
    # artist-set end points, keyed on the timeline (frame 4 differs), are used frame by frame
    from facelab_addon.pipeline.retarget import retarget
    from facelab_addon.pipeline.shot_settings import retarget_settings

    s.use_end_points = True
    s.end_points_upper, s.end_points_lower = (0.2, 0.8), (0.2, 0.8)
    scene.keyframe_insert("facelab_solve.end_points_upper", frame=0)
    s.end_points_upper = (0.3, 0.7)
    scene.keyframe_insert("facelab_solve.end_points_upper", frame=4)
    r = retarget(scene, obj, cre, retarget_settings(scene))
    eps = r.core.end_points
    np.testing.assert_allclose(eps[0].upper, [0.2, 0.8], atol=1e-6)
    np.testing.assert_allclose(eps[4].upper, [0.3, 0.7], atol=1e-6)
    np.testing.assert_allclose(eps[2].upper, [0.25, 0.75], atol=0.03)  # Bezier in between
    np.testing.assert_allclose(eps[4].lower, [0.2, 0.8], atol=1e-6)
    print(f"solve {t_solve:.1f} s, retarget {t_ret:.1f} s, test total {time.perf_counter() - t_start:.1f} s")


@pytest.mark.slow
def test_bad_input_messages(ict, addon, tmp_path):
    scene, obj, cams, markers, truth, views = build(ict, tmp_path)
    bpy.context.view_layer.objects.active = obj
    scene.facelab.face = obj
    s = scene.facelab_solve

    def run(op, **kw):
        with pytest.raises(RuntimeError) as e:
            op(**kw)
        return str(e.value)

    # tracks with no mesh binding
    assert "no track is bound" in run(bpy.ops.facelab.solve_performance)
    # a track whose marker in the second view belongs to another point is flagged when binding
    from facelab_addon.pipeline.solve import bind_tracks, solve_performance, summarise_skips
    from facelab_addon.pipeline.shot_settings import bind_settings, solve_settings

    t2 = s.views[1].clip.tracking.tracks
    co = np.array(t2["M07"].markers.find_frame(1).co)
    t2["M07"].markers.find_frame(1).co = co + [0.02, 0.0]  # 10.8 px off
    r = bind_tracks(scene, obj, 0, bind_settings(scene))
    assert r.disagree == ["M07"] and len(r.bound) == len(markers)
    t2["M07"].markers.find_frame(1).co = co
    # markers missing on some frames: skipped and reported
    clip = s.views[0].clip
    for tr in list(clip.tracking.tracks)[:5]:
        tr.markers.find_frame(3).mute = True  # clip frame 3 = scene frame 2
    assert bpy.ops.facelab.bind_tracks(frame=0) == {"FINISHED"}
    r = solve_performance(scene, obj, solve_settings(scene))
    assert r.missing == {} and not r.skipped  # the other camera still sees them
    clip2 = s.views[1].clip
    for tr in list(clip2.tracking.tracks)[:5]:
        tr.markers.find_frame(3).mute = True
    r = solve_performance(scene, obj, solve_settings(scene))
    assert r.missing == {2: 5}
    # a frame with no marker at all is skipped, with its reason
    for c in (clip, clip2):
        for tr in c.tracking.tracks:
            tr.markers.find_frame(4).mute = True
    s.use_corrective = False
    r = solve_performance(scene, obj, solve_settings(scene))
    assert list(r.skipped) == [3]
    assert "3" in summarise_skips(r.skipped)
    # cameras without calibration
    clip.tracking.camera.sensor_width = 0.0
    assert "no camera calibration" in run(bpy.ops.facelab.solve_performance)
    clip.tracking.camera.sensor_width = 36.0
    s.views[1].clip = None
    assert "has no Movie Clip" in run(bpy.ops.facelab.bind_tracks)
    s.views[1].clip = clip2
    # a rig without shape keys
    bare = new_mesh_object("Bare", truth[0], poly_verts=ict.poly_verts, poly_offsets=ict.poly_offsets)
    scene.facelab.face = bare
    assert "no shape keys" in run(bpy.ops.facelab.solve_performance)
    # a creature with no correspondence
    scene.facelab.face = obj
    blob = new_mesh_object("Blob", [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], [[0, 1, 2], [0, 1, 3], [0, 2, 3],
                                                                                   [1, 2, 3]])
    s.creature = blob
    msg = run(bpy.ops.facelab.retarget)
    assert "no correspondence" in msg and "Creature Markers" in msg


def test_bundles_bind_and_solve(ict, addon, tmp_path):
    """Empties as 3D bundles: bound to their nearest surface point, then the solve from bundles alone."""
    from facelab_addon.blender.actions import curve_values as _curve_values
    from facelab_addon.blender.bindings import read_bindings, write_bindings
    from facelab_addon.core.capture.markers import SurfacePoints

    scene, obj, cams, markers, truth, views = build(ict, tmp_path)
    bpy.context.view_layer.objects.active = obj
    scene.facelab.face = obj
    s = scene.facelab_solve
    P = markers.evaluate(truth)[:, ::2]  # 25 bundles on the truth surface
    keyed_empties(scene, P, collection="FL_bundles")
    s.bundles = "EMPTIES"
    assert bpy.ops.facelab.bind_tracks(frame=0) == {"FINISHED"}
    names, bv, bb = read_bindings(obj, "BUNDLE")
    assert names == [f"B{j:02d}" for j in range(P.shape[1])]
    np.testing.assert_allclose(SurfacePoints(bv, bb).evaluate(truth[0]), P[0], atol=1e-6)
    # bundles alone (marker bindings cleared) recover the weights in the rig's span
    write_bindings(obj, "MARKER", [], np.zeros((0, 3)), np.zeros((0, 3)))
    s.use_contours = s.use_corrective = False
    assert bpy.ops.facelab.solve_performance() == {"FINISHED"}
    W = _curve_values(obj.data.shape_keys, EXPR, np.arange(T))
    print("bundles only: weight error per frame:", np.abs(W - W_TRUTH).max(axis=1))
    assert np.abs(W[:3] - W_TRUTH[:3]).max() < 1e-4
    # a bound bundle that disappears is reported
    bpy.data.objects.remove(bpy.data.objects["B03"])
    with pytest.raises(RuntimeError, match="B03.*no longer exist.*Bind Tracks"):
        bpy.ops.facelab.solve_performance()


class _RecordingLayout:
    """Stands in for bpy.types.UILayout (not constructible headless): checks every property and operator drawn."""

    def __init__(self, seen):
        self.seen = seen

    def _sub(self, *a, **k):
        return self

    column = row = box = _sub

    def separator(self, *a, **k):
        pass

    def label(self, *a, **k):
        pass

    def prop(self, data, name, **k):
        assert name in data.bl_rna.properties, f"{type(data).__name__} has no property {name!r}"
        self.seen.append(name)

    def operator(self, idname, **k):
        mod, op = idname.split(".")
        assert hasattr(getattr(bpy.ops, mod), op) and getattr(getattr(bpy.ops, mod), op).get_rna_type(), idname
        self.seen.append(idname)
        return type("OpProps", (), {})()

    def template_list(self, listtype, list_id, data, prop, active_data, active_prop, **k):
        assert hasattr(bpy.types, listtype)
        assert prop in data.bl_rna.properties and active_prop in active_data.bl_rna.properties
        self.seen.append(prop)


def test_panel_sections_draw(addon):
    """The lead's panels call draw_solve_section / draw_retarget_section: every property and operator exists."""
    from facelab_addon.ui.panel_solve import draw_retarget_section, draw_solve_section

    bpy.ops.wm.read_factory_settings(use_empty=True)
    s = bpy.context.scene.facelab_solve
    s.views.add()
    s.bundles, s.use_end_points = "EMPTIES", True
    seen = []
    draw_solve_section(_RecordingLayout(seen), bpy.context)
    draw_retarget_section(_RecordingLayout(seen), bpy.context)
    for want in ("views", "mask", "sketch", "bundle_collection", "facelab.bind_tracks", "facelab.solve_performance",
                 "existing_animation", "creature", "creature_markers", "end_points_upper", "facelab.retarget"):
        assert want in seen, want


@pytest.mark.slow
def test_retarget_with_marker_correspondence(ict, addon, tmp_path):
    """Correspondence from empties named like the bound tracks; too few of them is refused."""
    from facelab_addon.blender.bindings import read_bindings
    from facelab_addon.core.capture.markers import SurfacePoints
    from facelab_addon.pipeline.retarget import retarget
    from facelab_addon.testing.creature import widen_mouth
    from facelab_addon.pipeline.shot_settings import retarget_settings

    scene, obj, cams, markers, truth, views = build(ict, tmp_path)
    bpy.context.view_layer.objects.active = obj
    scene.facelab.face = obj
    s = scene.facelab_solve
    s.use_contours = s.use_corrective = False
    assert bpy.ops.facelab.bind_tracks(frame=0) == {"FINISHED"}
    assert bpy.ops.facelab.solve_performance() == {"FINISHED"}
    neutral = truth[0]
    cre_rest = widen_mouth(neutral, neutral[ICT_MOUTH_LOOP].mean(0), factor=1.5)
    cre = new_mesh_object("Creature", cre_rest, poly_verts=ict.poly_verts, poly_offsets=ict.poly_offsets)
    cre.location = (0.3, 0.0, 0.0)  # empties are world space, the creature's rest is local
    s.creature, s.correspondence, s.lip_sync = cre, "MARKERS", False
    coll = bpy.data.collections.new("CreatureMarkers")
    scene.collection.children.link(coll)
    names, bv, bb = read_bindings(obj, "MARKER")
    P = SurfacePoints(bv, bb).evaluate(cre_rest) + [0.3, 0.0, 0.0]
    for n, p in list(zip(names, P))[:3]:
        e = bpy.data.objects.new(n, None)
        e.location = p
        coll.objects.link(e)
    s.creature_markers = coll
    with pytest.raises(RuntimeError, match="Only 3 creature marker empties.*need >= 4"):
        bpy.ops.facelab.retarget()
    for n, p in list(zip(names, P))[3:]:
        e = bpy.data.objects.new(n, None)
        e.location = p
        coll.objects.link(e)
    bpy.context.view_layer.update()
    r = retarget(scene, obj, cre, retarget_settings(scene))
    assert r.correspondence == f"{len(names)} markers" and r.created == EXPR
    # away from the widened mouth the creature is the actor, so its transferred shapes are the actor's there
    # (a wrong correspondence, e.g. empties read in the wrong space, gives errors of the order of the shapes)
    far = ict.part_vertex_mask("M_Face") & (np.linalg.norm(neutral - neutral[ICT_MOUTH_LOOP].mean(0), axis=1) > 0.04)
    D_actor = np.stack([(ict.expressions[n] - ict.neutral) * SCALE for n in EXPR])[:, far]
    D_cre = r.core.deltas[:, far]
    err = np.sqrt(((D_cre - D_actor) ** 2).sum() / (D_actor**2).sum())
    print(f"marker correspondence: relative RMS difference of the far-from-mouth shapes {err:.3f}")
    assert err < 0.2  # measured 0.094 (the closest-triangle correspondence is not exact near open regions)
