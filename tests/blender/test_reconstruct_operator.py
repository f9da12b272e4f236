"""Headless end to end: animated empties as bundles + the face's shape keys as the dataset ->
Reconstruct from Bundles -> keyed result equal to the core's and through the bundles."""

import numpy as np
import pytest

import bpy

import facelab_addon
from facelab_addon.blender.caches import evaluate_frames
from facelab_addon.blender.mesh import mesh_triangles
from facelab_addon.blender.scene import new_mesh_object
from facelab_addon.blender.shapekeys import add_corrective_key
from facelab_addon.core.geometric_indexing import GeometricIndexer, bind_points

pytestmark = pytest.mark.blender

SCALE = 0.01
EXPR = ["jawOpen", "mouthSmile_L", "mouthSmile_R", "mouthFunnel", "browInnerUp_L", "browInnerUp_R",
        "eyeBlink_L", "eyeBlink_R", "mouthPucker", "cheekPuff_L"]


@pytest.fixture(scope="module")
def addon():
    facelab_addon.register()
    yield
    facelab_addon.unregister()


def truth_all(truth, neutral):
    return np.concatenate([neutral[None], truth])


def test_reconstruct_from_bundles_end_to_end(ict, addon):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    T = 6
    scene.frame_start, scene.frame_end = 1, T
    neutral = ict.neutral * SCALE
    obj = new_mesh_object("Face", neutral, poly_verts=ict.poly_verts, poly_offsets=ict.poly_offsets)
    obj.shape_key_add(name="Basis", from_mix=False)
    for n in EXPR:
        add_corrective_key(obj, n, (ict.expressions[n] - ict.neutral) * SCALE)
    tris = mesh_triangles(obj.data)
    # 40 bundles on the front of the face, bound at the neutral
    rng = np.random.default_rng(0)
    face_tris = np.flatnonzero(ict.part_face_mask("M_Face")[: len(tris)] & (neutral[tris].mean(1)[:, 2] > 0.07))
    pick = rng.choice(face_tris, 40, replace=False)
    bary = rng.dirichlet([4, 4, 4], 40)
    # truth: each frame is one dataset shape blended with another (the bundles follow it)
    W = np.zeros((T, len(EXPR)))
    for t in range(T):
        W[t, t % len(EXPR)] = 0.6
        W[t, (t + 3) % len(EXPR)] = 0.4
    shapes = np.stack([(ict.expressions[n] - ict.neutral) * SCALE for n in EXPR])
    truth = neutral[None] + np.einsum("ts,svd->tvd", W, shapes)
    pts = np.einsum("bk,tbkd->tbd", bary, truth[:, tris[pick]])
    pts = np.concatenate([np.einsum("bk,bkd->bd", bary, neutral[tris[pick]])[None], pts])  # frame 0: neutral
    scene.frame_start = 0
    empties = []
    for b in range(40):
        e = bpy.data.objects.new(f"B{b:02d}", None)
        scene.collection.objects.link(e)
        for t in range(T + 1):
            e.location = pts[t, b]
            e.keyframe_insert("location", frame=t)
        e.select_set(True)
        empties.append(e)
    bpy.context.view_layer.objects.active = obj
    scene.facelab.face = obj

    assert bpy.ops.facelab.reconstruct_from_bundles(bind_frame=0) == {"FINISHED"}
    keys = [kb.name for kb in obj.data.shape_keys.key_blocks if kb.name.startswith("FL_Recon_")]
    assert keys
    frames = np.arange(0, T + 1)
    for kb in obj.data.shape_keys.key_blocks:  # the dataset keys themselves stay at 0
        assert kb.name.startswith("FL_") or kb.value == 0 or kb.name == "Basis"
    got = evaluate_frames(obj, frames, mute_shape_keys_prefix=())

    # the core, called directly, gives the same (within the 0.01 mm key compression tolerance)
    # (from the same Blender data: float32 keys and empties, as the operator reads them)
    from facelab_addon.blender.bundles import read_bundles
    from facelab_addon.blender.shapekeys import rest_vertices
    from facelab_addon.ui.ops_reconstruct import dataset_shapes

    n0 = rest_vertices(obj)
    names, data = dataset_shapes(obj)
    assert names == EXPR
    q = read_bundles(scene, empties, frames)
    np.testing.assert_allclose(q, pts, atol=1e-6)
    bf, bb, _ = bind_points(n0, tris, q[0])
    idx = GeometricIndexer(n0, tris, data, bf, bb, names=names)
    expect, skipped = idx.reconstruct_sequence(q)
    assert skipped == []
    assert np.abs(got - expect).max() < 1.2e-5, np.abs(got - expect).max()
    # and it passes through the bundles
    surf = np.einsum("bk,tbkd->tbd", bb, got[:, tris[bf]])
    assert np.abs(surf - q).max() < 1.5e-5
    # and it recovers the truth (every frame is a blend of two dataset shapes)
    front = ict.part_vertex_mask("M_Face") & (neutral[:, 2] > 0.07)
    e = np.linalg.norm(got - truth_all(truth, neutral), axis=2)[:, front]
    print("front-face error mm: mean %.4f max %.4f" % (e.mean() * 1e3, e.max() * 1e3))
    assert e.mean() < 1e-4  # 0.1 mm
