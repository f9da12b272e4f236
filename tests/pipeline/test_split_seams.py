"""The Dinev route on a face split along its UV seams (a glTF import: 26,719 -> 28,911 ICT vertices, M_Face in 9
pieces; the remeshed face, which has no UVs: islands of its mouth area cut out, 11,150 -> 12,049) gives the welded
face's result at every vertex, and every seam stays closed.

Both runs use one truth: the route scene of the face and of ``testing.split_seams.split_seams(face)`` (the same
expressions, cameras, armature), the split scene's capture error set to the welded one's (the route's error model
measures along the mesh, which a seam would cut), the same sketch pixels. Auto Regions, Refine Lips (frame 30) and
Propagate (frames 21-40) must agree at every split vertex with the welded vertex it copies, to 1e-6 of the mouth
width, and twins must coincide on the evaluated mesh after each step."""

import numpy as np
import pytest

pytestmark = pytest.mark.blender

FRAME = 30
FRAMES = np.arange(21, 41)


@pytest.fixture(scope="module", params=["ict", "remeshed"])
def runs(request, ict, addon):
    from facelab_addon.testing.remeshed import remeshed_ict
    from facelab_addon.testing.split_seams import run_route, split_seams

    face = ict if request.param == "ict" else remeshed_ict(ict)
    welded = run_route(face, frames=FRAMES, train=[FRAME])
    split = split_seams(face)
    cut = run_route(split, frames=FRAMES, train=[FRAME], error=welded["error"][split.source],
                    strokes=welded["strokes"])
    for r in (welded, cut):  # the refined and the captured frame
        r["refined"], r["captured"] = r["refined"][0], r["captured"][list(FRAMES).index(FRAME)]
        r["refine"] = r["refine"][0]
    return welded, split, cut


def test_the_split_face_falls_into_pieces(ict):
    from facelab_addon.core.lips.sketch_prior import separate_parts
    from facelab_addon.testing.split_seams import split_seams

    split = split_seams(ict)
    assert (len(ict.neutral), len(split.neutral)) == (26719, 28911)
    face = split.part_vertex_mask("M_Face")
    # without welding, separate_parts (the default fixed set) would hold most of the face still
    assert separate_parts(split.faces, len(split.neutral))[face].sum() > 1000


@pytest.mark.slow
def test_auto_regions_on_the_split_face_are_the_welded_regions(runs):
    welded, split, cut = runs
    assert welded["lips"].sum() > 100 and welded["mouth"].sum() > 100
    np.testing.assert_array_equal(cut["lips"], welded["lips"][split.source])
    np.testing.assert_array_equal(cut["mouth"], welded["mouth"][split.source])
    d = split.duplicates()
    assert cut["lips"][d[:, 1]].sum() > 0  # the lip band crosses seams


def test_refine_on_the_split_face_is_the_welded_refine_and_the_seams_stay_closed(runs):
    welded, split, cut = runs
    tol = 1e-6 * welded["width"]
    np.testing.assert_allclose(cut["captured"], welded["captured"][split.source], rtol=0, atol=tol)
    moved = np.linalg.norm(welded["refined"] - welded["captured"], axis=1)
    assert moved.max() > 1e-4  # m: Refine moved the lips (0.1 mm+)
    assert cut["refine"].moved_vertices >= welded["refine"].moved_vertices
    err = np.abs(cut["refined"] - welded["refined"][split.source]).max()
    assert err < tol, (err, tol)
    d = split.duplicates()
    moved_twins = moved[split.source[d[:, 0]]] > 1e-6
    assert moved_twins.sum() > 10  # the correction crosses seams
    gap = np.linalg.norm(cut["refined"][d[:, 0]] - cut["refined"][d[:, 1]], axis=1).max()
    assert gap < tol, gap


def test_propagate_on_the_split_face_is_the_welded_propagate_and_the_seams_stay_closed(runs):
    welded, split, cut = runs
    tol = 1e-6 * welded["width"]
    change = np.linalg.norm(welded["propagated"] - welded["captured"][None], axis=2).max()
    assert change > 1e-4
    err = np.abs(cut["propagated"] - welded["propagated"][:, split.source]).max()
    assert err < tol, (err, tol)
    d = split.duplicates()
    gap = np.linalg.norm(cut["propagated"][:, d[:, 0]] - cut["propagated"][:, d[:, 1]], axis=2).max()
    assert gap < tol, gap


def test_a_lip_cut_opened_by_a_shape_key_or_a_read_frame_is_not_welded(addon):
    """A mouth modelled closed, its upper and lower lip vertices coincident at rest (a cut): ``face_topology`` welds
    them only while no shape key and no frame the step reads opens the mouth."""
    import bpy

    from facelab_addon.blender.mesh import face_topology, mesh_triangles

    n = 6
    x = np.arange(n, dtype=float)
    V = np.vstack([np.c_[x, np.zeros(n), np.full(n, z)] for z in (1.0, 0.0, 0.0, -1.0)])  # rows 1, 2 coincide
    F = []
    for top in (0, 2):
        for i in range(n - 1):
            a, b, c, d = top * n + i, top * n + i + 1, (top + 1) * n + i, (top + 1) * n + i + 1
            F.append([a, c, d, b])
    me = bpy.data.meshes.new("Cut")
    me.from_pydata(V.tolist(), [], F)
    obj = bpy.data.objects.new("Cut", me)
    bpy.context.scene.collection.objects.link(obj)
    assert face_topology(obj).n_duplicates == n  # nothing tells the lips apart: welded
    opened = V.copy()
    opened[2 * n:, 2] -= 0.5
    assert face_topology(obj, [opened]).n_duplicates == 0  # a frame read opens the mouth (Refine's, Propagate's)
    obj.shape_key_add(name="Basis")
    kb = obj.shape_key_add(name="jawOpen")
    kb.data.foreach_set("co", opened.astype(np.float32).ravel())
    topo = face_topology(obj)
    assert topo.n_duplicates == 0
    np.testing.assert_array_equal(topo.tris, mesh_triangles(me))  # the mesh's own triangles


def test_the_bhat_solve_skin_on_the_split_face_is_the_welded_skin(ict, addon):
    """The Bhat solve's markers and contours go on the skin: triangles without a fixed vertex. Without an
    ``FL_fixed`` group the fixed vertices are the separate parts, those of the welded surface: on the UV-split
    face (M_Face in 9 pieces) the skin is the welded face's, not its largest UV island."""
    from facelab_addon.blender.mesh import mesh_triangles
    from facelab_addon.pipeline.solve import _skin_triangles
    from facelab_addon.testing.scenes import build_ict_face_scene
    from facelab_addon.testing.split_seams import split_seams

    names = ["jawOpen", "mouthClose"]
    fs = build_ict_face_scene(ict, names)
    skin, fixed, src = _skin_triangles(fs.obj, mesh_triangles(fs.obj.data), "FL_fixed")
    assert src == "separate mesh parts" and skin.sum() > 10000
    split = split_seams(ict)
    fs = build_ict_face_scene(split, names)
    skin_s, fixed_s, _ = _skin_triangles(fs.obj, mesh_triangles(fs.obj.data), "FL_fixed")
    np.testing.assert_array_equal(skin_s, skin)  # the same polygons, so the same triangles in the same order
    np.testing.assert_array_equal(fixed_s, fixed[split.source])
