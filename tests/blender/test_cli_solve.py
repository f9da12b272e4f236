"""The batch ``solve`` and ``retarget`` commands on a small tracked shot made here (the construction of
test_solve_operator: ICT face with 6 rig keys, a helmet stereo pair, one Movie Clip per camera whose
tracks are the projected truth surface points over 5 frames; frames 3-4 leave the rig's span).
The CLI runs in a subprocess; its JSON is checked against the truth weights, the saved .blend
against the JSON, and bad inputs against the documented exit codes."""

import json

import bpy
import numpy as np
import pytest

from facelab_addon.blender.scene import new_mesh_object

from .test_cli import cli
from .test_solve_operator import EXPR, W_TRUTH, T, build

pytestmark = [pytest.mark.blender, pytest.mark.slow]


@pytest.fixture(scope="module")
def shots(ict, addon, tmp_path_factory):
    """SHOT.blend (views, tracks, no bindings, a creature, a mesh without keys) and broken variants."""
    from facelab_addon.testing.creature import widen_mouth
    from facelab_addon.testing.synthetic import ICT_MOUTH_LOOP

    d = tmp_path_factory.mktemp("solve_shot")
    scene, obj, cams, markers, truth, views = build(ict, d)
    neutral = truth[0]
    new_mesh_object("Creature", widen_mouth(neutral, neutral[ICT_MOUTH_LOOP].mean(0), factor=1.5),
                    poly_verts=ict.poly_verts, poly_offsets=ict.poly_offsets)
    new_mesh_object("Bare", neutral, poly_verts=ict.poly_verts, poly_offsets=ict.poly_offsets)
    e = bpy.data.objects.new("NotAMesh", None)
    scene.collection.objects.link(e)
    scene.frame_set(2)  # not the neutral: the CLI must bind on --bind-frame / the first frame, not here
    paths = {"shot": d / "SHOT.blend"}
    bpy.ops.wm.save_as_mainfile(filepath=str(paths["shot"]))
    s = scene.facelab_solve
    # frame 3 (clip frame 4) has no marker in any view: skipped, with its reason
    for v in s.views:
        for tr in v.clip.tracking.tracks:
            tr.markers.find_frame(4).mute = True
    paths["gap"] = d / "GAP.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(paths["gap"]), copy=True)
    for v in s.views:
        for tr in v.clip.tracking.tracks:
            tr.markers.find_frame(4).mute = False
    s.views[1].clip.tracking.camera.sensor_width = 0.0  # no calibration
    paths["uncalibrated"] = d / "UNCAL.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(paths["uncalibrated"]), copy=True)
    s.views[1].clip.tracking.camera.sensor_width = 36.0
    s.views.clear()
    paths["noviews"] = d / "NOVIEWS.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(paths["noviews"]), copy=True)
    return dict(paths=paths, n_markers=len(markers), dir=d)


def _curves(key, names, frames):
    from facelab_addon.blender.actions import curve_values

    return curve_values(key, names, np.asarray(frames))


