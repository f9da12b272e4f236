"""Corrections measured on a rigged face are stored in rest space (``blender.rest_space``): with a head + jaw
Armature (both bones rotated 20°) in the modifier stack, a key written by ``to_rest_space`` shows exactly the
wanted displacement, and the evaluated mesh after Refine and after Propagate equals the solver's result within
0.01 mm; stacks that change the vertex count are refused with a message naming the modifier."""

import math

import bpy
import numpy as np
import pytest

from facelab_addon.blender import caches
from facelab_addon.blender.mesh import evaluated_vertices
from facelab_addon.blender.rest_space import deforming_modifiers, to_rest_space
from facelab_addon.core.errors import MeshError
from facelab_addon.names import PROPAGATE_PREFIX, REST_SPACE_KEY, SOLVE_PREFIX
from facelab_addon.pipeline.correctives import StorageSettings, write_corrective_keys

from .test_storage_policy import FRAMES, full_rank, head, low_rank, shown

pytestmark = pytest.mark.blender

TOL = 1e-5  # 0.01 mm, metres


def head_jaw_rig(obj, centre, *, angle=20.0, animate=()):
    """A head + jaw Armature deforming ``obj``: the jaw carries what lies below ``centre`` (the mouth).

    Both bones are rotated ``angle`` degrees (the head about its up axis and forward, the jaw open);
    ``animate`` frames get a keyed jaw angle that varies with the frame. Object-local units: metres.
    """
    co = np.array([v.co[:] for v in obj.data.vertices])
    c = np.asarray(centre, dtype=np.float64)
    size = float(np.ptp(co, axis=0).max())
    arm_data = bpy.data.armatures.new("Rig")
    arm = bpy.data.objects.new("Rig", arm_data)
    bpy.context.scene.collection.objects.link(arm)
    arm.matrix_world = obj.matrix_world.copy()
    bpy.context.view_layer.objects.active = arm
    bpy.ops.object.mode_set(mode="EDIT")
    hb = arm_data.edit_bones.new("head")
    hb.head, hb.tail = c + [0, -0.5 * size, -0.4 * size], c + [0, 0.3 * size, -0.4 * size]
    jb = arm_data.edit_bones.new("jaw")
    jb.head, jb.tail = c + [0, 0.0, -0.35 * size], c + [0, -0.2 * size, 0.0]
    jb.parent = hb
    bpy.ops.object.mode_set(mode="OBJECT")
    below = np.clip((c[1] + 0.01 * size - co[:, 1]) / (0.06 * size), 0, 1)
    jaw_w = below * np.clip((co[:, 2] - (c[2] - 0.45 * size)) / (0.1 * size), 0, 1)
    gh, gj = obj.vertex_groups.new(name="head"), obj.vertex_groups.new(name="jaw")
    for i, w in enumerate(jaw_w):
        gh.add([i], float(1 - w), "REPLACE")
        if w > 0:
            gj.add([i], float(w), "REPLACE")
    md = obj.modifiers.new("Armature", "ARMATURE")
    md.object = arm
    a = math.radians(angle)
    ph, pj = arm.pose.bones["head"], arm.pose.bones["jaw"]
    ph.rotation_mode = pj.rotation_mode = "XYZ"
    ph.rotation_euler = (0.3 * a, a, 0.2 * a)
    pj.rotation_euler = (a, 0, 0)
    for f in animate:
        pj.rotation_euler = (a * (0.5 + 0.5 * math.sin(0.3 * f)), 0, 0)
        pj.keyframe_insert("rotation_euler", frame=int(f))
    bpy.context.view_layer.objects.active = obj
    bpy.context.view_layer.update()
    return arm


