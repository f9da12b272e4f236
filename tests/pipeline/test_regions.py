"""The Auto Regions pipeline without operators, on the ICT face: the vertex groups it writes are the
core's regions exactly, it refuses to overwrite unless asked, reads them back validated, and takes
the inner-lip loop from a selection."""

import numpy as np
import pytest

from facelab_addon.blender.mesh import mesh_triangles, vertex_group_mask
from facelab_addon.blender.scene import new_mesh_object
from facelab_addon.core.errors import RegionError
from facelab_addon.core.lips import regions as core_regions
from facelab_addon.names import LIPS_GROUP, MOUTH_GROUP
from facelab_addon.pipeline.regions import RegionSettings, auto_regions, region_faces

pytestmark = pytest.mark.blender

SCALE = 0.01


def face(ict):
    import bpy

    bpy.ops.wm.read_factory_settings(use_empty=True)
    return new_mesh_object("Face", ict.neutral * SCALE, poly_verts=ict.poly_verts, poly_offsets=ict.poly_offsets)


def test_auto_regions_writes_the_core_regions(ict, addon):
    obj = face(ict)
    tris = mesh_triangles(obj.data)
    with pytest.raises(RegionError, match=f"no vertex group {MOUTH_GROUP} or {LIPS_GROUP}"):
        region_faces(obj, tris)

    r = auto_regions(obj)
    mouth, lips = core_regions.auto_regions(ict.neutral * SCALE, tris)
    np.testing.assert_array_equal(vertex_group_mask(obj, MOUTH_GROUP), mouth)
    np.testing.assert_array_equal(vertex_group_mask(obj, LIPS_GROUP), lips)
    assert (r.mouth_vertices, r.lip_vertices) == (mouth.sum(), lips.sum()) and r.replaced == []
    assert r.mouth_vertices > 100 and r.lip_vertices > 100
    mf, lf = region_faces(obj, tris)
    np.testing.assert_array_equal(mf, core_regions.faces_in_region(tris, mouth))
    np.testing.assert_array_equal(lf, core_regions.faces_in_region(tris, lips))
    assert not np.intersect1d(mf, lf).size  # the two regions share only a border

    # existing groups: refused and left alone, unless replace is asked for
    vg = obj.vertex_groups[LIPS_GROUP]
    vg.remove(np.flatnonzero(lips)[:50].tolist())
    with pytest.raises(RegionError, match="already exist"):
        auto_regions(obj)
    assert vertex_group_mask(obj, LIPS_GROUP).sum() == lips.sum() - 50
    r = auto_regions(obj, RegionSettings(replace=True))
    np.testing.assert_array_equal(vertex_group_mask(obj, LIPS_GROUP), lips)
    assert sorted(r.replaced) == sorted([MOUTH_GROUP, LIPS_GROUP])
    assert [g.name for g in obj.vertex_groups].count(LIPS_GROUP) == 1

    # overlapping regions are refused by region_faces
    obj.vertex_groups[LIPS_GROUP].add(np.flatnonzero(mouth).tolist(), 1.0, "REPLACE")
    with pytest.raises(RegionError, match="(?i)overlap"):
        region_faces(obj, tris)


def test_auto_regions_from_a_selected_loop(ict, addon):
    from facelab_addon.testing import synthetic as syn

    obj = face(ict)
    tris = mesh_triangles(obj.data)
    sel = np.zeros(len(obj.data.vertices), bool)
    sel[:3] = True
    obj.data.vertices.foreach_set("select", sel)
    with pytest.raises(RegionError, match="at least 4 vertices"):
        auto_regions(obj, RegionSettings(use_selection=True))
    assert obj.vertex_groups.get(MOUTH_GROUP) is None
    loop = np.asarray(syn.ICT_MOUTH_LOOP)
    sel[:] = False
    sel[loop] = True
    obj.data.vertices.foreach_set("select", sel)
    auto_regions(obj, RegionSettings(use_selection=True))
    mouth, lips = core_regions.auto_regions(ict.neutral * SCALE, tris, loop=np.flatnonzero(sel))
    np.testing.assert_array_equal(vertex_group_mask(obj, MOUTH_GROUP), mouth)
    np.testing.assert_array_equal(vertex_group_mask(obj, LIPS_GROUP), lips)
