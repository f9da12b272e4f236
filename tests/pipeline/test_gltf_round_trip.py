"""A real glTF round trip: the route face (ICT, with its UVs, smooth shaded) exported with its shape keys and read back
with Blender's glTF importer at its default settings (Merge Vertices off: the vertices split along the UV seams,
26,719 -> 28,716), then Auto Regions and Refine Lips on it give the exported face's result at every vertex (to 1e-6
of the mouth width) and keep every seam closed. The glTF add-on (``io_scene_gltf2``) ships with the bpy wheels of
4.5, 5.0 and 5.3."""

import os

import numpy as np
import pytest

from facelab_addon.blender import caches
from facelab_addon.names import FIXED_GROUP, LIPS_GROUP, MOUTH_GROUP

pytestmark = pytest.mark.blender

FRAME = 30


def test_auto_regions_and_refine_on_a_gltf_import_match_the_exported_face(ict, addon, tmp_path):
    import bpy
    from scipy.spatial import cKDTree

    from facelab_addon.blender.mesh import vertex_group_mask
    from facelab_addon.core.lips.lip_loop import loop_width
    from facelab_addon.pipeline.refine import refine
    from facelab_addon.pipeline.regions import auto_regions
    from facelab_addon.testing.route import build_route_scene, sketch_truth

    rs = build_route_scene(ict, units="m", frames=np.arange(FRAME - 1, FRAME + 2))
    scene, obj = rs.scene, rs.obj
    me = obj.data
    uv = me.uv_layers.new(name="UVMap")
    uv.data.foreach_set("uv", np.asarray(ict.uvs)[np.asarray(ict.poly_uv)].astype(np.float32).ravel())
    me.polygons.foreach_set("use_smooth", np.ones(len(me.polygons), bool))
    obj.vertex_groups.remove(obj.vertex_groups[FIXED_GROUP])  # glTF keeps no vertex groups: both use the pieces
    path = os.path.join(str(tmp_path), "face.glb")
    bpy.ops.object.select_all(action="DESELECT")
    obj.select_set(True)
    bpy.context.view_layer.objects.active = obj
    assert bpy.ops.export_scene.gltf(filepath=path, use_selection=True, export_morph=True,
                                     export_animations=True) == {"FINISHED"}

    def run(o):
        auto_regions(o, scene=scene)
        r = refine(scene, o, FRAME, sketch=gp)
        X = caches.evaluate_frames(o, [FRAME], mute_shape_keys_prefix=()).astype(np.float64)[0]
        return vertex_group_mask(o, MOUTH_GROUP), vertex_group_mask(o, LIPS_GROUP), r, X

    gp, _, _ = sketch_truth(rs, FRAME, rs.cameras[0])
    captured = caches.evaluate_frames(obj, [FRAME]).astype(np.float64)[0]
    mouth, lips, r0, X0 = run(obj)
    rest0 = rs.neutral
    bpy.data.objects.remove(obj)

    before = set(bpy.data.objects)
    assert bpy.ops.import_scene.gltf(filepath=path) == {"FINISHED"}  # Blender's defaults: Merge Vertices off
    (imp,) = [o for o in bpy.data.objects if o not in before and o.type == "MESH"]
    n = len(imp.data.vertices)
    assert n > len(rest0) + 1000  # split along the UV seams
    rest1 = np.empty(3 * n)
    imp.data.vertices.foreach_get("co", rest1)
    dist, src = cKDTree(rest0).query(rest1.reshape(n, 3))
    assert dist.max() < 1e-6  # every imported vertex is one of the face's (float32 positions, object-local metres)
    assert len(np.unique(src)) < n
    X1_captured = caches.evaluate_frames(imp, [FRAME]).astype(np.float64)[0]
    width = loop_width(rest0, rs.loop)
    np.testing.assert_allclose(X1_captured, captured[src], rtol=0, atol=1e-6 * width)

    mouth1, lips1, r1, X1 = run(imp)
    assert lips.sum() > 100
    np.testing.assert_array_equal(mouth1, mouth[src])
    np.testing.assert_array_equal(lips1, lips[src])
    assert r1.fixed_source == r0.fixed_source == "separate mesh parts"
    moved = np.linalg.norm(X0 - captured, axis=1)
    assert moved.max() > 1e-4  # Refine moved the lips
    err = np.abs(X1 - X0[src]).max()
    assert err < 1e-6 * width, (err, width)
    # every seam closed: the copies of one vertex coincide after Refine
    order = np.argsort(src, kind="stable")
    same = src[order][1:] == src[order][:-1]
    gap = np.linalg.norm(X1[order][1:][same] - X1[order][:-1][same], axis=1)
    assert same.sum() > 1000 and gap.max() < 1e-6 * width
    assert (moved[src[order][1:][same]] > 1e-6).sum() > 10  # some moved vertices are split
