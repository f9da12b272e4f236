"""Headless tests of the cache adapter (bpy 5.0 wheel).

Every direct read is checked against Blender's own evaluation of the Mesh
Cache modifier, and against the known positions written to the file; the
Alembic path goes through Blender's own exporter and importer.
"""

import os
import sys
import tempfile

if "bpy" not in sys.modules:
    os.environ["BLENDER_USER_RESOURCES"] = tempfile.mkdtemp(prefix="facelab-blender-user-")

import bpy  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from facelab_addon.blender import bakes, cache_integrate, caches  # noqa: E402
from facelab_addon.blender.ownership import own_key  # noqa: E402
from facelab_addon.core.capture import integrate, meshcache, pointcache, pointcache_writer  # noqa: E402
from facelab_addon.core.errors import CacheVertexCountError, FaceLabError, MeshError  # noqa: E402

pytestmark = [pytest.mark.blender, pytest.mark.usefixtures("empty_scene")]  # every test: an empty scene

T = 6
TOL = 2e-6  # float32 rounding (Integrate mode, axis matrix)


def ico(name="Face"):
    bpy.ops.mesh.primitive_ico_sphere_add(subdivisions=2, radius=1.0)
    ob = bpy.context.object
    ob.name = name
    return ob


def rest_of(ob):
    co = np.empty(len(ob.data.vertices) * 3, np.float32)
    ob.data.vertices.foreach_get("co", co)
    return co.reshape(-1, 3)


def known_sequence(rest, seed=0):
    """T frames: translated, rotated, scaled and noisy versions of the rest mesh."""
    rng = np.random.default_rng(seed)
    R = Rotation.from_euler("xyz", [0.4, 0.3, -0.2]).as_matrix()
    seq = [rest + [0.3, -0.1, 0.2], rest @ R.T, rest * 1.3]
    seq += [rest + rng.normal(size=rest.shape) * 0.05 for _ in range(T - 3)]
    return np.array(seq, dtype=np.float32)


def evaluated(ob):
    dg = bpy.context.evaluated_depsgraph_get()
    ev = ob.evaluated_get(dg)
    me = ev.to_mesh()
    co = np.empty(len(me.vertices) * 3, np.float32)
    me.vertices.foreach_get("co", co)
    ev.to_mesh_clear()
    return co.reshape(-1, 3)


def add_mesh_cache(ob, path, fmt, **settings):
    md = ob.modifiers.new("Capture", "MESH_CACHE")
    md.cache_format = fmt
    md.filepath = str(path)
    for k, v in settings.items():
        setattr(md, k, v)
    return md


def add_key(ob, name, offset):
    if ob.data.shape_keys is None:
        ob.shape_key_add(name="Basis", from_mix=False)
    kb = ob.shape_key_add(name=name, from_mix=False)
    kb.data.foreach_set("co", (rest_of(ob) + offset).astype(np.float32).ravel())
    kb.value = 1.0
    return kb


def key_per_frame(ob, seq, first=1):
    """Animate ``ob`` by one shape key per frame (capture case (a))."""
    for t, co in enumerate(seq):
        kb = add_key(ob, f"cap{t}", co - rest_of(ob))
        for f in range(first, first + len(seq)):
            kb.value = 1.0 if f == first + t else 0.0
            kb.keyframe_insert("value", frame=f)


def corners(ob):
    me = ob.data
    off = np.empty(len(me.polygons), np.int32)
    me.polygons.foreach_get("loop_start", off)
    cv = np.empty(len(me.loops), np.int32)
    me.loops.foreach_get("vertex_index", cv)
    return np.r_[off, len(cv)], cv


# --------------------------------------------------------------------------- Mesh Cache: direct read == Blender


