"""Broken caches never turn into silent garbage: a deleted, truncated, wrong-count or bad-header Mesh Cache
file, and a missing, truncated or motionless Alembic, are refused with the file, the problem and the fix,
before anything is evaluated or changed (no fall back to the static mesh; the artist's modifiers, keys and
files stay as they were). Bakes to unwritable places end in an OutputError."""

import os
import shutil

import bpy
import numpy as np
import pytest

from facelab_addon.blender import bakes, cache_integrate, caches, correction_files
from facelab_addon.core.capture import pointcache, pointcache_writer
from facelab_addon.core.errors import CacheFileError, CacheVertexCountError, OutputError
from facelab_addon.pipeline.bake import BakeSettings, bake

from .test_bad_input_files import unwritable_folder
from .test_caches import T, add_key, add_mesh_cache, ico, key_per_frame, known_sequence, rest_of

pytestmark = [pytest.mark.blender, pytest.mark.usefixtures("empty_scene")]


def state(ob):
    """What the artist made on ``ob``: modifiers (type, viewport, render, mode, file), key names and mutes."""
    mods = [(m.name, m.type, m.show_viewport, m.show_render, getattr(m, "deform_mode", None),
             getattr(m, "filepath", None)) for m in ob.modifiers]
    keys = ob.data.shape_keys
    kbs = [(k.name, k.mute, k.value) for k in keys.key_blocks] if keys else []
    return mods, kbs


def broken_pc2(kind, good, path):
    raw = bytearray(good.read_bytes())
    if kind == "deleted":
        return path  # never written
    if kind == "truncated":
        raw = raw[: len(raw) - 100]
    elif kind == "bad_header":
        raw[:12] = b"NOTACACHE\0\0\0"
    path.write_bytes(bytes(raw))
    return path


@pytest.mark.parametrize("kind, message", [
    ("deleted", r"file not found: '.*cap_deleted\.pc2'\. Check the path"),
    ("truncated", r"cap_truncated\.pc2' is truncated: its header announces 6 samples.*Re-export or re-copy"),
    ("bad_header", r"cap_bad_header\.pc2' is not a PC2 file: it starts with b'NOTACACHE"),
    ("wrong_count", r"has 12 points but 'Face' has 42 vertices\. Use the cache exported from this mesh"),
])
@pytest.mark.parametrize("mode", ["OVERWRITE", "INTEGRATE"])  # Integrate + an artist key: the evaluation path
def test_broken_mesh_cache_is_refused_not_evaluated(tmp_path, kind, message, mode):
    ob = ico("Face")
    seq = known_sequence(rest_of(ob))
    good = pointcache_writer.write_pc2(tmp_path / "good.pc2", seq)
    if kind == "wrong_count":
        path = pointcache_writer.write_pc2(tmp_path / "cap_wrong_count.pc2", seq[:, :12])
    else:
        path = broken_pc2(kind, good, tmp_path / f"cap_{kind}.pc2")
    add_mesh_cache(ob, path, "PC2", deform_mode=mode, frame_start=1.0)
    if mode == "INTEGRATE":
        add_key(ob, "ArtistSmile", 0.01)  # the direct read cannot reproduce this stack: Blender evaluates it
        assert caches.mesh_cache_direct_read_problem(ob) is not None
    before = state(ob)
    frame = bpy.context.scene.frame_current
    for read in (caches.read_captured_frames, caches.read_mesh_cache_frames, caches.evaluate_frames):
        with pytest.raises(CacheFileError, match=message) as e:
            read(ob, range(1, T + 1))
        assert "Mesh Cache 'Capture' of 'Face'" in str(e.value)
    if kind == "wrong_count":
        assert e.type is CacheVertexCountError
    with pytest.raises(CacheFileError, match=message):
        cache_integrate.cache_to_shape_key_ready(ob)  # an Overwrite cache stays Overwrite
    with pytest.raises(CacheFileError, match=message):
        bakes.bake_pc2(ob, range(1, T + 1), tmp_path / "out.pc2")
    assert state(ob) == before and bpy.context.scene.frame_current == frame
    assert not (tmp_path / "out.pc2").exists() and not (tmp_path / "out.pc2.tmp").exists()
    # the same stack on the good file reads the capture
    ob.modifiers["Capture"].filepath = str(good)
    if mode == "OVERWRITE":
        np.testing.assert_allclose(caches.read_captured_frames(ob, range(1, T + 1)), seq, atol=1e-6)