def test_to_rest_space_inverts_a_posed_head_and_jaw(addon):
    scene, obj = head(animated=False)
    head_jaw_rig(obj, (0, 0, 0.1))
    assert [m.name for m in deforming_modifiers(obj)] == ["Armature"]
    n = len(obj.data.vertices)
    before = shown(obj, [1])[0]
    rest = np.array([v.co[:] for v in obj.data.vertices])
    rng = np.random.default_rng(0)
    vid = np.flatnonzero(rest[:, 1] < 0.02)  # the lower half, jaw and blend zone included
    D = rng.normal(0, 1e-3, (1, len(vid), 3))
    c = to_rest_space(obj, [1], D, vid)
    assert obj.data.shape_keys is None  # the temporary keys (and the Basis it needed) are gone
    # stored naively, the rig turns the correction by up to 40°; stored in rest space it shows as wanted
    full = np.zeros((n, 3))
    full[vid] = c[0]
    naive = np.zeros((n, 3))
    naive[vid] = D[0]
    from facelab_addon.blender.shapekeys import add_corrective_key

    kb = add_corrective_key(obj, "fix", full)
    kb.value = 1.0
    got = shown(obj, [1], muted=())[0] - before
    assert np.abs(got[vid] - D[0]).max() < 1e-7 and np.abs(np.delete(got, vid, axis=0)).max() < 1e-7
    kb.data.foreach_set("co", (rest + naive).astype(np.float32).ravel())
    obj.data.update()
    assert np.linalg.norm(shown(obj, [1], muted=())[0] - before - naive, axis=1).max() > 3e-4


@pytest.mark.parametrize("dense", [False, True])
def test_writer_maps_through_an_animated_rig_keys_and_cache(tmp_path, dense, addon):
    """Measured on the evaluated mesh of a rig whose jaw moves every frame: keys or a cache, the
    evaluated mesh shows the wanted displacement within 0.01 mm."""
    scene, obj = head(animated=True)
    head_jaw_rig(obj, (0, 0, 0.1), animate=FRAMES)
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "rig.blend"))
    frames = FRAMES[:12]
    before = shown(obj, frames)
    D = (full_rank(obj) if dense else low_rank(obj))[: len(frames)]
    res = write_corrective_keys(obj, SOLVE_PREFIX, D, frames, scene=scene, measured_on="evaluated",
                                settings=StorageSettings(key_budget=8)).storage
    assert res.mode == ("cache" if dense else "keys")
    if dense:
        assert [m.type for m in obj.modifiers] == ["MESH_CACHE", "ARMATURE"]  # the cache goes before the rig
    else:
        assert 3 <= len(res.keys) <= 8  # the rig's per-frame rotation raises the rank of the rest-space offsets
    err = np.linalg.norm(shown(obj, frames, muted=()) - before - D, axis=2)
    assert err.max() <= TOL, err.max()
    assert REST_SPACE_KEY not in "".join(obj.data.shape_keys.key_blocks.keys())


def test_topology_changing_stack_is_refused(addon):
    scene, obj = head(animated=False)
    obj.modifiers.new("Decimate", "DECIMATE").ratio = 0.5
    with pytest.raises(MeshError, match="change its vertex count.*'Decimate'"):
        to_rest_space(obj, [1], np.zeros((1, len(obj.data.vertices), 3)))
    assert obj.data.shape_keys is None


# --------------------------------------------------------------------------- Refine and Propagate on a rig
ICT_LIP_RING = np.arange(6632, 6706)  # the ICT-FaceKit inner-lip ring (shared/ict-facekit/README.md)