CASES = {
    # name: (format, modifier settings, scene frames, scene settings)
    "pc2_frame_start1": ("PC2", dict(frame_start=1.0), np.r_[np.arange(-1, T + 3), 1.5, 3.25], {}),
    "pc2_defaults_axes": (
        "PC2",
        dict(forward_axis="NEG_Z", up_axis="POS_Y", flip_axis=(True, False, True)),
        np.arange(0, T + 1),
        {},
    ),
    "pc2_none_scaled": ("PC2", dict(interpolation="NONE", frame_scale=0.7, frame_start=0.4), np.arange(0, 10), {}),
    "pc2_time_remap": ("PC2", dict(frame_start=1.0), np.arange(1, 12) * 1.0, dict(frame_map_old=100, frame_map_new=50)),
    # Blender divides PC2 times by fps twice: a sample rate of 1/fps^2 plays sample f on frame f
    "pc2_time_quirk": ("PC2", dict(time_mode="TIME"), np.arange(0, 12) * 0.75, dict(pc2_rate=1 / 576)),
    "mdd_time": ("MDD", dict(time_mode="TIME"), np.r_[np.arange(0, T + 2), 2.5], dict(fps=30, fps_base=1.001)),
    "mdd_factor": ("MDD", dict(time_mode="FACTOR", frame_scale=0.2), np.arange(0, 8) * 1.0, {}),
}


@pytest.mark.parametrize("case", list(CASES))
def test_read_mesh_cache_frames_matches_blender(tmp_path, empty_scene, case):
    fmt, settings, frames, render = CASES[case]
    render = dict(render)
    pc2_rate = render.pop("pc2_rate", 1.0)
    for k, v in render.items():
        setattr(empty_scene.render, k, v)
    ob = ico()
    seq = known_sequence(rest_of(ob))
    path = tmp_path / f"cap.{fmt.lower()}"
    if fmt == "PC2":
        pointcache_writer.write_pc2(path, seq, start=0.0 if pc2_rate != 1.0 else 1.0, sample_rate=pc2_rate)
    else:
        pointcache_writer.write_mdd(path, seq, fps=caches.scene_fps(), start_frame=1)
    add_mesh_cache(ob, path, fmt, **settings)
    assert caches.sequence_source(ob) == "mesh_cache"
    assert caches.mesh_cache_direct_read_problem(ob) is None
    empty_scene.frame_set(3)

    got = caches.read_mesh_cache_frames(ob, frames)
    blender = caches.evaluate_frames(ob, frames)
    assert got.dtype == np.float32 and got.shape == (len(frames),) + seq.shape[1:]
    np.testing.assert_allclose(got, blender, atol=TOL, rtol=0)
    assert empty_scene.frame_current == 3

    if case == "pc2_frame_start1":  # known data: frame f plays sample f-1, halves blend
        np.testing.assert_array_equal(got[:2], seq[[0, 0]])
        np.testing.assert_array_equal(got[2 : 2 + T], seq)
        np.testing.assert_array_equal(got[-3], seq[-1])
        np.testing.assert_allclose(got[-2], 0.5 * (seq[0] + seq[1]), atol=1e-6)
    if case == "mdd_time":  # TIME mode + MDD times (start_frame + i) / fps: frame f -> sample f-1
        np.testing.assert_allclose(got[1 : T + 1], seq, atol=1e-6)
    if case == "pc2_time_quirk":
        np.testing.assert_allclose(got[[0, 4, 8]], seq[[0, 3, 5]], atol=1e-6)  # frames 0, 3, 6 (clamped)
    if case == "pc2_defaults_axes":
        M = meshcache.axis_conversion_matrix("NEG_Z", "POS_Y", (True, False, True)).astype(np.float32)
        np.testing.assert_allclose(got[:T], seq @ M.T, atol=1e-6)  # default frame_start 0: frame f -> sample f


