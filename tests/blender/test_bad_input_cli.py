"""The CLI on bad input: every failure ends in its documented exit code (2 usage, 3 input, 5 output, 1 data,
70 bug) with one clean ``error:`` line on stderr and only the JSON on stdout; frame ranges are checked
arithmetically; a refine of a frame whose sketch is held from an earlier keyframe is refused."""

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import bpy
import numpy as np
import pytest

from facelab_addon.cli import _common
from facelab_addon.cli._common import exit_code_for, operator_failure
from facelab_addon.cli._errors import CliError
from facelab_addon.cli._frames import contiguous, parse_frames
from facelab_addon.core.capture.pointcache_writer import write_pc2
from facelab_addon.core.errors import (
    CacheFileError,
    CacheVertexCountError,
    FaceLabError,
    ObjFileError,
    OutputError,
    SketchError,
)

from .test_bad_input_files import unwritable_folder

pytestmark = [pytest.mark.blender]

ROOT = Path(__file__).resolve().parents[2]

# a small closed mesh: an octahedron
OCTA_V = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float)
OCTA_F = [(0, 2, 4), (2, 1, 4), (1, 3, 4), (3, 0, 4), (2, 0, 5), (1, 2, 5), (3, 1, 5), (0, 3, 5)]


def octa_obj(path, nan_line=False):
    lines = [f"v {x:g} {y:g} {z:g}" for x, y, z in OCTA_V]
    if nan_line:
        lines[2] = "v 0 nan 0"
    lines += ["f " + " ".join(str(i + 1) for i in f) for f in OCTA_F]
    path.write_text("\n".join(lines) + "\n")
    return path


def run_main(tmp_path, *args):
    """In this process; returns (exit code, JSON summary)."""
    from facelab_addon import cli

    js = tmp_path / "summary.json"
    code = cli.main([*map(str, args), "--json", str(js), "--quiet"])
    s = json.loads(js.read_text())
    assert s["exit_code"] == code and (s["ok"] is (code == 0))
    return code, s


# --------------------------------------------------------------------------- frames


class Scene:
    frame_start, frame_end = 3, 7


class LongScene:
    frame_start, frame_end = 0, 200_000


@pytest.mark.parametrize("text, message", [
    ("1-3000000", "past Blender's last frame 1,048,574"),
    ("0-1048574", "1,048,575 frames, more than the 100,000"),
    ("1-60000,100000-160000", "120,001 frames, more than the 100,000"),
    ("40-1", "ends before it starts; write it as 1-40"),
    ("-5-10", "frame -5 is negative; Blender's scene range (and FaceLab's) starts at frame 0"),
    ("-3", "frame -3 is negative"),
    ("1-5,x", "expected 'A-B', 'N' or a comma list"),
])
def test_frames_refused_arithmetically(text, message):
    with pytest.raises(CliError, match=re.escape(message)) as e:
        parse_frames(text, Scene)
    assert e.value.code == 2


def test_frames_parsed():
    assert parse_frames(None, Scene) == [3, 4, 5, 6, 7]
    assert parse_frames("9,1-3,2-4", LongScene) == [1, 2, 3, 4, 9]
    assert parse_frames("0-99999", LongScene)[-1] == 99999  # 100,000 frames: the most one run takes
    assert contiguous([4, 5, 6], "propagate") == (4, 6)
    with pytest.raises(CliError, match="propagate: no frames to work on") as e:
        contiguous([], "propagate")
    assert e.value.code == 2


# --------------------------------------------------------------------------- exit codes


def test_exit_code_for_each_kind_of_failure():
    assert exit_code_for(CacheFileError("x")) == 3
    assert exit_code_for(CacheVertexCountError("x")) == 3
    assert exit_code_for(ObjFileError("x")) == 3
    assert exit_code_for(OutputError("x")) == 5
    assert exit_code_for(SketchError("x")) == 1
    assert exit_code_for(FaceLabError("x")) == 1
    assert exit_code_for(CliError("x", 4)) == 4
    assert exit_code_for(KeyError("x")) == 70


