"""``core.geometry.rigid.rigid_fit``: hand-made rotations and outliers."""

import numpy as np
import pytest

from facelab_addon.core.errors import FaceLabError
from facelab_addon.core.geometry.rigid import rigid_fit


def _rot_z(deg):
    a = np.radians(deg)
    return np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])


def test_a_quarter_turn_and_a_shift_are_found_exactly():
    A = np.array([[0.0, 0, 0], [1, 0, 0], [0, 2, 0], [0, 0, 3]])
    # by hand: a quarter turn about z maps (1,0,0) -> (0,1,0) and (0,2,0) -> (-2,0,0); then shifted by (5,0,-1)
    B = np.array([[5.0, 0, -1], [5, 1, -1], [3, 0, -1], [5, 0, 2]])
    R, t = rigid_fit(A, B)
    np.testing.assert_allclose(R, [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(t, [5, 0, -1], atol=1e-12)


def test_a_mirror_image_gives_a_rotation_not_a_reflection():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(50, 3))
    R, _ = rigid_fit(A, A * [-1.0, 1.0, 1.0])
    assert np.linalg.det(R) == pytest.approx(1.0)


def test_trimming_ignores_the_points_that_did_not_move_rigidly():
    rng = np.random.default_rng(1)
    A = rng.normal(size=(400, 3))
    R0 = _rot_z(20.0)
    B = A @ R0.T + [0.1, 0.2, 0.3]
    B[:120] += rng.normal(scale=0.5, size=(120, 3))  # 30 % moved on their own (an expression, an opened jaw)
    R_all, _ = rigid_fit(A, B)
    R_trim, t = rigid_fit(A, B, keep=0.5)
    assert np.abs(R_all - R0).max() > 1e-3  # plain least squares is pulled off
    np.testing.assert_allclose(R_trim, R0, atol=1e-12)
    np.testing.assert_allclose(t, [0.1, 0.2, 0.3], atol=1e-12)


@pytest.mark.parametrize("A,B,msg", [
    (np.zeros((2, 3)), np.zeros((2, 3)), "at least 3"),
    (np.zeros((4, 3)), np.zeros((5, 3)), "same shape"),
    (np.full((4, 3), np.nan), np.zeros((4, 3)), "NaN"),
])
def test_bad_input_is_named(A, B, msg):
    with pytest.raises(FaceLabError, match=msg):
        rigid_fit(A, B)