def test_unsupported_settings_fall_back_to_evaluation(tmp_path):
    ob = ico()
    seq = known_sequence(rest_of(ob))
    pointcache_writer.write_pc2(tmp_path / "c.pc2", seq)
    md = add_mesh_cache(ob, tmp_path / "c.pc2", "PC2", frame_start=1.0, factor=0.5)
    assert "influence" in caches.mesh_cache_direct_read_problem(ob)
    got = caches.read_mesh_cache_frames(ob, range(1, T + 1))
    np.testing.assert_allclose(got, 0.5 * rest_of(ob) + 0.5 * seq, atol=TOL)
    md.factor = 1.0
    ob.modifiers.new("Smooth", "SMOOTH")
    assert "after it" in caches.mesh_cache_direct_read_problem(ob)
    np.testing.assert_array_equal(caches.read_mesh_cache_frames(ob, [2]), caches.evaluate_frames(ob, [2]))


def test_mesh_cache_vertex_count_mismatch(tmp_path):
    ob = ico()
    pointcache_writer.write_pc2(tmp_path / "w.pc2", np.zeros((2, 7, 3)))
    add_mesh_cache(ob, tmp_path / "w.pc2", "PC2")
    with pytest.raises(CacheVertexCountError, match="7 points but 'Face' has 42 vertices"):
        caches.read_mesh_cache_frames(ob, [1])
    with pytest.raises(MeshError, match="no enabled Mesh Cache"):
        caches.read_mesh_cache_frames(ico("Other"), [1])


# --------------------------------------------------------------------------- shape keys on top of a Mesh Cache


def test_integrate_adds_shape_key_on_top(tmp_path, empty_scene):
    ob = ico()
    rest = rest_of(ob)
    seq = known_sequence(rest)
    pointcache_writer.write_pc2(tmp_path / "c.pc2", seq)
    md = add_mesh_cache(ob, tmp_path / "c.pc2", "PC2", frame_start=1.0)
    rng = np.random.default_rng(3)
    d = np.zeros_like(rest)
    d[:6] = rng.normal(size=(6, 3)) * 0.02
    kb = add_key(ob, "FL_Refine_1", d)
    empty_scene.frame_set(1)
    np.testing.assert_array_equal(evaluated(ob), seq[0])  # Overwrite hides the key

    msg = cache_integrate.cache_to_shape_key_ready(ob)
    assert md.deform_mode == "INTEGRATE" and "Integrate" in msg
    assert "already" in cache_integrate.cache_to_shape_key_ready(ob)
    off, cv = corners(ob)
    R = Rotation.from_euler("xyz", [0.4, 0.3, -0.2]).as_matrix()
    for f, expect in [(1, d), (2, d @ R.T), (3, 1.3 * d)]:  # translation adds exactly; rotation/scale carry it
        empty_scene.frame_set(f)
        np.testing.assert_allclose(evaluated(ob) - seq[f - 1], expect, atol=TOL)
    for f in range(4, T + 1):  # general frames: the per-vertex maps of core.capture.integrate
        empty_scene.frame_set(f)
        M = integrate.integrate_matrices(rest, seq[f - 1], off, cv)
        np.testing.assert_allclose(evaluated(ob), seq[f - 1] + np.einsum("vij,vj->vi", M, d), atol=TOL)
    # a wanted correction on frame 5 -> key offsets via the inverse maps
    want = np.zeros_like(rest)
    want[10:14] = rng.normal(size=(4, 3)) * 0.01
    key = integrate.integrate_offsets_to_key(integrate.integrate_matrices(rest, seq[4], off, cv), want)
    kb.data.foreach_set("co", (rest + key).astype(np.float32).ravel())
    ob.data.update()
    empty_scene.frame_set(5)
    np.testing.assert_allclose(evaluated(ob) - seq[4], want, atol=TOL)
    # the capture is still read exactly (FL_ keys muted by the fallback, direct read ignores them)
    np.testing.assert_allclose(caches.read_mesh_cache_frames(ob, range(1, T + 1)), seq, atol=TOL)
    assert kb.mute is False


# --------------------------------------------------------------------------- generic evaluation