def test_operator_failures_keep_their_codes(capsys):
    report = RuntimeError("Error: Correct at least one frame first (Refine Lips, or sculpt and Mark Training Frame)\n")
    assert operator_failure(report) == ("Correct at least one frame first (Refine Lips, or sculpt and Mark "
                                        "Training Frame)", 1)
    tb = ("Error: Python: Traceback (most recent call last):\n  File \"ops.py\", line 3, in execute\n"
          "    bake(...)\n{last}\n")
    out = RuntimeError(tb.format(last="facelab_addon.core.errors.OutputError: Cannot write '/ro/x.pc2': "
                                      "permission denied. Choose a file in a writable folder."))
    assert operator_failure(out) == ("Cannot write '/ro/x.pc2': permission denied. Choose a file in a writable "
                                     "folder.", 5)
    cache = RuntimeError(tb.format(last="CacheFileError: PC2 file '/a.pc2' is truncated."))
    assert operator_failure(cache) == ("PC2 file '/a.pc2' is truncated.", 3)
    bug = RuntimeError(tb.format(last="IndexError: index 0 is out of bounds for axis 0 with size 0"))
    msg, code = operator_failure(bug)
    assert code == 70 and "IndexError: index 0 is out of bounds" in msg and "a bug" in msg
    assert "Traceback" in capsys.readouterr().err  # the traceback goes to stderr


# --------------------------------------------------------------------------- input files


def test_bad_input_files_exit_3(tmp_path, addon):
    ok = octa_obj(tmp_path / "face.obj")
    garbage = tmp_path / "garbage.obj"
    garbage.write_bytes(os.urandom(4096) + b"\0")
    code, s = run_main(tmp_path, "propagate", "--mesh", garbage)
    assert code == 3 and "garbage.obj is a binary file, not a Wavefront OBJ" in s["error"]
    (tmp_path / "words.obj").write_text("this is not\na mesh at all\n")
    code, s = run_main(tmp_path, "propagate", "--mesh", tmp_path / "words.obj")
    assert code == 3 and "no vertices or no faces" in s["error"]
    code, s = run_main(tmp_path, "propagate", "--mesh", octa_obj(tmp_path / "nan.obj", nan_line=True))
    assert code == 3 and "nan.obj, line 3: NaN or infinite coordinate in 'v 0 nan 0'" in s["error"]
    code, s = run_main(tmp_path, "propagate", "--mesh", ok, "--corrected", f"5:{tmp_path / 'nan.obj'}")
    assert code == 3 and "line 3: NaN" in s["error"]

    seq = np.repeat(OCTA_V[None], 4, 0).astype(np.float32)
    good = write_pc2(tmp_path / "perf.pc2", seq)
    raw = bytearray(good.read_bytes())
    raw[2] = ord("x")
    (tmp_path / "damaged.pc2").write_bytes(bytes(raw))
    code, s = run_main(tmp_path, "propagate", "--mesh", ok, "--cache", tmp_path / "damaged.pc2")
    assert code == 3 and "damaged.pc2' is not a PC2 file" in s["error"]
    write_pc2(tmp_path / "count.pc2", seq[:, :5])
    code, s = run_main(tmp_path, "propagate", "--mesh", ok, "--cache", tmp_path / "count.pc2")
    assert code == 3 and "has 5 points but 'Face' has 6 vertices" in s["error"]
    write_pc2(tmp_path / "negative.pc2", seq, start=-5.0)
    code, s = run_main(tmp_path, "propagate", "--mesh", ok, "--cache", tmp_path / "negative.pc2")
    assert code == 3 and "first sample is on frame -5, before frame 0" in s["error"]
    code, s = run_main(tmp_path, "propagate", "--mesh", ok, "--cache", good, "--frames", "1-3000000")
    assert code == 2 and "past Blender's last frame" in s["error"]