def test_solve_then_retarget(shots, tmp_path):
    shot = shots["paths"]["shot"]
    solved = tmp_path / "SHOT_solved.blend"
    js = tmp_path / "solve.json"
    code, _, log = cli("solve", shot, "--object", "Face", "--frames", f"0-{T - 1}", "--bind-frame", "0",
                       "--out", solved, "--json", js)
    assert code == 0, log
    s = json.loads(js.read_text())
    assert s["ok"] and s["command"] == "solve" and s["object"] == "Face"
    assert s["frames"] == [0, T - 1] and s["frames_solved"] == T and s["skipped"] == {}
    assert [v["camera"] for v in s["views"]] == ["Cam0", "Cam1"] and all(v["size"] == [540, 960] for v in s["views"])
    b = s["bind"]
    assert b["performed"] and b["frame"] == 0 and b["bound"] == shots["n_markers"] and b["disagree"] == []
    assert s["rig_keys"] == EXPR and s["markers_bound"] == shots["n_markers"]
    # keyed weights against the truth: exact in the rig's span (frames 0-2), approximate outside it
    W = np.array([s["weights"]["values"][n] for n in EXPR]).T
    assert s["weights"]["frames"] == list(range(T)) and W.shape == (T, len(EXPR))
    print("CLI solve: weight error per frame", np.abs(W - W_TRUTH).max(axis=1))
    assert np.abs(W[:3] - W_TRUTH[:3]).max() < 1e-3
    assert np.abs(W[3:] - W_TRUTH[3:]).max() < 0.35
    for k, n in enumerate(EXPR):
        assert s["weight_range"][n] == pytest.approx([W[:, k].min(), W[:, k].max()], abs=1e-5)
    assert s["corrective"] and s["corrective_keys"] and all(k.startswith("FL_Solve_") for k in s["corrective_keys"])
    # the rig fits the markers to a fraction of a pixel in its span; worst where the truth leaves it
    rp = s["reprojection"]
    assert rp["marker_rms_px"]["max_frame"] in (3, 4) and rp["marker_rms_px"]["max"] > 0.1
    assert max(rp["per_frame"][str(f)]["marker_rms_px"] for f in range(3)) < 0.01
    assert rp["contour_rms_px"] is None and not s["contours"]
    assert s["timings"]["solve_seconds"] > 0 and "bind_seconds" in s["timings"]
    assert s["action"] == "FL_Solve" and s["saved"] == str(solved.resolve())
    assert "binding tracks on frame 0" in log and "Solved 5 frames" in log and "] solve: 5/5 (100 %)" in log

    # the saved .blend holds what the JSON says
    bpy.ops.wm.open_mainfile(filepath=str(solved))
    obj = bpy.data.objects["Face"]
    key = obj.data.shape_keys
    assert [kb.name for kb in key.key_blocks if kb.name.startswith("FL_Solve_")] == s["corrective_keys"]
    np.testing.assert_allclose(_curves(key, EXPR, range(T)), W, atol=2e-6)
    cw = _curves(key, s["corrective_keys"], range(T))
    assert np.abs(cw[3:]).max() > 0.1  # the corrective is keyed where the truth leaves the rig's span
    assert len(obj.facelab_solve.bindings) == shots["n_markers"] and obj.facelab_solve.bind_frame == 0
    assert bpy.context.scene.facelab_solve.frame_start == 0 and bpy.context.scene.facelab_solve.frame_end == T - 1

    # ---- retarget the solved shot
    out = tmp_path / "SHOT_creature.blend"
    code, r, log = cli("retarget", solved, "--object", "Face", "--creature", "Creature", "--threshold", "2",
                       "--out", out)
    assert code == 0, log
    assert r["ok"] and r["command"] == "retarget" and r["creature"] == "Creature"
    assert r["frames"] == [0, T - 1] and r["frame_count"] == T and r["correspondence"] == "same topology"
    assert r["shape_keys_created"] == EXPR and r["shape_keys_kept"] == []
    assert r["corrective_keys"] and all(k.startswith("FL_Retarget_") for k in r["corrective_keys"])
    assert r["lip_sync"] and r["threshold_mm"] == pytest.approx(2.0)
    # the creature's mouth is 1.5x wider: lip sync seals its corners on every frame
    assert r["lip_sync_end_points"]["frames_sealed"] == T
    assert r["saved"] == str(out.resolve()) and "Retargeted 5 frames to 'Creature'" in log
    bpy.ops.wm.open_mainfile(filepath=str(out))
    ck = bpy.data.objects["Creature"].data.shape_keys
    names = [kb.name for kb in ck.key_blocks]
    assert all(n in names for n in EXPR) and [n for n in names if n.startswith("FL_Retarget_")] == r["corrective_keys"]
    np.testing.assert_allclose(_curves(ck, EXPR, range(T)), W, atol=2e-6)  # the solved weights, copied
    assert np.abs(_curves(ck, r["corrective_keys"], range(T))).max() > 0
    assert bpy.context.scene.facelab_solve.lip_threshold == pytest.approx(0.002)  # 2 mm in metres


