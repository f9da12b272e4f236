"""The Reconstruct from Bundles and Generate Correctives pipelines called directly (no operators, no scene
settings): the ICT face with expression keys as the dataset, empties on its surface following poses of the
dataset -> a keyed reconstruction through the bundles and equal to the poses; a lost bundle skips its frame;
a combination corrective equal to the core's, closer to the dataset's combination than the linear rig."""

import bpy
import numpy as np
import pytest

from facelab_addon.blender.caches import evaluate_frames
from facelab_addon.blender.mesh import mesh_triangles
from facelab_addon.blender.shapekeys import rest_vertices
from facelab_addon.core.errors import FaceLabError
from facelab_addon.names import RECONSTRUCT_PREFIX, RIG_CORRECTIVE_PREFIX
from facelab_addon.pipeline.reconstruct import (
    CorrectiveSettings,
    ReconstructSettings,
    generate_correctives,
    parse_combinations,
    reconstruct_from_bundles,
)
from facelab_addon.testing.scenes import keyed_empties

from ..blender.test_reconstruct_operator import EXPR, SCALE, _face, front_bundles

pytestmark = pytest.mark.blender


def _shot(ict, keys, weights):
    """The face with ``keys`` as its dataset, one animated empty per bundle following the poses ``weights``
    (frame t: ``{key: w}``) on frames 0..T-1; returns (scene, face, empties, truth (T,V,3), bundles (T,B,3))."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 0, len(weights) - 1
    obj = _face(ict, "Face", {n: ict.expressions[n] for n in keys})
    tris, pick, bary = front_bundles(ict, obj, 30)
    truth = np.stack([ict.pose(w) for w in weights]) * SCALE
    pts = np.einsum("bk,tbkd->tbd", bary, truth[:, tris[pick]])
    empties = keyed_empties(scene, pts)
    return scene, obj, empties, truth, pts


@pytest.mark.slow
def test_reconstruct_passes_through_the_bundles_and_recovers_the_poses(ict, addon):
    keys = EXPR[:6]
    poses = [{}, {keys[0]: 0.5}, {keys[1]: 0.7, keys[2]: 0.3}, {keys[3]: 1.0}]
    scene, obj, empties, truth, pts = _shot(ict, keys, poses)
    done = []
    r = reconstruct_from_bundles(scene, obj, ReconstructSettings(bind_frame=0, selected=empties),
                                 progress=lambda d, n: done.append(d))
    assert list(r.frames) == [0, 1, 2, 3] and r.skipped == [] and r.missing == "" and done[-1] == 4
    assert r.n_bundles == 30 and r.n_shapes == 6 and r.jaw is None and r.live_keys == []
    assert r.keys and [kb.name for kb in obj.data.shape_keys.key_blocks if kb.name.startswith(RECONSTRUCT_PREFIX)] \
        == r.keys
    got = evaluate_frames(obj, range(4), mute_shape_keys_prefix=())
    tris, pick, bary = front_bundles(ict, obj, 30)
    surf = np.einsum("bk,tbkd->tbd", bary, got[:, tris[pick]])
    print(f"through the bundles: {np.abs(surf - pts).max() * 1e3:.4f} mm")
    assert np.abs(surf - pts).max() < 2e-5
    front = ict.part_vertex_mask("M_Face") & (ict.neutral[:, 2] > 7)
    e = np.linalg.norm(got - truth, axis=2)[:, front]
    print(f"front-face error to the poses: mean {e.mean() * 1e3:.4f} mm, max {e.max() * 1e3:.4f} mm")
    assert e.mean() < 1e-4  # 0.1 mm


def test_lost_bundle_skips_its_frame_and_bad_input_writes_nothing(ict, addon):
    keys = EXPR[:6]
    scene, obj, empties, truth, pts = _shot(ict, keys, [{}, {keys[0]: 0.5}, {keys[1]: 0.7}])
    lost = empties[7]  # disabled in renders on frame 2: its track is lost there
    lost.hide_render = False
    lost.keyframe_insert("hide_render", frame=1)
    lost.hide_render = True
    lost.keyframe_insert("hide_render", frame=2)
    r = reconstruct_from_bundles(scene, obj, ReconstructSettings(selected=empties))
    assert r.skipped == [2] and r.missing == "missing: B07"
    got = evaluate_frames(obj, [0, 1, 2], mute_shape_keys_prefix=())
    np.testing.assert_allclose(got[2], ict.neutral * SCALE, atol=1e-6)  # shown neutral
    front = ict.part_vertex_mask("M_Face") & (ict.neutral[:, 2] > 7)
    assert np.abs(got[1] - got[0]).max() > 1e-3  # frame 1 is reconstructed
    assert np.linalg.norm(got[1] - truth[1], axis=1)[front].mean() < 1e-4
    # no bundles at all: refused, the previous reconstruction is untouched
    before = [kb.name for kb in obj.data.shape_keys.key_blocks]
    with pytest.raises(FaceLabError, match="No bundles"):
        reconstruct_from_bundles(scene, obj, ReconstructSettings(selected=()))
    with pytest.raises(FaceLabError, match="no vertex group 'jaw'"):
        reconstruct_from_bundles(scene, obj, ReconstructSettings(selected=empties, jaw_source="BONE"))
    assert [kb.name for kb in obj.data.shape_keys.key_blocks] == before


@pytest.mark.slow
def test_noise_setting_in_millimetres_and_estimated_from_jitter(ict, addon):
    keys = EXPR[:6]
    T = 24
    s = 0.5 + 0.4 * np.sin(np.linspace(0, np.pi, T - 1))
    poses = [{}] + [{keys[0]: float(a), keys[3]: float(1 - a)} for a in s]  # frame 0 neutral: the bind frame
    scene, obj, empties, truth, pts = _shot(ict, keys, poses)
    # replace the bundles' motion by the noisy one: 0.3 mm per axis in world space (the face is in metres)
    sigma_mm = 0.3
    noisy = pts + sigma_mm * 1e-3 * np.random.default_rng(2).standard_normal(pts.shape)
    noisy[0] = pts[0]  # bind frame: the neutral
    for e, track in zip(empties, noisy.transpose(1, 0, 2)):
        for t, p in enumerate(track):
            e.location = p
            e.keyframe_insert("location", frame=t)
    front = ict.part_vertex_mask("M_Face") & (ict.neutral[:, 2] > 7)
    err = {}
    for label, noise in (("estimated", -1.0), ("given", sigma_mm), ("exact", 0.0)):
        r = reconstruct_from_bundles(scene, obj, ReconstructSettings(bind_frame=0, selected=empties, noise=noise))
        assert r.method == "FIT_RESIDUAL"
        if label == "estimated":
            assert r.noise_mm == pytest.approx(sigma_mm, rel=0.25)
        else:
            assert r.noise_mm == pytest.approx(noise)
        got = evaluate_frames(obj, range(1, T), mute_shape_keys_prefix=())
        err[label] = np.linalg.norm(got - truth[1:], axis=2)[:, front].mean() * 1e3
    print("mean error mm:", err)
    assert err["given"] < 0.9 * err["exact"] and err["estimated"] < 0.9 * err["exact"]


@pytest.mark.slow
def test_generate_correctives_matches_the_core_and_beats_the_linear_rig(ict, addon):
    from facelab_addon.blender.objects import triangle_uvs
    from facelab_addon.blender.rig import dataset_shapes
    from facelab_addon.core.lgi.correctives import RigCorrectives

    bpy.ops.wm.read_factory_settings(use_empty=True)
    rig_names = ["mouthSmile_L", "mouthSmile_R", "cheekSquint_L", "cheekSquint_R", "mouthFunnel", "mouthPucker"]
    d = {n: ict.expressions[n] - ict.neutral for n in rig_names}
    # the actor's dataset: the rig's shapes, and a smile whose combination with the squint bulges the cheek more
    combo = ("mouthSmile_L", "cheekSquint_L")
    extra = 0.5 * d["cheekSquint_L"]
    data = {n: ict.expressions[n] for n in rig_names}
    data["smile+squint"] = ict.neutral + d[combo[0]] + d[combo[1]] + extra
    face = _face(ict, "Face", data)
    rig = _face(ict, "Rig", {n: ict.expressions[n] for n in rig_names})
    scene = bpy.context.scene
    assert parse_combinations(" mouthSmile_L+cheekSquint_L ;a + b\nc") == [combo, ("a", "b"), ("c",)]
    with pytest.raises(FaceLabError, match="no shape keys \\['nope'\\]"):
        generate_correctives(scene, face, CorrectiveSettings(rig_object=rig, combinations="nope+mouthSmile_L"))
    with pytest.raises(FaceLabError, match="Pick the template rig"):
        generate_correctives(scene, face, CorrectiveSettings(rig_object=face, combinations="+".join(combo)))
    assert [kb.name for kb in rig.data.shape_keys.key_blocks][1:] == rig_names  # nothing written
    r = generate_correctives(scene, face, CorrectiveSettings(rig_object=rig, combinations="+".join(combo),
                                                             n_bundles=60))
    name = RIG_CORRECTIVE_PREFIX + "+".join(combo)
    assert r.rig == "Rig" and [a[0] for a in r.added] == [name] and r.n_dataset == 7 and r.n_bundles == 60
    kb = rig.data.shape_keys.key_blocks[name]
    fcs = {fc.data_path: fc for fc in rig.data.shape_keys.animation_data.drivers}
    assert fcs[f'key_blocks["{name}"].value'].driver.expression == "w0 * w1"
    # the key is the core's corrective for the same inputs
    n0 = rest_vertices(face)
    names, shapes = dataset_shapes(face)
    rig_sh = {n: n0 + (s - rest_vertices(rig)) for n, s in zip(*dataset_shapes(rig))
              if not n.startswith(RIG_CORRECTIVE_PREFIX)}
    rc = RigCorrectives(n0, mesh_triangles(face.data), rig_sh, shapes, dataset_names=names, n_bundles=60,
                        uvs=triangle_uvs(face.data))
    try:
        c, _ = rc.corrective(combo)
        lin = rc.linear(combo)
    finally:
        rc.close()
    co = np.empty(len(n0) * 3)
    kb.data.foreach_get("co", co)
    np.testing.assert_allclose(co.reshape(-1, 3) - n0, c, atol=1e-6)
    # and the rig plus the corrective is closer to the dataset's combination than the linear rig alone
    truth = data["smile+squint"] * SCALE
    skin = ict.part_vertex_mask("M_Face")
    e_lin = np.linalg.norm(lin - truth, axis=1)[skin].mean()
    e_cor = np.linalg.norm(lin + c - truth, axis=1)[skin].mean()
    print(f"{name}: linear {e_lin * 1e3:.3f} mm, with corrective {e_cor * 1e3:.3f} mm")
    assert e_cor < 0.1 * e_lin  # measured 0.278 -> 0.006 mm