def test_truncated_alembic_input_is_refused_before_blender_reads_it(tmp_path, addon):
    """Blender's Alembic importer aborts the whole process on a truncated file: FaceLab reads it first."""
    from facelab_addon.blender import bakes

    from .test_caches import T, ico, key_per_frame, known_sequence, rest_of

    bpy.ops.wm.read_factory_settings(use_empty=True)
    ob = ico("Face")
    key_per_frame(ob, known_sequence(rest_of(ob)))
    data = bakes.bake_alembic(ob, range(1, T + 1), tmp_path / "shot.abc").read_bytes()
    (tmp_path / "cut.abc").write_bytes(data[: len(data) * 2 // 3])
    code, s = run_main(tmp_path, "propagate", "--mesh", tmp_path / "cut.abc")
    assert code == 3 and "cut.abc: Blender cannot read this Alembic file: it is truncated" in s["error"]


# --------------------------------------------------------------------------- outputs


def test_unwritable_bake_exits_5_before_any_work(tmp_path, addon):
    ok = octa_obj(tmp_path / "face.obj")
    blocker = tmp_path / "out"
    blocker.write_text("a file")
    code, s = run_main(tmp_path, "propagate", "--mesh", ok, "--corrected", f"1:{ok}", "--bake",
                       blocker / "fixed.pc2")
    assert code == 5 and "out' is a file, not a folder" in s["error"]
    code, s = run_main(tmp_path, "propagate", "--mesh", ok, "--corrected", f"1:{ok}", "--bake",
                       os.path.join(unwritable_folder(tmp_path), "fixed.pc2"))
    assert code == 5 and ("read-only" in s["error"] or "permission denied" in s["error"])
    assert blocker.read_text() == "a file"


def test_streams_in_a_subprocess(tmp_path):
    """stdout is the JSON and nothing else; stderr ends in one clean error line; no traceback."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    nan = octa_obj(tmp_path / "nan.obj", nan_line=True)
    r = subprocess.run([sys.executable, "-m", "facelab_addon", "propagate", "--mesh", str(nan)], cwd=tmp_path,
                       env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, timeout=300)
    assert r.returncode == 3, r.stderr
    s = json.loads(r.stdout)
    assert s["exit_code"] == 3 and "line 3" in s["error"]
    errors = [ln for ln in r.stderr.splitlines() if "error:" in ln]
    assert len(errors) == 1 and errors[0].endswith(s["error"]) and "Traceback" not in r.stderr


# --------------------------------------------------------------------------- refine: a sketch held from another frame


def test_refine_a_frame_without_its_own_sketch_keyframe(ict, addon, tmp_path):
    from facelab_addon.blender.camera import camera_from_blender
    from facelab_addon.blender.strokes import write_stroke_pixels
    from facelab_addon.pipeline.refine import refine

    from .test_cli import sketched_shot
    from .test_refine_operator import FRAME

    s, shot = sketched_shot(tmp_path, ict)
    scene = s["scene"]
    cam = camera_from_blender(scene)
    later = FRAME + 18
    code, summary = run_main(tmp_path, "refine", shot, "--object", "Face", "--frames", later)
    assert code == 1
    assert (f"frame {later}: The lip sketch 'FL_LipSketch' has no 'Upper lip' keyframe on frame {later}: the "
            f"strokes shown there are held from frame {FRAME}") in summary["error"]
    assert f"refine a sketched frame ({FRAME})" in summary["error"]
    # the pipeline itself refuses, and nothing is written
    scene = bpy.context.scene
    obj = bpy.data.objects["Face"]
    keys_before = [k.name for k in obj.data.shape_keys.key_blocks] if obj.data.shape_keys else []
    with pytest.raises(SketchError, match=f"held from frame {FRAME}"):
        refine(scene, obj, later, sketch=scene.facelab.sketch)
    assert ([k.name for k in obj.data.shape_keys.key_blocks] if obj.data.shape_keys else []) == keys_before
    assert len(obj.facelab.training_frames) == 0
    # once the lips are keyed on that frame too, it refines
    write_stroke_pixels(scene.facelab.sketch, "Upper lip", later, [s["up_px"]], cam)
    write_stroke_pixels(scene.facelab.sketch, "Lower lip", later, [s["lo_px"]], cam)
    assert refine(scene, obj, later, sketch=scene.facelab.sketch).shape_key == f"FL_Refine_{later:04d}"


def test_common_has_no_leftover_names():
    assert _common.MAX_FRAME == 1048574


# --------------------------------------------------------------------------- outputs against each other and inputs


def tiny_blend(path):
    """A saved .blend holding the octahedron as 'Face'."""
    from facelab_addon.blender.scene import new_mesh_object

    bpy.ops.wm.read_factory_settings(use_empty=True)
    new_mesh_object("Face", OCTA_V, poly_verts=np.array(OCTA_F).ravel(), poly_offsets=np.arange(0, 25, 3))
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    return path


def run_stdout(capfd, *args):
    """In this process, the JSON on stdout; returns (exit code, JSON summary)."""
    from facelab_addon import cli

    capfd.readouterr()
    code = cli.main([*map(str, args), "--quiet"])
    out = capfd.readouterr().out  # (the test's own Blender calls may flush their C-buffered lines first)
    s = json.loads(out[out.index('{\n  "command"'):])
    assert s["exit_code"] == code and (s["ok"] is (code == 0))
    return code, s


def test_outputs_that_are_one_file_or_an_input_are_refused_before_any_work(tmp_path, addon, capfd):
    shot = tiny_blend(tmp_path / "SHOT.blend")
    face = octa_obj(tmp_path / "face.obj")
    perf = write_pc2(tmp_path / "perf.pc2", np.repeat(OCTA_V[None], 4, 0).astype(np.float32))
    kept = {p: p.read_bytes() for p in (shot, face, perf)}
    x = tmp_path / "X.blend"
    (tmp_path / "link.blend").symlink_to(shot)
    for args, message in [
        ((shot, "--out", x, "--json", x), f"--out and --json are the same file ({x})"),
        ((shot, "--out", shot), "is the input SHOT.blend: FaceLab never writes over its input"),
        ((shot, "--out", tmp_path / "link.blend"), "is the input SHOT.blend"),  # a link to the input
        ((shot, "--json", shot), f"--json {shot} is the input SHOT.blend"),
        (("--mesh", face, "--cache", perf, "--bake", perf), "is the input --cache"),
        (("--mesh", face, "--out", x, "--bake", tmp_path / "sub" / ".." / "X.blend"), "are the same file"),
        (("--mesh", face, "--corrected", f"2:{face}", "--json", face), "is the input --mesh"),
    ]:
        code, s = run_stdout(capfd, "propagate", *args)
        assert code == 2 and message in s["error"], (args, s["error"])
        assert not x.exists() and {p: p.read_bytes() for p in kept} == kept  # nothing written, the JSON on stdout
    # an output that is a file the opened scene reads (its capture here): refused once the .blend is open
    bpy.ops.wm.open_mainfile(filepath=str(shot))
    md = bpy.data.objects["Face"].modifiers.new("Capture", "MESH_CACHE")
    md.cache_format, md.filepath = "PC2", str(perf)
    played = tmp_path / "played.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(played))
    code, s = run_stdout(capfd, "propagate", played, "--json", perf)
    assert code == 2 and "the scene reads this file (the Mesh Cache 'Capture' of 'Face')" in s["error"]
    assert perf.read_bytes() == kept[perf]
    # an output inside Blender's open file: the open .blend is the input
    bpy.ops.wm.open_mainfile(filepath=str(shot))
    code, s = run_stdout(capfd, "propagate", "--from-open-scene", "--out", shot)
    assert code == 2 and "is the .blend Blender opened, FaceLab's input" in s["error"]
    assert shot.read_bytes() == kept[shot]


def test_output_folders_checked_before_any_work(tmp_path, addon, monkeypatch):
    face = octa_obj(tmp_path / "face.obj")
    code, s = run_main(tmp_path, "propagate", "--mesh", face, "--corrected", f"1:{face}",
                       "--bake", tmp_path / "missing" / "fixed.pc2")
    assert code == 5 and "the folder" in s["error"] and "does not exist; create it first" in s["error"]
    from facelab_addon import cli

    code = cli.main(["propagate", "--mesh", str(face), "--json", str(tmp_path / "nowhere" / "s.json"), "--quiet"])
    assert code == 5 and not (tmp_path / "nowhere").exists()
    code, s = run_main(tmp_path, "propagate", "--mesh", face, "--out",
                       os.path.join(unwritable_folder(tmp_path), "fixed.blend"))
    assert code == 5 and ("read-only" in s["error"] or "permission denied" in s["error"])
    long_name = "Л" * 130 + ".blend"  # 260 bytes in UTF-8
    code, s = run_main(tmp_path, "propagate", "--mesh", face, "--out", tmp_path / long_name)
    assert code == 5 and "more than the file system's limit of 255 bytes" in s["error"]
    # ~ is expanded as a shell would (--out=~/x.blend and paths given from Python reach FaceLab as typed)
    monkeypatch.setenv("HOME", str(tmp_path))
    code = cli.main(["propagate", "--mesh", "~/face.obj", "--json", "~/home.json", "--quiet"])
    s = json.loads((tmp_path / "home.json").read_text())  # written in $HOME, not in a folder named '~'
    assert code == 1 and "Cannot find the inner-lip line" in s["error"]  # face.obj was found and read


def test_bake_over_an_existing_file_needs_overwrite_as_in_the_panel(tmp_path, addon):
    face = octa_obj(tmp_path / "face.obj")
    old = tmp_path / "fixed.pc2"
    old.write_bytes(b"the artist's earlier bake")
    code, s = run_main(tmp_path, "propagate", "--mesh", face, "--corrected", f"1:{face}", "--bake", old)
    assert code == 5 and "the file exists; give --overwrite to replace it" in s["error"]
    assert old.read_bytes() == b"the artist's earlier bake"
    code, s = run_main(tmp_path, "propagate", "--mesh", face, "--corrected", f"1:{face}", "--bake", old,
                       "--overwrite")
    assert "the file exists" not in s.get("error", "")  # past the check (the octahedron fails later)


# --------------------------------------------------------------------------- frames outside the shot


class Shot48:
    frame_start, frame_end = 1, 48


def test_frames_outside_the_shot_are_refused_not_keyed(tmp_path, addon):
    with pytest.raises(CliError, match=re.escape("frame 500 is outside the shot, whose frame range is 1-48")) as e:
        parse_frames("1-500", Shot48)
    assert e.value.code == 2
    with pytest.raises(CliError, match="frame 0 is outside the shot"):
        parse_frames("0,5", Shot48)
    assert parse_frames("1-48", Shot48) == list(range(1, 49))
    face = octa_obj(tmp_path / "face.obj")
    perf = write_pc2(tmp_path / "perf.pc2", np.repeat(OCTA_V[None], 4, 0).astype(np.float32), start=1.0)
    for cmd in ("propagate", "reconstruct"):
        code, s = run_main(tmp_path, cmd, "--mesh", face, "--cache", perf, "--frames", "1-500")
        assert code == 2 and "frame 500 is outside the shot, whose frame range is 1-4" in s["error"], s["error"]


# --------------------------------------------------------------------------- input .blend messages


def test_a_folder_or_a_blend_from_a_newer_blender(tmp_path, addon):
    folder = tmp_path / "shots"
    folder.mkdir()
    tiny_blend(folder / "SHOT.blend")
    code, s = run_main(tmp_path, "propagate", folder)
    assert code == 3 and "is a folder, not a .blend file; give the .blend itself (the folder holds SHOT.blend)" \
        in s["error"]
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "plain.blend"), compress=False)
    raw = (tmp_path / "plain.blend").read_bytes()
    assert raw[:7] == b"BLENDER"
    future = tmp_path / "future.blend"
    future.write_bytes(raw[:7] + b"99" + raw[9:])  # a header format this Blender does not know
    code, s = run_main(tmp_path, "propagate", future)
    assert code == 3 and f"this Blender ({bpy.app.version_string}) cannot read it" in s["error"]
    assert "newer" in s["error"] and "or older?" not in s["error"]
    # a newer version number in a header this Blender parses: it reads the file, and the summary says so
    later = tmp_path / "later.blend"
    later.write_bytes(raw[:13] + b"0900" + raw[17:] if raw[7:9] == b"17" else raw[:9] + b"900" + raw[12:])
    code, s = run_main(tmp_path, "propagate", later)
    assert code != 3 and any(n.startswith("later.blend was saved by Blender 9.0, newer than this Blender")
                             for n in s["notes"]), s


@pytest.mark.slow
def test_a_saved_shot_whose_alembic_was_truncated_is_refused_before_blender_reads_it(tmp_path, addon):
    """Blender aborts (signal 6) opening a .blend whose Alembic capture is truncated: in a subprocess."""
    from .test_caches import T, ico, key_per_frame, known_sequence, rest_of

    bpy.ops.wm.read_factory_settings(use_empty=True)
    src = ico("Face")
    key_per_frame(src, known_sequence(rest_of(src)))
    from facelab_addon.blender import bakes

    abc = bakes.bake_alembic(src, range(1, T + 1), tmp_path / "cap.abc")
    bpy.ops.wm.read_factory_settings(use_empty=True)
    assert bpy.ops.wm.alembic_import(filepath=str(abc)) == {"FINISHED"}
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "shot.blend"), relative_remap=True)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    data = abc.read_bytes()
    abc.write_bytes(data[: len(data) * 2 // 3])
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    r = subprocess.run([sys.executable, "-m", "facelab_addon", "propagate", str(tmp_path / "shot.blend"),
                        "--object", "Face"], cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                       text=True, timeout=300)
    assert r.returncode == 3, (r.returncode, r.stderr[-2000:])
    s = json.loads(r.stdout)
    assert f"shot.blend plays the Alembic file '{abc}'" in s["error"] and "it is truncated" in s["error"]
    assert "Re-export or re-copy the Alembic file" in s["error"]


# --------------------------------------------------------------------------- refine: never a second key in silence


@pytest.mark.slow
def test_refine_without_frames_refines_only_frames_not_refined_yet(ict, addon, tmp_path):
    from .test_cli import sketched_shot
    from .test_refine_operator import FRAME

    _, shot = sketched_shot(tmp_path, ict)
    once = tmp_path / "once.blend"
    code, s = run_main(tmp_path, "refine", shot, "--object", "Face", "--out", once)
    assert code == 0 and [r["shape_key"] for r in s["refined"]] == [f"FL_Refine_{FRAME:04d}"]
    # run again on its output: nothing new, the refined frame is listed as skipped with a note
    twice = tmp_path / "twice.blend"
    code, s = run_main(tmp_path, "refine", once, "--object", "Face", "--out", twice)
    assert code == 0 and s["refined"] == [] and [d["frame"] for d in s["skipped"]] == [FRAME]
    assert any("already refined" in n for n in s["notes"])
    bpy.ops.wm.open_mainfile(filepath=str(twice))
    keys = [k.name for k in bpy.data.objects["Face"].data.shape_keys.key_blocks]
    assert [k for k in keys if k.startswith("FL_Refine_")] == [f"FL_Refine_{FRAME:04d}"]  # no .001 stacked
    # naming the refined frame is refused unless --again, which says which key it replaced there
    code, s = run_main(tmp_path, "refine", once, "--object", "Face", "--frames", FRAME)
    assert code == 1 and f"frames [{FRAME}] are already refined (FL_Refine_{FRAME:04d})" in s["error"]
    assert "Give --again" in s["error"]
    code, s = run_main(tmp_path, "refine", once, "--object", "Face", "--frames", FRAME, "--again")
    assert code == 0 and s["refined"][0]["shape_key"] == f"FL_Refine_{FRAME:04d}.001"
    assert any(f"replaces ['FL_Refine_{FRAME:04d}'] on that frame" in n for n in s["notes"])
