"""The route scenes of ``benchmarks/route_sweep.py``: ``testing.route.build_route_scene``'s camera options and
its OBJ import (Blender's importer with its default axes) put the same face, truth and error where the
benchmark says; and the lip contact of other actors on the coarse face (the sweep's finding, fixed by the slit-end
search)."""

import numpy as np
import pytest

from facelab_addon.core.lips import lip_loop

pytestmark = [pytest.mark.blender, pytest.mark.slow]


@pytest.fixture(scope="module")
def face(ict, addon):
    from facelab_addon.testing.remeshed import remeshed_ict

    return remeshed_ict(ict)


def _world(rs, X):
    M = np.array(rs.obj.matrix_world)
    return X @ M[:3, :3].T + M[:3, 3]


@pytest.mark.parametrize("scale", [1.0, 0.01])
def test_an_imported_obj_is_the_same_face(face, scale):
    from facelab_addon.blender.camera import camera_from_blender
    from facelab_addon.testing.route import build_route_scene

    frames = np.arange(1, 5)
    ref = build_route_scene(face, units="m", armature=True, pose=True, frames=frames)
    want = _world(ref, ref.evaluated_truth([2])[0])  # metres, Z up
    want_err = _world(ref, ref.neutral + ref.error) - _world(ref, ref.neutral)
    want_px = [camera_from_blender(ref.scene, c).project(want) for c in ref.cameras]
    inner = ref.inner_lips.copy()
    rs = build_route_scene(face, units="m", armature=True, pose=True, frames=frames, obj_import=True,
                           import_scale=scale)
    # as Blender's OBJ importer leaves it: the data keeps the file's Y-up centimetre numbers, the object is
    # turned 90 degrees about X (and scaled by the importer's scale)
    np.testing.assert_allclose(rs.neutral, face.neutral, atol=1e-5)
    np.testing.assert_allclose(np.array(rs.obj.rotation_euler), [np.pi / 2, 0, 0], atol=1e-6)
    np.testing.assert_allclose(np.array(rs.obj.scale), [scale] * 3, rtol=1e-6)
    # a centimetre file read as metres is the same face 100 times bigger (x0.01: the same size), posed by its
    # armature as the reference is, with the same capture error
    k = 100.0 * scale
    got = _world(rs, rs.evaluated_truth([2])[0])
    np.testing.assert_allclose(got, k * want, atol=2e-6 * k)  # 2 micrometres of the face
    got_err = _world(rs, rs.neutral + rs.error) - _world(rs, rs.neutral)
    np.testing.assert_allclose(got_err, k * want_err, atol=1e-7 * k)
    np.testing.assert_array_equal(rs.inner_lips, inner)
    # millimetres per local unit: world millimetres (1 m per unit, times the object's scale)
    assert rs.mm_per_unit == pytest.approx(1000.0 * scale, rel=1e-6)
    # the cameras see the same face: the same pixels
    for pa, c in zip(want_px, rs.cameras):
        np.testing.assert_allclose(camera_from_blender(rs.scene, c).project(got), pa, atol=1e-3)


def test_the_camera_options(face):
    from facelab_addon.blender.camera import camera_from_blender
    from facelab_addon.testing.route import build_route_scene

    ref = build_route_scene(face, units="m", frames=np.arange(1, 3))
    mc = _world(ref, ref.neutral[ref.loop].mean(axis=0))
    f0 = camera_from_blender(ref.scene, ref.cameras[0]).K[0, 0]
    rs = build_route_scene(face, units="m", frames=np.arange(1, 3), lens_mm=85.0, camera_cm=25.0, camera_yaw=15.0,
                           camera_roll=10.0)
    c = camera_from_blender(rs.scene, rs.cameras[0])
    assert c.K[0, 0] == pytest.approx(f0 * 85.0 / 50.0, rel=1e-6)
    d = c.center - mc
    assert np.linalg.norm(d) == pytest.approx(0.25, rel=1e-6)  # 25 cm from the mouth, metres
    # 15 degrees toward the face's left (+x), at mouth height
    assert np.degrees(np.arctan2(d[0], -d[1])) == pytest.approx(15.0, abs=1e-4) and abs(d[2]) < 1e-6
    np.testing.assert_allclose(c.project(mc[None])[0], [960.0, 540.0], atol=0.01)  # still looks at the mouth
    # rolled 10 degrees about its viewing axis: the world's up is 10 degrees off the image's up
    up_img = c.project((mc + [0, 0, 0.01])[None])[0] - c.project(mc[None])[0]
    assert np.degrees(np.arctan2(abs(up_img[0]), -up_img[1])) == pytest.approx(10.0, abs=0.05)


@pytest.mark.parametrize("seed", range(8))
def test_the_lip_contact_of_another_actor_on_the_coarse_face(ict, face, seed):
    """Other actors (route_sweep's "identity s<seed>": ICT's neutral plus N(0, 1) identity offsets) on the coarse
    remeshed face (about 4 mm edges at the lips): the automatic loop runs corner to corner as on full-resolution
    ICT. Before the slit-end search 4 of these 8 loops kept only the middle of the mouth (2.3, 2.9, 2.9 and
    0.8 cm wide instead of about 4.3), as the contact pairs stop 1-2 edges short of the corners there."""
    from facelab_addon.core.lips.regions import _loop_edge_length

    w = np.random.default_rng(seed).normal(size=len(ict.identities))
    off = ict.pose(identity=dict(zip(ict.identities, w))) - ict.neutral
    Vd = ict.neutral + off
    V = face.neutral + face.transfer(off)  # the same actor sampled at the coarse face's vertices
    ref = lip_loop.inner_lip_loop(Vd, ict.faces)
    W = lip_loop.loop_width(Vd, ref)
    for toward in (V.mean(axis=0) + [0.0, 0.0, 60.0], None):  # a camera in front; the skin's front
        loop = lip_loop.inner_lip_loop(V, face.faces, toward=toward)
        assert abs(lip_loop.loop_width(V, loop) - W) < 0.1 * W
        # the corners (the ends of the loop's principal axis) are where full-resolution ICT has them: within
        # 1.5 of the coarse loop's edges (both faces share ICT's space: the coarse face samples its surface)
        h = _loop_edge_length(V, face.faces, loop)
        for a, b in zip(_corners(Vd[ref]), _corners(V[loop])):
            assert np.linalg.norm(a - b) < 1.5 * h


def _corners(P):
    """(2,3) the points of ``P`` at either end of its principal axis, ordered along x."""
    c = P.mean(axis=0)
    s = (P - c) @ np.linalg.svd(P - c, full_matrices=False)[2][0]
    ends = P[[np.argmin(s), np.argmax(s)]]
    return ends[np.argsort(ends[:, 0])]
