"""Surface-point binding (Bhat et al. 2013 §4.1): ray cast and nearest point against hand-computed geometry."""

import numpy as np

from facelab_addon.core.capture.camera import Camera
from facelab_addon.core.capture.markers import (
    SurfacePoints,
    bind_surface_points,
    nearest_surface_points,
    ray_triangle_hits,
)

# unit square in z=0 (two triangles) and, in front of it (z=1), a triangle covering x + y <= 0.5
V = np.array(
    [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [-1, -1, 1], [1.5, -1, 1], [-1, 1.5, 1]], dtype=float
)
F = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6]])


def cam_above(x, y):
    return Camera.look_at([x, y, 5.0], [x, y, 0.0], [0, 1, 0], 50, 36, 640, 480)


def test_ray_cast_hits_back_plane_with_hand_computed_barycentrics():
    cam = cam_above(0.7, 0.2)  # rays to (0.7,0.2,0) and (0.3,0.6,0) pass z=1 where x + y = 0.9: beside the occluder
    px = cam.project(np.array([[0.7, 0.2, 0.0], [0.3, 0.6, 0.0]]))
    pts, hit = bind_surface_points(V, F, cam, px)
    assert hit.all()
    # (0.7, 0.2) in triangle 0 = a + u(b-a) + v(c-a): v = 0.2, u = 0.5 -> (0.3, 0.5, 0.2)
    np.testing.assert_array_equal(pts.vertices[0], [0, 1, 2])
    np.testing.assert_allclose(pts.bary[0], [0.3, 0.5, 0.2], atol=1e-12)
    # (0.3, 0.6) in triangle 1 = (0,2,3): p = u(1,1) + v(0,1): u = 0.3, v = 0.3 -> (0.4, 0.3, 0.3)
    np.testing.assert_array_equal(pts.vertices[1], [0, 2, 3])
    np.testing.assert_allclose(pts.bary[1], [0.4, 0.3, 0.3], atol=1e-12)
    np.testing.assert_allclose(pts.evaluate(V), [[0.7, 0.2, 0.0], [0.3, 0.6, 0.0]], atol=1e-12)


def test_ray_cast_keeps_the_first_hit_and_reports_misses():
    cam = cam_above(0.0, 0.0)
    # ray to (0.1, 0.1, 0) crosses the occluder at z=1 first; (3, 3, 0) misses; NaN is untracked
    px = np.vstack([cam.project(np.array([[0.1, 0.1, 0.0], [3.0, 3.0, 0.0]])), [[np.nan, np.nan]]])
    pts, hit = bind_surface_points(V, F, cam, px)
    np.testing.assert_array_equal(hit, [True, False, False])
    np.testing.assert_array_equal(pts.vertices[0], [4, 5, 6])
    x = pts.evaluate(V)[0]
    # the ray from (0,0,5) through (0.1,0.1,0) meets z=1 at (0.08, 0.08, 1)
    np.testing.assert_allclose(x, [0.08, 0.08, 1.0], atol=1e-12)
    np.testing.assert_array_equal(pts.vertices[1:], -1)
    assert np.isnan(pts.evaluate(V)[1:]).all()
    # excluding the occluder with a face mask reaches the plane behind
    pts2, hit2 = bind_surface_points(V, F, cam, px[:1], face_mask=[True, True, False])
    assert hit2[0]
    np.testing.assert_allclose(pts2.evaluate(V)[0], [0.1, 0.1, 0.0], atol=1e-12)


def test_moller_trumbore_rejects_hits_behind_the_origin():
    a, b, c = np.array([[0.0, 0, 0]]), np.array([[1.0, 0, 0]]), np.array([[0.0, 1, 0]])
    t, bary = ray_triangle_hits(np.array([[0.2, 0.2, 1.0]]), np.array([[0, 0, -2.0]]), a, b, c)
    np.testing.assert_allclose(t, [0.5])
    np.testing.assert_allclose(bary, [[0.6, 0.2, 0.2]])
    t, _ = ray_triangle_hits(np.array([[0.2, 0.2, 1.0]]), np.array([[0, 0, 1.0]]), a, b, c)
    assert np.isinf(t).all()


def test_nearest_surface_points_inside_and_on_an_edge():
    P = np.array([[0.7, 0.2, 0.4], [2.0, 0.5, 0.0], [np.nan, 0, 0]])
    pts = nearest_surface_points(V[:4], F[:2], P)
    np.testing.assert_allclose(pts.evaluate(V[:4])[:2], [[0.7, 0.2, 0.0], [1.0, 0.5, 0.0]], atol=1e-12)
    np.testing.assert_allclose(pts.bary[0], [0.3, 0.5, 0.2], atol=1e-12)
    assert not pts.bound[2]


def test_surface_points_follow_a_deformation_and_sequences():
    pts = SurfacePoints([[0, 1, 2]], [[0.2, 0.3, 0.5]])
    seq = np.stack([V, V * 2.0, V + 1.0])
    x = pts.evaluate(seq)
    expect = 0.2 * seq[:, 0] + 0.3 * seq[:, 1] + 0.5 * seq[:, 2]
    np.testing.assert_allclose(x[:, 0], expect)
    np.testing.assert_allclose((pts.matrix(len(V)) @ V)[0], expect[0])


def test_bind_on_ict_recovers_visible_skin_points(ict):
    import time

    from facelab_addon.testing.capture_sim import helmet_cameras, sample_markers

    cams = helmet_cameras()
    skin = ict.part_face_mask("M_Face")
    mk = sample_markers(ict.neutral, ict.faces, cams, skin, n=60, seed=3)
    X = mk.evaluate(ict.neutral)
    for cam in cams:
        t0 = time.perf_counter()
        pts, hit = bind_surface_points(ict.neutral, ict.faces, cam, cam.project(X))
        dt = time.perf_counter() - t0
        assert hit.all()
        np.testing.assert_allclose(pts.evaluate(ict.neutral), X, atol=1e-9)
        assert dt < 2.0  # 60 rays x 52k triangles; typically ~0.03 s (generous for a loaded machine)
