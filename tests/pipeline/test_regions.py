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


@pytest.mark.slow
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


def body_object(ict, hands=1, units="m"):
    """The ICT head with fingers and eyelid folds (``testing.bodies``) as one object in a Z-up scene.

    ``units``: "m" (metres, unit scale 1), "cm" (data in centimetres, unit scale 0.01), or "mm-scaled"
    (data in metres, object scale 1000, unit scale 0.001).
    """
    import bpy

    from facelab_addon.testing.bodies import head_with_folds

    bpy.ops.wm.read_factory_settings(use_empty=True)
    V, F, folds = head_with_folds(ict, hands=hands)
    Vz = np.c_[V[:, 0], -V[:, 2], V[:, 1]]  # ICT (y up, z forward) -> Blender (z up, -y forward), centimetres
    scene = bpy.context.scene
    data = {"m": 0.01, "cm": 1.0, "mm-scaled": 0.01}[units]
    scene.unit_settings.scale_length = {"m": 1.0, "cm": 0.01, "mm-scaled": 0.001}[units]
    obj = new_mesh_object("Body", Vz * data, F)
    if units == "mm-scaled":
        obj.scale = (1000.0, 1000.0, 1000.0)
        bpy.context.view_layer.update()
    return scene, obj, folds


@pytest.mark.slow
def test_auto_regions_on_a_body_uses_the_camera_and_the_sketch(ict, addon):
    import bpy

    from facelab_addon.blender.camera import camera_from_blender, new_camera_object
    from facelab_addon.blender.strokes import new_lip_sketch, write_stroke_pixels
    from facelab_addon.core.capture.camera import Camera
    from facelab_addon.core.lips.lip_loop import inner_lip_loop

    scene, obj, folds = body_object(ict, hands=1)  # one hand: the mesh has no mirror plane to go by
    ref = inner_lip_loop(ict.neutral, ict.faces)
    n = len(ict.neutral)
    # without camera and sketch the lips cannot be told from the folds
    try:
        auto_regions(obj, RegionSettings(use_camera=False))
        assert not vertex_group_mask(obj, LIPS_GROUP)[ref].all()
    except RegionError as e:
        assert "Lip Contact Gap" in str(e) and "max_gap" not in str(e)
    # a camera 40 cm in front of the mouth and a sketch of the lips
    W = np.array([v.co[:] for v in obj.data.vertices])
    mouth_c = W[ref].mean(axis=0)
    cam = Camera.look_at(mouth_c + [0, -0.4, 0], mouth_c, [0, 0, 1], 50, 36, 1920, 1080)
    new_camera_object(scene, cam)
    gp = new_lip_sketch(scene, scene.camera)
    bc = camera_from_blender(scene)
    px = bc.project(W[ref])
    half = len(ref) // 2
    write_stroke_pixels(gp, "Upper lip", scene.frame_current, [px[:half]], bc)
    write_stroke_pixels(gp, "Lower lip", scene.frame_current, [px[half:]], bc)
    bpy.context.view_layer.update()
    r = auto_regions(obj, RegionSettings(replace=True))
    lips = vertex_group_mask(obj, LIPS_GROUP)
    mouth = vertex_group_mask(obj, MOUTH_GROUP)
    assert lips[ref].mean() > 0.9 and not (lips | mouth)[folds].any() and r.lip_vertices > 100
    _, l0 = core_regions.auto_regions(ict.neutral, ict.faces)  # the head alone
    assert (lips[:n] ^ l0).sum() < 0.1 * l0.sum()


@pytest.mark.parametrize("units", ["cm", "mm-scaled"])
@pytest.mark.slow
def test_the_contact_gap_is_in_millimetres_of_world_space(ict, addon, units):
    """A 6 mm contact gap finds the same regions in metres, in centimetres and on an object scaled 1000x."""
    _, obj, _ = body_object(ict, hands=2, units="m")
    auto_regions(obj, RegionSettings(contact_gap=6.0))
    want = vertex_group_mask(obj, LIPS_GROUP), vertex_group_mask(obj, MOUTH_GROUP)
    _, obj, _ = body_object(ict, hands=2, units=units)
    auto_regions(obj, RegionSettings(contact_gap=6.0))
    np.testing.assert_array_equal(vertex_group_mask(obj, LIPS_GROUP), want[0])
    assert (vertex_group_mask(obj, MOUTH_GROUP) != want[1]).sum() <= 2  # geodesic ties at the band edge
    # a gap too small for the lips (0.01 mm) is refused naming the setting to raise
    with pytest.raises(RegionError, match="Lip Contact Gap"):
        auto_regions(obj, RegionSettings(contact_gap=0.01, replace=True))
