"""Headless: a capture played by a Mesh Cache (PC2) -> Refine Lips on a few frames ->
Propagate. Corrective keys must show on top of the cache (Integrate) and match the core."""

import bpy
import numpy as np
import pytest

from facelab_addon.blender import caches
from facelab_addon.blender.camera import camera_from_blender
from facelab_addon.blender.mesh import mesh_triangles, vertex_group_mask
from facelab_addon.blender.strokes import write_stroke_pixels
from facelab_addon.core.capture.pointcache_writer import write_pc2
from facelab_addon.core.geometry.silhouette import contour_distance
from facelab_addon.core.lips.mouth import find_mouth
from facelab_addon.core.lips.regressor import LipRegressor
from facelab_addon.core.lips.regions import faces_in_region
from facelab_addon.pipeline.propagate import training_input
from facelab_addon.testing import synthetic as syn
from facelab_addon.testing.scenes import build_ict_face_scene

pytestmark = pytest.mark.blender

SCALE, UPM = 0.01, 0.001
T = 16
TRAIN = [3, 9, 14]


@pytest.mark.parametrize("patch", [False, pytest.param(True, marks=pytest.mark.slow)])
def test_refine_and_propagate_on_a_mesh_cache(tmp_path, ict, addon, patch, monkeypatch):
    """``patch``: the key offsets count as needing more shapes than keys hold (as on a long shot), so the
    correction goes to a point cache of the corrected vertices after the capture (Geometry Nodes)."""
    from facelab_addon.pipeline import propagate as prop

    if patch:
        monkeypatch.setattr(prop, "key_shapes_over_cache", lambda budget: 1)
    F = ict.faces
    neutral = ict.neutral * SCALE
    t = np.linspace(0, 1, T)
    jaw = 0.15 + 0.12 * np.sin(2 * np.pi * t)
    funnel = 0.15 + 0.1 * np.cos(2 * np.pi * t)
    truth = np.stack([ict.pose({"jawOpen": a, "mouthFunnel": b}) * SCALE for a, b in zip(jaw, funnel)])
    fixed = ~ict.part_vertex_mask("M_Face")
    mouth = find_mouth(neutral, F, fixed, loop=syn.ICT_MOUTH_LOOP, units_per_mm=UPM)
    w, side = syn.lip_error_weights(neutral, F, fixed, mouth=mouth)
    err = np.zeros_like(neutral)
    err[:, 1] = side * w * 1.0 * UPM
    strength = 1.5 - jaw / 0.3  # the error grows as the jaw closes: learnable from the mouth
    captured = truth + strength[:, None, None] * err[None]
    pc2 = write_pc2(tmp_path / "capture.pc2", captured.astype(np.float32))

    cam = syn.frontal_camera(neutral, mouth.center, distance=0.40)
    fs = build_ict_face_scene(ict, frame_range=(1, T), scale=SCALE, fixed_group=True, camera=cam, select=False)
    scene, obj = fs.scene, fs.obj
    md = obj.modifiers.new("Capture", "MESH_CACHE")
    md.cache_format, md.filepath, md.frame_start = "PC2", str(pc2), 1.0  # frame 1 plays sample 0
    bpy.context.view_layer.objects.active = obj
    np.testing.assert_allclose(caches.read_captured_frames(obj, np.arange(1, T + 1)), captured, atol=1e-6)

    bcam = camera_from_blender(scene)
    for f in TRAIN:
        scene.frame_set(f)
        m_f = find_mouth(truth[f - 1], F, fixed, loop=syn.ICT_MOUTH_LOOP, units_per_mm=UPM)
        up, lo = syn.lip_contours(truth[f - 1], F, cam, fixed, mouth=m_f)
        bpy.context.view_layer.objects.active = obj
        bpy.ops.facelab.new_lip_sketch()
        write_stroke_pixels(scene.facelab.sketch, "Upper lip", f, [up], bcam)
        write_stroke_pixels(scene.facelab.sketch, "Lower lip", f, [lo], bcam)
        bpy.context.view_layer.objects.active = obj
        assert bpy.ops.facelab.refine_lips() == {"FINISHED"}
        assert md.deform_mode == "INTEGRATE"  # made ready so the corrective key shows over the cache
        X = caches.evaluate_frames(obj, [f], mute_shape_keys_prefix=())[0]
        d = np.r_[contour_distance(X, F, cam, up, +1, candidates=~fixed), contour_distance(X, F, cam, lo, -1, candidates=~fixed)]
        assert d.mean() < 1.0, d.mean()  # the key shows on the cached frame, on the strokes

    bpy.context.view_layer.objects.active = obj
    assert bpy.ops.facelab.auto_regions() == {"FINISHED"}
    if patch:  # an unsaved .blend without a cache folder is refused before the shot is corrected, scene untouched
        assert not bpy.data.filepath
        before = [(m.name, m.type, getattr(m, "deform_mode", None)) for m in obj.modifiers]
        with monkeypatch.context() as m, pytest.raises(RuntimeError, match="not saved"):
            m.setattr(prop, "CaptureReader", None)  # refused before a frame is read
            bpy.ops.facelab.propagate(suggestions=0)
        assert [(m.name, m.type, getattr(m, "deform_mode", None)) for m in obj.modifiers] == before
    scene.facelab_store.cache_directory = str(tmp_path)
    assert bpy.ops.facelab.propagate(suggestions=0) == {"FINISHED"}
    names = [(m.name, m.type) for m in obj.modifiers]
    if patch:
        from facelab_addon.blender.ownership import correction_cache
        from facelab_addon.core.capture.pointcache import cache_info

        assert names == [("Capture", "MESH_CACHE"), ("FL_Prop_Cache", "NODES")] and not [
            k for k in obj.data.shape_keys.key_blocks.keys() if k.startswith("FL_Prop_")]
        files = correction_cache(obj, "FL_Prop_")[1]
        info = cache_info(files[-1], "PC2")
        assert 0 < info.num_points <= vertex_group_mask(obj, "FL_lips").sum() < len(neutral) / 10  # only the lips
        assert caches.mesh_cache_direct_read_problem(obj) is None  # the capture is still read from its file
    else:
        assert names == [("Capture", "MESH_CACHE")]

    tris = mesh_triangles(obj.data)
    frames = np.arange(1, T + 1)
    cap = caches.read_captured_frames(obj, frames)
    corrected = caches.evaluate_frames(obj, TRAIN, mute_shape_keys_prefix=("FL_Prop_",))
    reg = LipRegressor(neutral, tris, faces_in_region(tris, vertex_group_mask(obj, "FL_mouth")),
                       faces_in_region(tris, vertex_group_mask(obj, "FL_lips")))
    reg.fit(training_input(cap[np.array(TRAIN) - 1], corrected, reg.interior_vertices))  # mouth from the capture
    if patch:
        assert info.num_points == len(reg.interior_vertices)
    held = [1, 6, 12, 16]
    expect = reg.predict(cap[np.array(held) - 1].astype(np.float64))
    got = caches.evaluate_frames(obj, held, mute_shape_keys_prefix=())
    assert np.abs(got - expect).max() < 2.5e-5, np.abs(got - expect).max()  # 0.01 mm key tolerance, carried by the cache

    # bake the corrected performance for other packages; never overwrite silently
    from facelab_addon.core.capture.pointcache import read_pc2

    out = tmp_path / "corrected.pc2"
    assert bpy.ops.facelab.bake(filepath=str(out), format="PC2") == {"FINISHED"}
    baked, start, rate = read_pc2(out)
    np.testing.assert_allclose(baked, caches.evaluate_frames(obj, frames, mute_shape_keys_prefix=()), atol=1e-6)
    with pytest.raises(RuntimeError, match="exists"):
        bpy.ops.facelab.bake(filepath=str(out), format="PC2")
    assert bpy.ops.facelab.bake(filepath=str(tmp_path / "corrected.abc"), format="ABC") == {"FINISHED"}
    assert (tmp_path / "corrected.abc").stat().st_size > 1000

    # the artist's loop on the cache: Refine a propagated frame, Propagate again; the frame keeps the refined shape
    # (Propagate's correction, keys or the point cache after the capture, is keyed off on the refined frame)
    f = 6
    scene.frame_set(f)
    m_f = find_mouth(truth[f - 1], F, fixed, loop=syn.ICT_MOUTH_LOOP, units_per_mm=UPM)
    up, lo = syn.lip_contours(truth[f - 1], F, cam, fixed, mouth=m_f)
    bpy.context.view_layer.objects.active = obj
    bpy.ops.facelab.new_lip_sketch()
    write_stroke_pixels(scene.facelab.sketch, "Upper lip", f, [up], bcam)
    write_stroke_pixels(scene.facelab.sketch, "Lower lip", f, [lo], bcam)
    bpy.context.view_layer.objects.active = obj
    assert bpy.ops.facelab.refine_lips() == {"FINISHED"}
    refined = caches.evaluate_frames(obj, [f], mute_shape_keys_prefix=())[0]
    X = refined @ np.array(obj.matrix_world)[:3, :3].T + np.array(obj.matrix_world)[:3, 3]
    d = np.r_[contour_distance(X, F, cam, up, +1, candidates=~fixed), contour_distance(X, F, cam, lo, -1, candidates=~fixed)]
    assert d.mean() < 1.0, d.mean()  # right after Refine the frame is on the strokes (nothing propagated on top)
    assert bpy.ops.facelab.propagate(suggestions=0) == {"FINISHED"}
    after = caches.evaluate_frames(obj, [f], mute_shape_keys_prefix=())[0]
    assert np.abs(after - refined).max() < 1e-5  # 0.01 mm