def test_nan_in_a_mesh_cache_names_the_sample(tmp_path):
    ob = ico("Face")
    seq = known_sequence(rest_of(ob))
    seq[3, 5, 1] = np.nan
    path = tmp_path / "nan.pc2"
    pointcache_writer.write_pc2(tmp_path / "ok.pc2", seq[:3])
    raw = bytearray((tmp_path / "ok.pc2").read_bytes())
    raw[28:32] = np.int32(T).tobytes()
    path.write_bytes(bytes(raw) + seq[3:].astype("<f4").tobytes())
    add_mesh_cache(ob, path, "PC2", frame_start=1.0)
    np.testing.assert_allclose(caches.read_captured_frames(ob, [1, 2, 3]), seq[:3], atol=1e-6)
    with pytest.raises(CacheFileError, match=r"nan\.pc2' has NaN or infinite positions in sample 3"):
        caches.read_captured_frames(ob, range(1, T + 1))


# --------------------------------------------------------------------------- Alembic


@pytest.fixture
def alembic(tmp_path):
    """(object playing a copy of an animated Alembic, the copy's path, the original bytes, the capture)."""
    src = ico("Capture")
    seq = known_sequence(rest_of(src))
    key_per_frame(src, seq)
    abc = bakes.bake_alembic(src, range(1, T + 1), tmp_path / "cap.abc")
    bpy.ops.wm.read_factory_settings(use_empty=True)
    live = tmp_path / "live.abc"
    shutil.copy(abc, live)
    assert bpy.ops.wm.alembic_import(filepath=str(live)) == {"FINISHED"}
    ob = bpy.data.objects["Capture"]
    bpy.context.scene.frame_start, bpy.context.scene.frame_end = 1, T
    return ob, live, abc.read_bytes(), caches.evaluate_frames(ob, range(1, T + 1))