def test_evaluate_frames_mutes_and_restores(empty_scene):
    ob = ico()
    rest = rest_of(ob)
    seq = known_sequence(rest)
    key_per_frame(ob, seq)
    assert caches.sequence_source(ob) == "shape_keys"
    fl = add_key(ob, "FL_fix", np.full_like(rest, 0.01))
    other = add_key(ob, "FL_muted", np.full_like(rest, 5.0))
    own_key(fl), own_key(other)  # FaceLab's output (an artist's FL_* key is part of the capture)
    other.mute = True
    empty_scene.frame_set(4)
    calls = []
    got = caches.evaluate_frames(ob, range(1, T + 1), progress=lambda i, n: calls.append((i, n)))
    np.testing.assert_allclose(got, seq, atol=1e-6)
    assert calls == [(i, T) for i in range(T)]
    assert (fl.mute, other.mute) == (False, True) and empty_scene.frame_current == 4
    final = caches.evaluate_frames(ob, [2], mute_shape_keys_prefix=())
    np.testing.assert_allclose(final[0], seq[1] + 0.01, atol=1e-6)
    np.testing.assert_allclose(caches.read_captured_frames(ob, [2]), seq[1:2], atol=1e-6)
    # FaceLab's own animated keys do not make a mesh "animated"
    ob2 = ico("Static")
    k = add_key(ob2, "FL_Refine_3", np.zeros((42, 3)))
    own_key(k)
    k.keyframe_insert("value", frame=3)
    assert caches.sequence_source(ob2) == "static"


def test_errors_restore_state(empty_scene):
    ob = ico()
    fl = add_key(ob, "FL_fix", np.zeros((42, 3)))
    bpy.context.scene.collection.objects.unlink(ob)
    empty_scene.frame_set(7)
    with pytest.raises(MeshError, match="not in the active view layer"):
        caches.evaluate_frames(ob, [1, 2])
    assert fl.mute is False and empty_scene.frame_current == 7
    bpy.context.scene.collection.objects.link(ob)
    with pytest.raises(FaceLabError, match="evenly spaced"):
        bakes.bake_pc2(ob, [1, 2, 4], "/tmp/never.pc2")


# --------------------------------------------------------------------------- bakes


def test_bake_pc2_and_mdd_round_trip(tmp_path, empty_scene):
    ob = ico()
    rest = rest_of(ob)
    seq = known_sequence(rest)
    key_per_frame(ob, seq, first=3)
    add_key(ob, "FL_fix", np.full_like(rest, 0.01))
    frames = range(3, 3 + T)
    final = caches.evaluate_frames(ob, frames, mute_shape_keys_prefix=())
    np.testing.assert_allclose(final, seq + 0.01, atol=1e-6)

    p = bakes.bake_pc2(ob, frames, tmp_path / "out" / "face.pc2")
    data, start, rate = pointcache.read_pc2(p)
    np.testing.assert_array_equal(data, final)
    assert (start, rate) == (3.0, 1.0)
    m = bakes.bake_mdd(ob, frames, tmp_path / "face.mdd")
    data, times = pointcache.read_mdd(m)
    np.testing.assert_array_equal(data, final)
    np.testing.assert_allclose(times, np.arange(3, 3 + T) / 24.0, rtol=1e-6)

    # Blender plays the baked files back on the same frames
    plain = ico("Plain")
    add_mesh_cache(plain, p, "PC2", frame_start=3.0)
    np.testing.assert_array_equal(caches.evaluate_frames(plain, frames), final)
    plain.modifiers.clear()
    add_mesh_cache(plain, m, "MDD", time_mode="TIME")
    np.testing.assert_allclose(caches.evaluate_frames(plain, frames), final, atol=1e-6)


# --------------------------------------------------------------------------- Alembic


