"""How corrections are stored (``pipeline.correctives``): a low-rank correction becomes a few keys, a
full-rank one a point cache played by a Mesh Cache modifier; both evaluate (depsgraph) to the correction
within the tolerance; the tolerance is in world millimetres whatever the units and the object's scale;
re-running and undo replace only FaceLab's own output."""

import math

import bpy
import numpy as np
import pytest

from facelab_addon.blender import caches
from facelab_addon.blender.ownership import owned_keys
from facelab_addon.blender.shapekeys import add_corrective_key, key_values_bulk
from facelab_addon.core.errors import FaceLabError, MeshError
from facelab_addon.core.geometry.compress import StorageOutcome
from facelab_addon.names import CORRECTION_CACHES_PROP, OWNED_KEYS_PROP, PROPAGATE_PREFIX, SOLVE_PREFIX
from facelab_addon.pipeline.correctives import (
    CorrectionResult,
    CorrectionWriter,
    StorageSettings,
    write_corrective_keys,
)
from facelab_addon.pipeline.settings import describe

pytestmark = pytest.mark.blender

FRAMES = np.arange(1, 31)
TOL = 1e-5  # 0.01 mm in metres


def head(animated=True, scale=1.0):
    """A sphere 'head' (radius 0.1 m * ``scale``); with ``animated``, two keyed capture shape keys."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    me = bpy.data.meshes.new("Head")
    import bmesh

    bm = bmesh.new()
    bmesh.ops.create_uvsphere(bm, u_segments=48, v_segments=24, radius=0.1 * scale)
    bm.to_mesh(me)
    bm.free()
    obj = bpy.data.objects.new("Head", me)
    scene.collection.objects.link(obj)
    bpy.context.view_layer.objects.active = obj
    if animated:
        co = np.array([v.co[:] for v in me.vertices])
        add_corrective_key(obj, "Open", np.c_[0 * co[:, 0], np.minimum(co[:, 1], 0) * 0.2, 0 * co[:, 2]])
        add_corrective_key(obj, "Smile", np.c_[co[:, 0] * 0.1, 0 * co[:, 1], np.abs(co[:, 0]) * 0.1])
        obj.data.shape_keys[OWNED_KEYS_PROP] = []  # the artist's keys, not FaceLab's
        t = (FRAMES - 1) / (len(FRAMES) - 1)
        key_values_bulk(obj, ["Open", "Smile"], FRAMES, np.c_[np.sin(math.pi * t), t])
    return scene, obj


def smooth_fields(obj, k, seed=0, amp=1e-3):
    """(k,V,3) smooth displacement fields (object units), ``amp`` metres at most."""
    rng = np.random.default_rng(seed)
    co = np.array([v.co[:] for v in obj.data.vertices])
    r = np.abs(co).max()
    out = np.empty((k, len(co), 3))
    for i in range(k):
        c = co[rng.integers(len(co))]
        w = np.exp(-np.sum((co - c) ** 2, axis=1) / (0.3 * r) ** 2)
        out[i] = w[:, None] * rng.normal(0, 1, 3) * amp * r / 0.1
    return out


def low_rank(obj, rank=3, seed=0):
    rng = np.random.default_rng(seed)
    B = smooth_fields(obj, rank, seed)
    W = np.sin(np.outer(FRAMES, rng.uniform(0.1, 0.5, rank)) + rng.uniform(0, 3, rank))
    return np.einsum("tr,rvc->tvc", W, B)


def full_rank(obj, seed=1):
    rng = np.random.default_rng(seed)
    return rng.normal(0, 3e-4, (len(FRAMES), len(obj.data.vertices), 3))  # every frame its own shape


def shown(obj, frames=FRAMES, muted=()):
    return caches.evaluate_frames(obj, frames, mute_shape_keys_prefix=muted).astype(np.float64)


def saved(tmp_path, name="shot.blend"):
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / name))


def test_storage_settings_describe_themselves():
    fields = {d["name"]: d for d in describe(StorageSettings)}
    assert set(fields) == {"key_budget", "tolerance_mm", "cache_format", "cache_directory"}
    assert fields["tolerance_mm"]["unit"] == "mm" and fields["tolerance_mm"]["default"] == 0.01
    assert 16 <= fields["key_budget"]["default"] <= 32
    assert [c[0] for c in fields["cache_format"]["choices"]] == ["PC2", "MDD"]


@pytest.mark.parametrize("animated", [False, True])
def test_low_rank_correction_becomes_keys_that_evaluate_to_it(animated, addon):
    scene, obj = head(animated)
    before = shown(obj)
    D = low_rank(obj)
    keys = write_corrective_keys(obj, PROPAGATE_PREFIX, D, FRAMES, scene=scene)
    res = keys.storage
    assert isinstance(res, CorrectionResult) and res.mode == "keys" and res.cache_path == ""
    assert res.outcome is StorageOutcome.KEYS and not res.outcome.reported
    assert keys == owned_keys(obj, PROPAGATE_PREFIX) and 1 <= len(keys) <= 3 == res.rank
    assert not [m for m in obj.modifiers]  # no cache
    err = np.linalg.norm(shown(obj) - before - D, axis=2)
    assert err.max() <= TOL and res.max_error_mm <= 0.01


@pytest.mark.parametrize("animated,fmt", [(False, "PC2"), (True, "PC2"), (True, "MDD")])
def test_full_rank_correction_becomes_a_cache_beside_the_blend(tmp_path, animated, fmt, addon):
    scene, obj = head(animated)
    saved(tmp_path)
    before = shown(obj)
    D = full_rank(obj)
    res = write_corrective_keys(obj, SOLVE_PREFIX, D, FRAMES, scene=scene,
                                settings=StorageSettings(cache_format=fmt)).storage
    assert res.mode == "cache" and res.keys == [] and not owned_keys(obj, SOLVE_PREFIX)
    assert res.outcome is StorageOutcome.CACHE and res.outcome.reported
    assert res.cache_path == str(tmp_path / f"shot_Head_FL_Solve.{fmt.lower()}") and "point cache" in res.note
    md = obj.modifiers[res.modifier]
    assert md.type == "MESH_CACHE" and md.cache_format == fmt and bpy.path.abspath(md.filepath) == res.cache_path
    # static capture: the cache holds rest + correction and integrates shape keys; animated: the corrected input
    assert md.deform_mode == ("OVERWRITE" if animated else "INTEGRATE") and list(obj.modifiers).index(md) == 0
    err = np.linalg.norm(shown(obj) - before - D, axis=2)
    assert err.max() <= TOL  # float32 positions
    # outside the stored frames the cache is off; reading the capture leaves it out, like FaceLab's keys
    np.testing.assert_allclose(shown(obj, [0, 31]), shown(obj, [0, 31], muted=("FL_",)), atol=1e-7)
    np.testing.assert_allclose(shown(obj, muted=("FL_",)), before, atol=1e-7)
    assert caches.sequence_source(obj) == ("shape_keys" if animated else "static")
    # the .blend stays light: the correction lives in the file
    saved(tmp_path)
    assert (tmp_path / "shot.blend").stat().st_size < 2_000_000


def test_a_cache_needs_a_place_and_falls_back_to_keys_in_an_unsaved_blend(addon):
    scene, obj = head(False)
    D = full_rank(obj)[:6]
    res = write_corrective_keys(obj, SOLVE_PREFIX, D, FRAMES[:6], scene=scene,
                                settings=StorageSettings(key_budget=2)).storage
    assert res.mode == "keys" and len(res.keys) == 6 and "not saved" in res.note and "budget of 2" in res.note
    assert res.outcome is StorageOutcome.KEYS_OVER_BUDGET and res.outcome.reported
    assert np.linalg.norm(shown(obj, FRAMES[:6]) - shown(obj, FRAMES[:6], muted=("FL_",)) - D, axis=2).max() <= TOL


def test_rerun_and_undo_replace_only_facelabs_output(tmp_path, addon):
    scene, obj = head(True)
    saved(tmp_path)
    n = len(obj.data.vertices)
    # the artist's things: a key named like FaceLab's, a Mesh Cache modifier, a file where FaceLab would write
    add_corrective_key(obj, "FL_Solve_MyFix", np.full((n, 3), 1e-4))
    obj.data.shape_keys[OWNED_KEYS_PROP] = []  # made by the artist
    theirs = tmp_path / "shot_Head_FL_Solve.pc2"
    theirs.write_bytes(b"the artist's cache")
    art = obj.modifiers.new("FL_Solve_Cache", "MESH_CACHE")  # their own, named like FaceLab's
    art.show_viewport = False
    captured = shown(obj, muted=(SOLVE_PREFIX,)) - 0  # with the artist's FL_Solve_MyFix (not FaceLab's)

    D = full_rank(obj)
    r1 = write_corrective_keys(obj, SOLVE_PREFIX, D, FRAMES, scene=scene).storage
    assert r1.mode == "cache" and r1.cache_path.endswith("shot_Head_FL_Solve.001.pc2")
    assert theirs.read_bytes() == b"the artist's cache" and r1.modifier == "FL_Solve_Cache.001"
    np.testing.assert_allclose(shown(obj), captured + D, atol=TOL)
    bpy.ops.ed.undo_push(message="first")

    D2 = low_rank(obj)
    r2 = write_corrective_keys(obj, SOLVE_PREFIX, D2, FRAMES, scene=scene).storage
    bpy.ops.ed.undo_push(message="second")
    assert r2.mode == "keys" and r2.keys == owned_keys(obj, SOLVE_PREFIX)
    assert [m.name for m in obj.modifiers] == ["FL_Solve_Cache"]  # FaceLab's cache modifier went, theirs stays
    assert "FL_Solve_MyFix" in obj.data.shape_keys.key_blocks and theirs.read_bytes() == b"the artist's cache"
    np.testing.assert_allclose(shown(obj), captured + D2, atol=TOL)

    # the same again: FaceLab's keys replaced (same names), nothing else
    r3 = write_corrective_keys(obj, SOLVE_PREFIX, 2 * D2, FRAMES, scene=scene).storage
    assert r3.keys == r2.keys and len(obj.data.shape_keys.key_blocks) == 4 + len(r3.keys)
    np.testing.assert_allclose(shown(obj), captured + 2 * D2, atol=TOL)
    bpy.ops.ed.undo_push(message="third")

    # undo twice: back to the cache run, which still plays its file
    bpy.ops.ed.undo()
    bpy.ops.ed.undo()
    obj = bpy.data.objects["Head"]
    assert not owned_keys(obj, SOLVE_PREFIX) and "FL_Solve_Cache.001" in obj.modifiers
    np.testing.assert_allclose(shown(obj), captured + D, atol=TOL)
    assert obj[CORRECTION_CACHES_PROP].to_dict()[SOLVE_PREFIX]["modifier"] == "FL_Solve_Cache.001"


def test_the_tolerance_is_world_millimetres_whatever_the_units(addon):
    """The same physical correction at 0.01, 1 and 100 units per metre: with the mesh in those units (scene
    Unit Scale to match), and with a metre mesh and the object scaled instead: the same number of keys,
    every vertex within 0.01 mm of the world."""
    counts = {}
    for units in (0.01, 1.0, 100.0):
        for how in ("data", "object"):
            scene, obj = head(False, scale=units if how == "data" else 1.0)
            scene.unit_settings.scale_length = 1.0 / units
            if how == "object":
                obj.scale = (units, units, units)
            rng = np.random.default_rng(7)
            B = smooth_fields(obj, 10, seed=7)
            W = rng.normal(0, 1, (len(FRAMES), 10)) * 0.5 ** np.arange(10)  # a decaying spectrum
            D = np.einsum("tr,rvc->tvc", W, B)
            keys = write_corrective_keys(obj, PROPAGATE_PREFIX, D, FRAMES, scene=scene)
            counts[units, how] = len(keys)
            err = np.linalg.norm(shown(obj) - shown(obj, muted=("FL_",)) - D, axis=2).max()
            metres = err * (units if how == "object" else 1.0) / units  # local -> world units -> metres
            assert metres <= 1.01e-5, (units, how, metres)
    assert len(set(counts.values())) == 1 and 3 <= counts[1.0, "data"] <= 10, counts


def test_writer_streams_chunks_and_takes_a_low_rank_product(addon):
    scene, obj = head(True)
    before = shown(obj)
    lip = np.arange(0, len(obj.data.vertices), 2)
    D = low_rank(obj)[:, lip]
    with CorrectionWriter(scene, obj, PROPAGATE_PREFIX, vertices=lip) as w:
        for i in range(0, len(FRAMES), 7):  # chunks of 7 frames
            w.add(FRAMES[i:i + 7], D[i:i + 7])
        res = w.finish()
    assert res.mode == "keys" and res.rank == 3 and res.frames == len(FRAMES)
    want = before.copy()
    want[:, lip] += D
    np.testing.assert_allclose(shown(obj), want, atol=TOL)
    # already low rank (Propagate's output is, by construction): no spool, same result
    rng = np.random.default_rng(2)
    B, W = smooth_fields(obj, 4, seed=3)[:, lip], rng.normal(0, 1, (len(FRAMES), 4))
    with CorrectionWriter(scene, obj, PROPAGATE_PREFIX, vertices=lip) as w:
        w.add_low_rank(FRAMES, B, W)
        res = w.finish()
    assert res.mode == "keys" and res.rank == 4
    want = before.copy()
    want[:, lip] += np.einsum("tr,rvc->tvc", W, B)
    np.testing.assert_allclose(shown(obj), want, atol=TOL)
    # all zero: nothing stored, FaceLab's previous keys removed
    with CorrectionWriter(scene, obj, PROPAGATE_PREFIX, vertices=lip) as w:
        w.add(FRAMES, np.zeros_like(D))
        assert w.finish().mode == "none"
    assert not owned_keys(obj, PROPAGATE_PREFIX)


def test_bad_input_is_refused_before_anything_changes(addon):
    scene, obj = head(True)
    keys = list(obj.data.shape_keys.key_blocks.keys())
    with pytest.raises(FaceLabError, match="key budget"):
        CorrectionWriter(scene, obj, SOLVE_PREFIX, settings=StorageSettings(key_budget=0))
    with pytest.raises(FaceLabError, match="cache format"):
        CorrectionWriter(scene, obj, SOLVE_PREFIX, settings=StorageSettings(cache_format="ABC"))
    w = CorrectionWriter(scene, obj, SOLVE_PREFIX)
    with pytest.raises(MeshError, match=r"must be \(2,1106,3\), got \(2, 10, 3\)"):
        w.add([1, 2], np.zeros((2, 10, 3)))
    bad = np.zeros((1, len(obj.data.vertices), 3))
    bad[0, 5] = np.nan
    with pytest.raises(MeshError, match="NaN"):
        w.add([1], bad)
    w.close()
    obj.modifiers.new("Subdivision", "SUBSURF")
    with pytest.raises(MeshError, match="Subdivision"):
        CorrectionWriter(scene, obj, SOLVE_PREFIX)  # measured on the evaluated mesh: cannot be mapped back
    assert list(obj.data.shape_keys.key_blocks.keys()) == keys


@pytest.mark.slow
def test_reconstruct_solver_result_as_keys_then_as_a_cache(tmp_path, ict, addon, monkeypatch):
    """A pipeline through the policy: Reconstruct from Bundles stores its per-frame result as keys (default
    budget), then, with a budget of 2 keys, as a cache replacing those keys; both evaluate to the solver's
    reconstruction within 0.01 mm."""
    from facelab_addon.core.lgi.indexing.indexer import GeometricIndexer
    from facelab_addon.names import RECONSTRUCT_PREFIX
    from facelab_addon.pipeline.reconstruct import ReconstructSettings, reconstruct_from_bundles

    from ..pipeline.test_reconstruct import EXPR, _shot

    keys = EXPR[:6]
    poses = [{}, {keys[0]: 0.5}, {keys[1]: 0.7, keys[2]: 0.3}, {keys[3]: 1.0}, {keys[4]: 0.6, keys[5]: 0.4}]
    scene, obj, empties, truth, pts = _shot(ict, keys, poses)
    saved(tmp_path)
    solved = {}
    real = GeometricIndexer.reconstruct_stream

    def spy(self, bundles, jaw, sink, **k):  # the pipeline streams the solver's frames: collect them too
        X = solved["X"] = np.full((len(bundles), self.dataset.V, 3), np.nan)

        def both(t, x):
            X[t] = x
            sink(t, x)

        return real(self, bundles, jaw, both, **k)

    monkeypatch.setattr(GeometricIndexer, "reconstruct_stream", spy)
    frames = range(len(poses))
    r = reconstruct_from_bundles(scene, obj, ReconstructSettings(bind_frame=0, selected=empties, method="INDEXING"))
    assert r.keys and r.keys.storage.mode == "keys" and len(r.keys) <= 5
    assert np.linalg.norm(shown(obj, frames, muted=()) - solved["X"], axis=2).max() <= TOL

    scene.facelab_store.key_budget = 2  # the shot's storage setting (FaceLab > Train & Propagate > Settings)
    r = reconstruct_from_bundles(scene, obj, ReconstructSettings(bind_frame=0, selected=empties, method="INDEXING"))
    st = r.keys.storage
    assert r.keys == [] and st.mode == "cache" and "does not fit in 2 keys" in st.note
    assert not [k for k in obj.data.shape_keys.key_blocks.keys() if k.startswith(RECONSTRUCT_PREFIX)]
    assert obj.modifiers[st.modifier].deform_mode == "INTEGRATE"  # the dataset keys are not animated
    assert np.linalg.norm(shown(obj, frames, muted=()) - solved["X"], axis=2).max() <= TOL


@pytest.mark.parametrize("budget", [24, 2])
@pytest.mark.parametrize("subset", [False, True])
def test_over_a_captured_point_cache_keys_and_cache_show_the_same(tmp_path, budget, subset, addon):
    """Over a PC2 capture (Mesh Cache, Integrate) the deltas are key offsets in the cache's local frames
    (``cache_integrate``); stored as keys or as a correction cache they show the same correction."""
    from facelab_addon.blender.cache_integrate import polygon_corners
    from facelab_addon.core.capture.integrate import integrate_matrices, integrate_offsets_to_key
    from facelab_addon.core.capture.pointcache_writer import write_pc2

    scene, obj = head(False)
    saved(tmp_path)
    rest = np.array([v.co[:] for v in obj.data.vertices])
    frames = FRAMES[:10]
    a = np.radians(3.0) * np.arange(len(frames))  # the captured head turns
    R = np.stack([[[np.cos(x), 0, np.sin(x)], [0, 1, 0], [-np.sin(x), 0, np.cos(x)]] for x in a])
    cap = np.einsum("tij,vj->tvi", R, rest) * (1 + 0.2 * np.clip(rest[:, 1], 0, None))[None, :, None]
    write_pc2(tmp_path / "capture.pc2", cap, start=float(frames[0]))
    mc = obj.modifiers.new("Capture", "MESH_CACHE")
    mc.cache_format, mc.filepath, mc.deform_mode = "PC2", str(tmp_path / "capture.pc2"), "INTEGRATE"
    mc.frame_start, mc.forward_axis, mc.up_axis = float(frames[0]), "POS_Y", "POS_Z"
    captured = shown(obj, frames)
    np.testing.assert_allclose(captured, cap, atol=1e-6)
    D = (full_rank(obj) if budget == 2 else low_rank(obj))[: len(frames)]  # wanted on the evaluated mesh
    sub = np.arange(0, len(rest), 3) if subset else None  # a correction of some vertices only (as Propagate's)
    if subset:
        D[:, np.setdiff1d(np.arange(len(rest)), sub)] = 0.0
    corners = polygon_corners(obj.data)
    K = np.stack([integrate_offsets_to_key(integrate_matrices(rest, cap[t], *corners), D[t])
                  for t in range(len(frames))])
    res = write_corrective_keys(obj, PROPAGATE_PREFIX, K if sub is None else K[:, sub], frames, scene=scene,
                                vertices=sub, settings=StorageSettings(key_budget=budget)).storage
    assert res.mode == ("cache" if budget == 2 else "keys")
    if budget == 2:  # under the capture, playing the key offsets: the file holds only the correction
        assert [m.name for m in obj.modifiers] == [res.modifier, "Capture"] and "under the capture" in res.note
        assert obj.modifiers[res.modifier].deform_mode == "INTEGRATE"
        from facelab_addon.core.capture.pointcache import read_pc2

        held = read_pc2(res.cache_path)[0]
        np.testing.assert_allclose(held - rest[None].astype(np.float32), K if sub is None else _on(K, sub), atol=1e-7)
        # the capture is still read straight from its file (the correction cache is FaceLab's output)
        assert caches.mesh_cache_direct_read_problem(obj) is None
    assert caches.sequence_source(obj) == "mesh_cache"  # the capture is still the capture
    np.testing.assert_allclose(shown(obj, frames, muted=("FL_",)), captured, atol=1e-6)
    np.testing.assert_allclose(caches.read_captured_frames(obj, frames), captured, atol=1e-6)
    err = np.linalg.norm(shown(obj, frames, muted=()) - captured - D, axis=2)
    assert err.max() <= 2 * TOL, err.max()  # the tolerance on the keys, carried by the cache's frames


def _on(K, sub):
    out = np.zeros_like(K)
    out[:, sub] = K[:, sub]
    return out


def _turning_capture(tmp_path, obj, frames):
    """Save the .blend in ``tmp_path`` and give ``obj`` a PC2 capture (Integrate Mesh Cache) of its rest mesh
    turning 4 degrees a frame about z; returns ``(rest (V,3), capture (T,V,3))``."""
    from facelab_addon.core.capture.pointcache_writer import write_pc2

    saved(tmp_path)
    rest = np.array([v.co[:] for v in obj.data.vertices])
    a = np.radians(4.0) * np.arange(len(frames))
    R = np.stack([[[np.cos(x), -np.sin(x), 0], [np.sin(x), np.cos(x), 0], [0, 0, 1]] for x in a])
    cap = np.einsum("tij,vj->tvi", R, rest)
    write_pc2(tmp_path / "capture.pc2", cap, start=float(frames[0]))
    mc = obj.modifiers.new("Capture", "MESH_CACHE")
    mc.cache_format, mc.filepath, mc.deform_mode = "PC2", str(tmp_path / "capture.pc2"), "INTEGRATE"
    mc.frame_start, mc.forward_axis, mc.up_axis = float(frames[0]), "POS_Y", "POS_Z"
    return rest, cap


def test_under_a_capture_a_key_moving_the_corrected_vertices_keeps_the_cache_exact(tmp_path, addon):
    """Where the artist's own shape key moves corrected vertices on a corrected frame, a correction cache under
    the capture would carry that key through its own surface; the cache then goes after the capture holding the
    whole corrected input (Overwrite), and still shows capture + key + correction."""
    from facelab_addon.blender.cache_integrate import polygon_corners
    from facelab_addon.core.capture.integrate import integrate_matrices, integrate_offsets_to_key

    scene, obj = head(False)
    frames = FRAMES[:8]
    rest, cap = _turning_capture(tmp_path, obj, frames)
    sub = np.arange(0, len(rest), 2)
    fix = np.zeros_like(rest)
    fix[sub[:40]] = 2e-3  # the artist's key moves some corrected vertices
    add_corrective_key(obj, "ArtistFix", fix)
    obj.data.shape_keys[OWNED_KEYS_PROP] = []
    key_values_bulk(obj, ["ArtistFix"], [frames[2], frames[3], frames[4]], [0.0, 1.0, 0.0])
    before = shown(obj, frames, muted=("FL_",))
    D = full_rank(obj)[: len(frames)]
    D[:, np.setdiff1d(np.arange(len(rest)), sub)] = 0.0
    corners = polygon_corners(obj.data)
    K = np.stack([integrate_offsets_to_key(integrate_matrices(rest, cap[t], *corners), D[t])
                  for t in range(len(frames))])
    res = write_corrective_keys(obj, PROPAGATE_PREFIX, K[:, sub], frames, scene=scene, vertices=sub,
                                settings=StorageSettings(key_budget=2)).storage
    assert res.mode == "cache" and [m.name for m in obj.modifiers] == ["Capture", res.modifier]
    assert obj.modifiers[res.modifier].deform_mode == "OVERWRITE"
    err = np.linalg.norm(shown(obj, frames, muted=()) - before - D, axis=2)
    assert err.max() <= 2 * TOL, err.max()
    # without the key on corrected frames the same correction goes under the capture
    key_values_bulk(obj, ["ArtistFix"], [frames[2], frames[3], frames[4]], [0.0, 0.0, 0.0])
    res = write_corrective_keys(obj, PROPAGATE_PREFIX, K[:, sub], frames, scene=scene, vertices=sub,
                                settings=StorageSettings(key_budget=2)).storage
    assert [m.name for m in obj.modifiers] == [res.modifier, "Capture"]
    err = np.linalg.norm(shown(obj, frames, muted=()) - shown(obj, frames, muted=("FL_",)) - D, axis=2)
    assert err.max() <= 2 * TOL, err.max()


def test_after_capture_the_correction_is_a_patch_of_its_vertices_rerun_and_undo_replace_it(tmp_path, addon):
    """``after_capture``: displacements of the captured mesh go to a point cache of the corrected vertices only,
    added after the capture by a Geometry Nodes modifier; they add to the capture and to the artist's keys
    exactly; a re-run and undo replace only FaceLab's patch (modifier, node group, patch object, attribute)."""
    from facelab_addon.blender.ownership import correction_cache
    from facelab_addon.core.capture.pointcache import read_pc2

    scene, obj = head(False)
    frames = FRAMES[:8]
    rest, _ = _turning_capture(tmp_path, obj, frames)
    sub = np.arange(0, len(rest), 4)
    add_corrective_key(obj, "ArtistFix", np.full_like(rest, 1e-3))  # the artist's key, on the corrected vertices
    obj.data.shape_keys[OWNED_KEYS_PROP] = []
    key_values_bulk(obj, ["ArtistFix"], frames[:3], [0.0, 1.0, 0.0])
    art = obj.modifiers.new("FL_Prop_Cache", "NODES")  # the artist's own, named like FaceLab's
    art.show_viewport = False
    before = shown(obj, frames, muted=("FL_",))

    def store(D):
        with CorrectionWriter(scene, obj, PROPAGATE_PREFIX, vertices=sub, after_capture=True) as w:
            w.add(frames[:5], D[:5])
            w.add(frames[5:], D[5:])
            return w.finish()

    D1 = full_rank(obj)[: len(frames)][:, sub]
    r1 = store(D1)
    assert r1.mode == "cache" and r1.keys == [] and "Geometry Nodes" in r1.note
    assert r1.outcome is StorageOutcome.PATCH_CACHE
    assert [m.name for m in obj.modifiers] == ["Capture", r1.modifier, "FL_Prop_Cache"]
    md = obj.modifiers[r1.modifier]
    assert md.type == "NODES" and list(obj.modifiers).index(md) == 1  # right after the capture
    held, _, _ = read_pc2(r1.cache_path)
    assert held.shape == (len(frames), len(sub), 3)  # the corrected vertices only
    want = before.copy()
    want[:, sub] += D1
    np.testing.assert_allclose(shown(obj, frames), want, atol=1e-7)
    np.testing.assert_allclose(shown(obj, frames, muted=("FL_",)), before, atol=1e-7)  # the capture stays readable
    np.testing.assert_allclose(shown(obj, [0, 9]), shown(obj, [0, 9], muted=("FL_",)), atol=1e-7)  # off outside
    bpy.ops.ed.undo_push(message="first")

    D2 = 0.5 * D1[::-1]
    r2 = store(D2)
    bpy.ops.ed.undo_push(message="second")
    assert r2.cache_path != r1.cache_path and r2.modifier == r1.modifier
    assert [m.name for m in obj.modifiers] == ["Capture", r2.modifier, "FL_Prop_Cache"]
    patches = [o for o in bpy.data.objects if o != obj]
    assert len(patches) == 1 and len(bpy.data.node_groups) == 1  # the first patch went with its modifier
    want2 = before.copy()
    want2[:, sub] += D2
    np.testing.assert_allclose(shown(obj, frames), want2, atol=1e-7)

    bpy.ops.ed.undo()
    obj = bpy.data.objects["Head"]
    np.testing.assert_allclose(shown(obj, frames), want, atol=1e-7)  # the first run, still playing its file
    assert correction_cache(obj, PROPAGATE_PREFIX)[1][-1] == r1.cache_path
    assert "FL_Prop_Cache" in obj.modifiers and not obj.modifiers["FL_Prop_Cache"].show_viewport  # theirs