def test_skipped_frames_and_kept_bindings(shots, tmp_path, addon):
    """In this process (the code path of the subprocess minus starting Python): a frame with no
    marker is skipped with its reason; a second run keeps the bindings unless told otherwise."""
    from facelab_addon import cli as facelab_cli

    js = tmp_path / "gap.json"
    out = tmp_path / "GAP_solved.blend"
    assert facelab_cli.main(["solve", str(shots["paths"]["gap"]), "--object", "Face", "--no-corrective", "--brief",
                             "--out", str(out), "--json", str(js), "--quiet"]) == 0
    s = json.loads(js.read_text())
    assert s["frames"] == [0, T - 1] and s["frames_solved"] == T - 1  # default: the scene's range
    assert list(s["skipped"]) == ["3"] and "marker" in s["skipped"]["3"]
    assert s["bind"]["frame"] == 0  # no --bind-frame: the first frame, not the saved current frame (2)
    assert not s["corrective"] and s["corrective_keys"] == [] and "weights" not in s  # --brief
    # the keyed weights of the frames around the gap are the truth's
    bpy.ops.wm.open_mainfile(filepath=str(out))
    key = bpy.data.objects["Face"].data.shape_keys
    np.testing.assert_allclose(_curves(key, EXPR, [0, 1, 2]), W_TRUTH[:3], atol=1e-3)
    # the bindings are kept on a second run; --bind-frame elsewhere rebinds
    assert facelab_cli.main(["solve", str(out), "--object", "Face", "--frames", "0-2", "--no-corrective",
                             "--json", str(js), "--quiet"]) == 0
    s = json.loads(js.read_text())
    assert s["bind"] == {"performed": False, "frame": 0, "bindings": shots["n_markers"]}
    assert s["frames_solved"] == 3
    assert facelab_cli.main(["solve", str(out), "--object", "Face", "--frames", "0-2", "--bind-frame", "1",
                             "--no-corrective", "--json", str(js), "--quiet"]) == 0
    s = json.loads(js.read_text())
    assert s["bind"]["performed"] and s["bind"]["frame"] == 1 and "--bind-frame 1" in s["bind"]["why"]


@pytest.mark.parametrize("command, blend, args, code, message", [
    ("solve", "shot", ["--object", "Nose"], 4, "no such object"),
    ("solve", "shot", ["--object", "NotAMesh"], 4, "not a mesh"),
    ("solve", "shot", ["--object", "Bare"], 1, "no shape keys"),
    ("solve", "noviews", ["--object", "Face"], 1, "No solve views"),
    ("solve", "uncalibrated", ["--object", "Face"], 1, "no camera calibration"),
    ("solve", "shot", ["--object", "Face", "--bind-frame", "40"], 1, "Bind Tracks bound none of the 50 tracks"),
    ("solve", "shot", ["--object", "Face", "--frames", "0-1,3"], 2, "one frame range"),
    ("retarget", "shot", ["--object", "Face", "--creature", "Troll"], 4, "no such object"),
    ("retarget", "shot", ["--object", "Face", "--creature", "NotAMesh"], 4, "not a mesh"),
    ("retarget", "shot", ["--object", "Face"], 4, "Which mesh is the creature"),
    ("retarget", "shot", ["--object", "Face", "--creature", "Creature"], 1, "no solved performance"),
    ("retarget", "shot", ["--object", "Bare", "--creature", "Creature"], 1, "no shape keys"),
])
def test_bad_input_exit_codes(shots, command, blend, args, code, message, tmp_path, addon):
    from facelab_addon import cli as facelab_cli

    js = tmp_path / "s.json"
    out = tmp_path / "never.blend"
    assert facelab_cli.main([command, str(shots["paths"][blend]), *args, "--out", str(out), "--json", str(js),
                             "--quiet"]) == code
    s = json.loads(js.read_text())
    assert s["ok"] is False and s["exit_code"] == code and message in s["error"], s["error"]
    assert not out.exists()  # nothing is saved on failure


def test_exit_codes_in_a_subprocess(shots):
    """The process's own exit status, the JSON alone on stdout, no traceback."""
    for cmd, blend, args, code, message in (
            ("solve", "shot", ["--object", "Nose"], 4, "no such object"),
            ("solve", "noviews", ["--object", "Face"], 1, "No solve views"),
            ("retarget", "shot", ["--object", "Face", "--creature", "Troll"], 4, "no such object")):
        got, s, log = cli(cmd, shots["paths"][blend], *args)
        assert got == code, log
        assert s["ok"] is False and s["exit_code"] == code and message in s["error"], s["error"]
        assert "Traceback" not in log
