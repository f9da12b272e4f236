import numpy as np
import pytest

from facelab_addon.core.capture.camera import Camera
from facelab_addon.core.errors import CameraError


def _rot(axis, ang):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(ang) * K + (1 - np.cos(ang)) * K @ K


def test_project_hand_computed():
    # f = 1000 px, principal point (960, 540); identity pose
    K = np.array([[1000.0, 0, 960], [0, 1000, 540], [0, 0, 1]])
    cam = Camera(K, np.eye(3), np.zeros(3), 1920, 1080)
    X = np.array([[0.0, 0, 10], [1, 0, 10], [0, 2, 10], [-1, -1, 5]])
    np.testing.assert_allclose(cam.project(X), [[960, 540], [1060, 540], [960, 740], [760, 340]])


def test_rays_round_trip_and_pass_through_points():
    rng = np.random.default_rng(1)
    cam = Camera.look_at([3, -2, 40], [0, 0, 0], [0, 1, 0], 50, 36, 1920, 1080)
    X = rng.normal(size=(50, 3)) * 5
    px = cam.project(X)
    o, d = cam.rays(px)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0)
    np.testing.assert_allclose(o, np.repeat(cam.center[None], 50, 0))
    v = X - o
    perp = v - (v * d).sum(1, keepdims=True) * d
    assert np.abs(perp).max() < 1e-9
    assert ((v * d).sum(1) > 0).all()  # rays point into the scene


def test_look_at_is_opencv():
    cam = Camera.look_at([0, 0, 40], [0, 0, 0], [0, 1, 0], 50, 36, 1920, 1080)
    # world +y (up) must go up in the image (smaller pixel y), +x to the right
    p = cam.project(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]]))
    np.testing.assert_allclose(p[0], [960, 540])
    assert p[1, 0] > 960 and abs(p[1, 1] - 540) < 1e-9
    assert p[2, 1] < 540 and abs(p[2, 0] - 960) < 1e-9
    np.testing.assert_allclose(cam.K[0, 0], 50 / 36 * 1920)
    np.testing.assert_allclose(cam.forward, [0, 0, -1], atol=1e-12)


@pytest.mark.parametrize("scale", [1.0, -2.5, 1e-3])
def test_from_projection_round_trip(scale):
    R = _rot([0.3, 1, 0.2], 0.7)
    K = np.array([[1500.0, 2.0, 900], [0, 1400, 560], [0, 0, 1]])
    cam = Camera(K, R, [0.1, -0.4, 30], 1920, 1080)
    cam2 = Camera.from_projection(scale * cam.P, 1920, 1080)
    np.testing.assert_allclose(cam2.K, cam.K, atol=1e-8)
    np.testing.assert_allclose(cam2.R, cam.R, atol=1e-10)
    np.testing.assert_allclose(cam2.t, cam.t, atol=1e-9)


def test_bad_cameras_raise():
    with pytest.raises(CameraError, match="rotation"):
        Camera(np.diag([1000, 1000, 1.0]), 2 * np.eye(3), np.zeros(3), 10, 10)
    with pytest.raises(CameraError, match="focal"):
        Camera(np.diag([0, 1000, 1.0]), np.eye(3), np.zeros(3), 10, 10)
    with pytest.raises(CameraError, match="singular"):
        Camera.from_projection(np.zeros((3, 4)), 10, 10)