def test_alembic_file_problem(alembic, tmp_path):
    _, live, data, _ = alembic
    assert caches.alembic_file_problem(live) is None
    for n, why in ((0, "0 bytes, too short"), (12, "12 bytes, too short"), (len(data) // 2, "it is truncated"),
                   (len(data) - 1, "it is truncated")):
        p = tmp_path / f"cut{n}.abc"
        p.write_bytes(data[:n])
        assert why in caches.alembic_file_problem(p), n
    unfinished = tmp_path / "unfinished.abc"
    unfinished.write_bytes(data[:5] + b"\0" + data[6:])
    assert "did not finish" in caches.alembic_file_problem(unfinished)
    (tmp_path / "hdf5.abc").write_bytes(b"\x89HDF\r\n\x1a\n" + bytes(64))
    assert "HDF5" in caches.alembic_file_problem(tmp_path / "hdf5.abc")
    assert "does not exist" in caches.alembic_file_problem(tmp_path / "none.abc")


@pytest.mark.parametrize("kind, why", [("truncated", "it is truncated"), ("emptied", "it has 0 bytes"),
                                       ("deleted", "the file does not exist")])
def test_broken_alembic_is_refused_and_the_artists_modifier_stays_on(alembic, tmp_path, kind, why):
    ob, live, data, _ = alembic
    before = state(ob)
    if kind == "deleted":
        live.unlink()
    else:
        live.write_bytes(data[: len(data) // 2] if kind == "truncated" else b"")
    msg = rf"Mesh Sequence Cache 'MeshSequenceCache' of 'Capture' plays '.*live\.abc', but {why}.*Re-export or re-copy"
    with pytest.raises(CacheFileError, match=msg):
        cache_integrate.cache_to_shape_key_ready(ob, directory=tmp_path, scene_frames=range(1, T + 1))
    with pytest.raises(CacheFileError, match=msg):
        caches.read_captured_frames(ob, range(1, T + 1))
    assert state(ob) == before and ob.modifiers[0].show_viewport and ob.modifiers[0].show_render
    assert not list(tmp_path.glob("Capture_capture*.pc2"))  # nothing baked
    live.write_bytes(data)  # Blender never read the broken file; the good one plays again


def test_alembic_that_does_not_move_is_not_baked(alembic, tmp_path):
    ob, live, data, seq = alembic
    assert np.abs(seq - seq[0]).max() > 0.05
    before = state(ob)
    scene = bpy.context.scene
    # past the end of the file's animation every frame holds the last sample: no motion to capture
    with pytest.raises(CacheFileError, match=r"does not move on frames 20-30.*Check the frame range"):
        cache_integrate.cache_to_shape_key_ready(ob, directory=tmp_path, scene_frames=range(20, 31))
    assert state(ob) == before and not list(tmp_path.glob("Capture_capture*.pc2"))
    held = caches.read_captured_frames(ob, range(20, 31))  # reading a held pose is fine...
    np.testing.assert_array_equal(held, np.repeat(seq[-1:], 11, axis=0))
    with pytest.raises(CacheFileError, match="does not move on frames 20-30"):  # ...as a whole capture it is not
        caches.check_alembic_moves(ob, np.arange(20.0, 31.0), held)
    assert scene.frame_current == 1
    blocker = tmp_path / "shots"
    blocker.write_text("not a folder")
    with pytest.raises(OutputError, match=r"shots' is a file, not a folder"):  # the PC2 cannot be written
        cache_integrate.cache_to_shape_key_ready(ob, directory=blocker / "bakes", scene_frames=range(1, T + 1))
    assert state(ob) == before
    # over the animated frames it is baked and switched as documented
    msg = cache_integrate.cache_to_shape_key_ready(ob, directory=tmp_path, scene_frames=range(1, T + 1))
    assert "turned it off" in msg and (tmp_path / "Capture_capture.pc2").is_file()


# --------------------------------------------------------------------------- bakes to unwritable places


def test_bakes_to_unwritable_places_are_output_errors(tmp_path):
    ob = ico("Face")
    key_per_frame(ob, known_sequence(rest_of(ob)))
    blocker = tmp_path / "renders"
    blocker.write_text("not a folder")
    ro = unwritable_folder(tmp_path)
    for fmt in ("PC2", "MDD", "ABC"):
        ext = fmt.lower()
        with pytest.raises(OutputError, match=r"renders' is a file, not a folder"):
            bake(ob, range(1, T + 1), blocker / f"x.{ext}", BakeSettings(format=fmt))
        with pytest.raises(OutputError, match="(read-only|permission denied)"):
            bake(ob, range(1, T + 1), os.path.join(ro, f"x.{ext}"), BakeSettings(format=fmt))
        # a path relative to an unsaved .blend would land in the working directory
        with pytest.raises(OutputError, match=r"relative to the \.blend, but the \.blend is not saved yet"):
            bake(ob, range(1, T + 1), f"//x.{ext}", BakeSettings(format=fmt))
        with pytest.raises(OutputError, match="is a relative path"):
            bake(ob, range(1, T + 1), f"x.{ext}", BakeSettings(format=fmt))
        assert not os.path.exists(f"x.{ext}")
    with pytest.raises(OutputError, match="is a file, not a folder"):
        bakes.bake_alembic(ob, range(1, T + 1), blocker / "sub" / "x.abc")
    assert blocker.read_text() == "not a folder"


# --------------------------------------------------------------------------- the operators on a broken cache


@pytest.mark.parametrize("kind", ["truncated", "deleted"])
@pytest.mark.slow
def test_propagate_operator_refuses_a_broken_mesh_cache(tmp_path, ict, addon, kind):
    """The probe's case: Propagate over a Mesh Cache whose file broke after the training frames were made."""
    from facelab_addon.blender.shapekeys import add_corrective_key, key_spike
    from facelab_addon.testing.scenes import build_ict_face_scene

    frames = 8
    neutral = ict.neutral * 0.01
    t = np.linspace(0, 1, frames)
    seq = np.stack([ict.pose({"jawOpen": 0.1 + 0.2 * a}) * 0.01 for a in t]).astype(np.float32)
    pc2 = pointcache_writer.write_pc2(tmp_path / "capture.pc2", seq)
    fs = build_ict_face_scene(ict, frame_range=(1, frames), scale=0.01, fixed_group=True, select=False)
    scene, obj = fs.scene, fs.obj
    md = add_mesh_cache(obj, pc2, "PC2", frame_start=1.0)
    bpy.context.view_layer.objects.active = obj
    assert bpy.ops.facelab.auto_regions() == {"FINISHED"}
    scene.frame_set(4)
    d = np.zeros_like(neutral)
    d[6632:6706, 1] = 0.0005
    key_spike(add_corrective_key(obj, "Sculpt_4", d), 4)
    assert bpy.ops.facelab.mark_training_frame() == {"FINISHED"}
    before = state(obj)
    if kind == "deleted":
        pc2.unlink()
    else:
        pc2.write_bytes(pc2.read_bytes()[:-1000])
    with pytest.raises(RuntimeError, match=r"capture\.pc2"):
        bpy.ops.facelab.propagate(suggestions=0)
    assert state(obj) == before and md.deform_mode == "OVERWRITE"  # nothing switched, no FL_Prop key
    assert not [k for k in obj.data.shape_keys.key_blocks if k.name.startswith("FL_Prop")]


# --------------------------------------------------------------------------- correction caches: names and moves


def test_correction_cache_names_fit_the_file_system_whatever_the_names(tmp_path):
    """A face named with 150 Cyrillic letters in a .blend with a 120-letter name: the cache name fits the
    255-byte limit (it was 542 bytes and a raw OSError escaped), and is written; 'é' is kept like Cyrillic."""
    ob = ico("Л" * 150)
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / ("Ж" * 120 + ".blend")))
    path = bakes.correction_cache_path(ob, "FL_Prop_", "PC2")
    assert path.parent == tmp_path and len(path.name.encode()) + len(".tmp") <= 255
    assert path.name.startswith("Ж" * 20) and "Л" * 20 in path.name and path.name.endswith("_FL_Prop.pc2")
    seq = np.repeat(rest_of(ob)[None], 2, 0)
    assert pointcache_writer.write_pc2(path, seq) == path and path.is_file()
    ob.name = "visage é"
    assert "_visage_é_FL_Prop" in bakes.correction_cache_path(ob, "FL_Prop_", "PC2").name
    assert cache_integrate.file_name_part is bakes.file_name_part  # one sanitiser for every generated file


def test_a_blend_moved_without_its_correction_cache_is_refused_not_baked_uncorrected(tmp_path, addon):
    a, b = tmp_path / "a", tmp_path / "b"
    a.mkdir()
    b.mkdir()
    ob = ico("Face")
    rest = rest_of(ob)
    seq = known_sequence(rest)
    key_per_frame(ob, seq)
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 1, T
    bpy.ops.wm.save_as_mainfile(filepath=str(a / "shot.blend"))
    corr = np.zeros_like(rest)
    corr[:5] = [0.0, 0.0, 0.1]  # a correction of five vertices, on every frame
    cache = bakes.correction_cache_path(ob, "FL_Prop_", "PC2")
    pointcache_writer.write_pc2(cache, np.repeat((rest + corr)[None], T, 0))
    bakes.add_correction_cache(ob, "FL_Prop_", cache, "PC2", 1, T, integrate=True)
    assert ob.modifiers[0].filepath == "//shot_Face_FL_Prop.pc2"
    corrected = caches.evaluate_frames(ob, range(1, T + 1), mute_shape_keys_prefix=())
    moved = np.linalg.norm(corrected - seq, axis=2)
    assert moved[:, :5].min() > 0.05  # the correction plays on every frame
    assert correction_files.correction_cache_problems(ob) == []
    bpy.ops.wm.save_as_mainfile(filepath=str(a / "shot.blend"))
    shutil.copy(a / "shot.blend", b / "shot.blend")  # copied to another machine, without the cache

    bpy.ops.wm.open_mainfile(filepath=str(b / "shot.blend"))
    ob = bpy.data.objects["Face"]
    (problem,) = correction_files.correction_cache_problems(ob)
    assert "The correction cache of 'Face' (FL_Prop_*, modifier 'FL_Prop_Cache') plays '//shot_Face_FL_Prop.pc2'" \
        in problem and f"no such file ('{b / 'shot_Face_FL_Prop.pc2'}'" in problem
    assert f"it is still at '{cache}': copy it to '{b / 'shot_Face_FL_Prop.pc2'}'" in problem
    assert correction_files.missing_correction_files(ob) == [("FL_Prop_", "//shot_Face_FL_Prop.pc2")]
    out = tmp_path / "baked.pc2"
    with pytest.raises(CacheFileError, match=r"Bake Corrected Sequence would use 'Face' without FaceLab's correction"):
        bake(ob, range(1, T + 1), out, BakeSettings(format="PC2"))
    assert not out.exists()
    from facelab_addon.blender import review

    with pytest.raises(CacheFileError, match="The correction heat map would use 'Face' without"):
        review.correction_magnitude(ob, bpy.context.evaluated_depsgraph_get())
    cache.unlink()
    assert "copy 'shot_Face_FL_Prop.pc2' back beside the .blend" in correction_files.correction_cache_problems(ob)[0]
    # the CLI says it in the summary's notes, even when the command then fails for another reason
    import json

    from facelab_addon import cli

    js = tmp_path / "s.json"
    cli.main(["propagate", str(b / "shot.blend"), "--object", "Face", "--json", str(js), "--quiet"])
    notes = json.loads(js.read_text())["notes"]
    assert any("plays '//shot_Face_FL_Prop.pc2', but there is no such file" in n for n in notes)
    bpy.ops.wm.open_mainfile(filepath=str(b / "shot.blend"))
    ob = bpy.data.objects["Face"]
    # once the file is back beside the .blend, the correction plays and bakes again
    pointcache_writer.write_pc2(b / "shot_Face_FL_Prop.pc2", np.repeat((rest + corr)[None], T, 0))
    assert correction_files.correction_cache_problems(ob) == []
    bake(ob, range(1, T + 1), out, BakeSettings(format="PC2"))
    np.testing.assert_allclose(pointcache.read_pc2(out)[0], corrected, atol=1e-5)