@pytest.mark.slow
def test_refine_on_a_rigged_face_shows_the_solver_result(tmp_path, ict, addon, monkeypatch):
    from facelab_addon.blender.camera import camera_from_blender
    from facelab_addon.blender.strokes import new_lip_sketch, write_stroke_pixels
    from facelab_addon.pipeline import refine as refine_mod

    from .test_refine_operator import FRAME, scene_setup

    s = scene_setup(tmp_path, ict)
    scene, obj = s["scene"], s["obj"]
    rig = head_jaw_rig(obj, s["C"][ICT_LIP_RING].mean(0), angle=20.0)
    # the camera moves with the head bone (a helmet camera), so the sketch still frames the mouth
    ph = rig.pose.bones["head"]
    scene.camera.matrix_world = rig.matrix_world @ ph.matrix @ ph.bone.matrix_local.inverted() @ \
        rig.matrix_world.inverted() @ scene.camera.matrix_world
    bpy.context.view_layer.update()
    gp = new_lip_sketch(scene, scene.camera)
    cam = camera_from_blender(scene)
    write_stroke_pixels(gp, "Upper lip", FRAME, [s["up_px"]], cam)
    write_stroke_pixels(gp, "Lower lip", FRAME, [s["lo_px"]], cam)
    solved = {}
    real = refine_mod.refine_lips_views

    def spy(V, *a, **k):
        X, info = real(V, *a, **k)
        solved["V"], solved["X"] = V.copy(), X.copy()
        return X, info

    monkeypatch.setattr(refine_mod, "refine_lips_views", spy)
    refine_mod.refine(scene, obj, FRAME, sketch=gp)
    got = evaluated_vertices(obj, bpy.context.evaluated_depsgraph_get())
    moved = np.linalg.norm(solved["X"] - solved["V"], axis=1).max()
    assert moved > 3e-4  # a real correction (m)
    e = np.linalg.norm(got - solved["X"], axis=1).max()
    print(f"Refine on a posed rig: correction up to {moved * 1e3:.3f} mm, evaluated vs solver {e * 1e3:.6f} mm")
    assert e < TOL


@pytest.mark.slow
def test_propagate_on_a_rigged_face_shows_the_regression(ict, addon):
    from ..pipeline.test_propagate import HELD, corrected_scene, independent_prediction
    from .test_propagate_operator import FRAMES as SHOT
    from .test_propagate_operator import TRAIN

    scene, obj, err, cap_w = corrected_scene(ict)
    rest = np.array([v.co[:] for v in obj.data.vertices])
    head_jaw_rig(obj, rest[ICT_LIP_RING].mean(0), angle=20.0)
    from facelab_addon.pipeline.propagate import PropagateSettings, propagate

    # the paper's maps, undamped: what independent_prediction computes
    propagate(scene, obj, SHOT, PropagateSettings(suggestions=0, ridge="none", damping=False))
    got = caches.evaluate_frames(obj, HELD, mute_shape_keys_prefix=())
    want = independent_prediction(obj, TRAIN, HELD, "whole")[0]  # sculpted in place: the whole-motion model
    captured = caches.evaluate_frames(obj, HELD, mute_shape_keys_prefix=(PROPAGATE_PREFIX,))
    assert np.abs(want - captured).max() > 1e-4  # the regression does correct these frames
    e = np.linalg.norm(got - want, axis=2).max()
    print(f"Propagate on a posed rig: correction up to {np.abs(want - captured).max() * 1e3:.3f} mm, "
          f"evaluated vs regression {e * 1e3:.6f} mm")
    assert e < TOL


def test_armature_jacobians_agree_with_the_measured_ones(addon):
    """The analytic path (bone matrices weighted by the vertex groups) equals the numeric one (unit
    offsets through the evaluated stack), with the rig and the mesh under different transforms."""
    scene, obj = head(animated=True)
    obj.location, obj.rotation_euler, obj.scale = (0.2, -0.1, 0.05), (0.3, 0.1, -0.2), (1.5, 1.5, 1.5)
    rig = head_jaw_rig(obj, (0, 0, 0.1), animate=FRAMES[:4])
    rig.location, rig.rotation_euler = (-0.3, 0.1, 0.0), (0.0, 0.2, 0.5)
    bpy.context.view_layer.update()
    rng = np.random.default_rng(1)
    D = rng.normal(0, 1e-3, (4, len(obj.data.vertices), 3))
    a = to_rest_space(obj, FRAMES[:4], D)
    b = to_rest_space(obj, FRAMES[:4], D, numeric=True)
    assert np.abs(a - b).max() < 1e-3 * np.abs(D).max()  # float32 finite differences
    assert np.abs(a - D).max() > 0.1 * np.abs(D).max()  # the rig does turn the offsets
    rig.data.bones["jaw"].bbone_segments = 4  # B-Bones bend space: the numeric path, with its Newton check
    c = to_rest_space(obj, FRAMES[:1], D[:1])
    assert np.isfinite(c).all()
