"""The non-ICT test face: ICT decimated to quads with every expression transferred barycentrically. Its
topology is not ICT's, its poses are ICT's poses sampled at other points, Auto Regions finds its mouth
without help, its teeth are a separate part, and its route scene is the same face in every unit."""

import numpy as np
import pytest
from scipy.sparse.csgraph import connected_components

from facelab_addon.core.geometry.mesh import vertex_adjacency
from facelab_addon.core.lips import lip_loop, regions

pytestmark = [pytest.mark.blender, pytest.mark.slow]


@pytest.fixture(scope="module")
def face(ict, addon):
    from facelab_addon.testing.remeshed import remeshed_ict

    return remeshed_ict(ict)


def test_a_different_topology_with_the_truth_known(ict, face):
    V, F = face.neutral, face.faces
    assert 0.25 * len(ict.neutral) < len(V) < 0.6 * len(ict.neutral)
    sizes = np.diff(face.poly_offsets)
    assert (sizes == 4).mean() > 0.5 and set(np.unique(sizes)) <= {3, 4}
    # poses are ICT's poses at the new points: linear in the expression weights, and on ICT's surface
    w = {"jawOpen": 0.6, "mouthSmile_L": 0.4}
    np.testing.assert_allclose(face.pose(w), face.transfer(ict.pose(w)), atol=1e-9)
    assert np.allclose(face.barycentric.sum(1), 1) and (face.barycentric >= 0).all()
    # the new vertices are where Decimate put them, on the surface: within 0.5 mm of ICT's mesh
    from scipy.spatial import cKDTree

    d, _ = cKDTree(ict.neutral).query(V)
    assert np.median(d) > 0.02  # not ICT's vertices (cm)
    # the teeth are separate parts, and every part keeps its vertices
    n, lab = connected_components(vertex_adjacency(F, len(V)), directed=False)
    teeth = face.part_vertex_mask("M_Teeth")
    skin = face.part_vertex_mask("M_Face")
    assert teeth.any() and not np.intersect1d(lab[teeth], lab[skin]).size
    # an expression moves the lips as ICT's does: mean jawOpen displacement of the lips within 2 %
    loop_i = lip_loop.inner_lip_loop(ict.neutral, ict.faces)
    near = cKDTree(V).query(ict.neutral[loop_i])[1]
    dj = np.linalg.norm(face.expressions["jawOpen"] - face.neutral, axis=1)[near].mean()
    di = np.linalg.norm(ict.expressions["jawOpen"] - ict.neutral, axis=1)[loop_i].mean()
    assert abs(dj - di) < 0.05 * di


def test_auto_regions_finds_the_mouth_of_the_remeshed_face(ict, face):
    V, F = face.neutral, face.faces
    ref = lip_loop.inner_lip_loop(ict.neutral, ict.faces)
    loop = lip_loop.inner_lip_loop(V, F)
    d = np.linalg.norm(V[loop][:, None] - ict.neutral[ref][None], axis=2)
    assert d.min(axis=1).max() < 0.3  # every loop vertex within 3 mm of ICT's contact line
    W, Wi = lip_loop.loop_width(V, loop), lip_loop.loop_width(ict.neutral, ref)
    assert abs(W - Wi) < 0.05 * Wi  # corner to corner
    mouth, lips, d, _ = regions.auto_regions(V, F, return_distance=True)
    assert lips[loop].all() and not (mouth | lips)[face.part_vertex_mask("M_Teeth", "M_GumsTongue")].any()
    # without the edge-ring floor the lip band is the same physical band as on ICT (widths are relative to
    # the mouth)
    area = lambda X, Fa, m: 0.5 * np.linalg.norm(np.cross(X[Fa[:, 1]] - X[Fa[:, 0]], X[Fa[:, 2]] - X[Fa[:, 0]]),
                                                 axis=1)[regions.faces_in_region(Fa, m)].sum()  # noqa: E731
    _, li = regions.auto_regions(ict.neutral, ict.faces)
    _, lips0 = regions.auto_regions(V, F, min_rings=0)
    # (this face's band is whole 4 mm triangles: its area steps by 5-10 % when the band width changes by 1 %)
    assert 0.65 < area(V, F, lips0) / area(ict.neutral, ict.faces, li) < 1.3
    # this face's edges at the lips are about 4 mm: the band is 3 of them wide (0.12 mouth widths is 5 mm), so
    # Refine, which holds the band's border, has two rings inside it to move
    h = regions._loop_edge_length(V, F, loop)
    assert 3 * h > 2 * regions.DEFAULT_LIP_WIDTH * W
    assert 0.8 * 3 * h < d[lips].max() <= 3 * h * 1.001
    assert area(V, F, lips) > 1.5 * area(ict.neutral, ict.faces, li)


@pytest.mark.parametrize("units", ["cm", "mm", "mm-object"])
def test_the_route_scene_is_the_same_face_in_every_unit(face, units):
    from facelab_addon.testing.route import build_route_scene

    rs = build_route_scene(face, units="m", armature=True, pose=True, frames=np.arange(1, 5))
    want = rs.evaluated_truth([2]) * rs.mm_per_unit
    M = np.array(rs.obj.matrix_world)
    cam = np.array(rs.cameras[0].matrix_world)[:3, 3]
    want_cam = np.linalg.norm(want[0] - (np.linalg.inv(M) @ np.r_[cam, 1])[:3] * rs.mm_per_unit, axis=1)
    rs = build_route_scene(face, units=units, armature=True, pose=True, frames=np.arange(1, 5))
    got = rs.evaluated_truth([2]) * rs.mm_per_unit
    np.testing.assert_allclose(got, want, atol=2e-3)  # millimetres
    M = np.array(rs.obj.matrix_world)
    cam = np.array(rs.cameras[0].matrix_world)[:3, 3]
    got_cam = np.linalg.norm(got[0] - (np.linalg.inv(M) @ np.r_[cam, 1])[:3] * rs.mm_per_unit, axis=1)
    np.testing.assert_allclose(got_cam, want_cam, rtol=1e-5)  # the camera sees the same face
    # the armature moves the face: the posed truth is not the rest-pose truth
    assert np.abs(got[0] - rs.truth([2])[0] * rs.mm_per_unit).max() > 5.0