def test_alembic_bake_import_and_shape_key_ready(tmp_path, empty_scene):
    src = ico("Capture")
    rest = rest_of(src)
    seq = known_sequence(rest)
    key_per_frame(src, seq)
    src_frames = caches.evaluate_frames(src, range(1, T + 1))
    np.testing.assert_allclose(src_frames, seq, atol=1e-6)
    other = ico("Bystander")
    other.select_set(True)
    bpy.context.view_layer.objects.active = other
    abc = bakes.bake_alembic(src, range(1, T + 1), tmp_path / "cap.abc")
    assert abc.is_file()
    assert other.select_get() and not src.select_get() and bpy.context.view_layer.objects.active == other

    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    assert bpy.ops.wm.alembic_import(filepath=str(abc)) == {"FINISHED"}
    assert [o.name for o in bpy.data.objects] == ["Capture"]  # only the baked object
    ob = bpy.data.objects["Capture"]
    assert [m.type for m in ob.modifiers] == ["MESH_SEQUENCE_CACHE"]
    assert caches.sequence_source(ob) == "mesh_sequence_cache"
    # vertex order and float32 values survive the round trip exactly
    np.testing.assert_array_equal(caches.evaluate_frames(ob, range(1, T + 1)), src_frames)
    seq = src_frames

    # shape keys do not show on top of the Alembic modifier...
    d = np.zeros_like(rest)
    d[:4] = 0.05
    kb = add_key(ob, "FL_fix", d)
    scene.frame_set(1)
    np.testing.assert_array_equal(evaluated(ob), seq[0])
    kb.mute = True
    # ...until the capture is re-played by an Integrate Mesh Cache
    with pytest.raises(FaceLabError, match="Save the .blend first"):
        cache_integrate.cache_to_shape_key_ready(ob)  # unsaved file, no directory: nothing changes
    assert [m.show_viewport for m in ob.modifiers] == [True]
    msg = cache_integrate.cache_to_shape_key_ready(ob, directory=tmp_path, scene_frames=range(1, T + 1))
    assert kb.mute is True
    kb.mute = False
    msc, mc = ob.modifiers
    assert msc.type == "MESH_SEQUENCE_CACHE" and not msc.show_viewport and not msc.show_render
    assert mc.type == "MESH_CACHE" and mc.deform_mode == "INTEGRATE" and mc.cache_format == "PC2"
    assert "Capture_capture.pc2" in msg and "turned it off" in msg
    np.testing.assert_array_equal(pointcache.read_pc2(tmp_path / "Capture_capture.pc2")[0], seq)
    assert caches.sequence_source(ob) == "mesh_cache"
    np.testing.assert_allclose(caches.read_captured_frames(ob, range(1, T + 1)), seq, atol=TOL)
    scene.frame_set(1)  # frame 1 is a translation of the rest mesh: the key adds exactly
    np.testing.assert_allclose(evaluated(ob), seq[0] + d, atol=TOL)
    off, cv = corners(ob)
    base = rest_of(ob)  # the imported mesh's own positions (frame 1 of the capture)
    for f in (2, 5):
        scene.frame_set(f)
        M = integrate.integrate_matrices(base, seq[f - 1], off, cv)
        np.testing.assert_allclose(evaluated(ob), seq[f - 1] + np.einsum("vij,vj->vi", M, d), atol=TOL)
    # a second call does not bake again, and the artist's modifier is never deleted
    assert "already" in cache_integrate.cache_to_shape_key_ready(ob, directory=tmp_path)
    assert len(ob.modifiers) == 2


def test_a_vertex_count_changing_modifier_is_named_in_the_refusal(empty_scene):
    """A Subdivision modifier the artist named 'Smooth Lips' on the face: both evaluated-mesh readers refuse
    and name the enabled modifiers, so the artist knows which one to disable."""
    from facelab_addon.blender.mesh import evaluated_vertices

    ob = ico()
    ob.modifiers.new("Smooth Lips", "SUBSURF").levels = 1
    dg = bpy.context.evaluated_depsgraph_get()
    with pytest.raises(MeshError, match="vertex count.*'Smooth Lips'"):
        evaluated_vertices(ob, dg)
    with pytest.raises(MeshError, match="instead of.*'Smooth Lips'"):
        caches.evaluate_frames(ob, [1])
    ob.modifiers["Smooth Lips"].show_viewport = False
    assert caches.evaluate_frames(ob, [1]).shape == (1, len(ob.data.vertices), 3)
