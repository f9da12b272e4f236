"""The lip regressor's checks (core/lips/regressor/guards.py) on hand-made inputs."""

import numpy as np
import pytest

from facelab_addon.core.errors import FaceLabError, FrameError, MeshError, PredictionError
from facelab_addon.core.lips.regressor.guards import (
    check_features,
    check_prediction,
    check_settings,
    checked_mesh,
    checked_out,
    same_array,
)


def test_check_prediction_names_the_frames_that_move_too_far_or_are_not_finite():
    xc = np.zeros((3, 2, 3))
    xi = xc.copy()
    xi[1, 0] = [3.0, 4.0, 0.0]  # moves 5 scene units
    check_prediction(xi, xc, 0, 5.0)  # exactly the mouth's size is allowed
    with pytest.raises(PredictionError, match="frame index 11.*up to 5 scene units") as e:
        check_prediction(xi, xc, 10, 4.9)
    assert e.value.frame_indices == (11,)
    xi[2, 1, 2] = np.nan
    with pytest.raises(PredictionError, match="not finite") as e:
        check_prediction(xi, xc, 0, 5.0)
    assert e.value.frame_indices == (2,)


def test_check_features_wants_float_rows_of_nine_per_mouth_triangle():
    Y = np.zeros((4, 18))
    assert check_features(Y, 2) is not None
    with pytest.raises(FaceLabError, match=r"expected \(T, 27\)"):
        check_features(Y, 3)
    with pytest.raises(FaceLabError, match="0 frames"):
        check_features(Y[:0], 2)
    with pytest.raises(FaceLabError, match="dtype int"):
        check_features(Y.astype(int), 2)
    Y[3, 5] = np.inf
    with pytest.raises(FrameError, match="frame index 3"):
        check_features(Y, 2)


def test_checked_out_and_same_array():
    A = np.zeros((1, 4, 3))
    out = np.ones((4, 3), np.float32)
    view = checked_out(out, A)
    assert view.shape == (1, 4, 3) and np.shares_memory(view, out)  # a (V,3) out for a single frame
    with pytest.raises(FaceLabError, match="dtype int"):
        checked_out(np.zeros((1, 4, 3), int), A)
    with pytest.raises(FaceLabError, match="expected \\(1, 4, 3\\)"):
        checked_out(np.zeros((2, 4, 3)), A)
    ro = np.zeros((1, 4, 3))
    ro.flags.writeable = False
    with pytest.raises(FaceLabError, match="read-only"):
        checked_out(ro, A)
    assert same_array(A, A) and same_array(A[:], A)  # the same elements of the same buffer
    assert not same_array(A.copy(), A) and not same_array(A[:, ::2], A[:, :2])


@pytest.mark.parametrize("ridge, rtol, atol, patches, radius, bad", [
    (-0.1, 1e-4, 1e-4, 1, None, "ridge"), ("gcv", 1e-4, 1e-4, 1, None, "ridge"), (0, 1.0, 1e-4, 1, None, "rtol"),
    (0, 1e-4, -1e-4, 1, None, "atol"), (0, 1e-4, 1e-4, 1.5, None, "patches"), (0, 1e-4, 1e-4, 0, None, "patches"),
    (0, 1e-4, 1e-4, True, None, "patches"), (0, 1e-4, 1e-4, 3, 0.0, "input_radius"),
])
def test_check_settings_names_the_setting(ridge, rtol, atol, patches, radius, bad):
    with pytest.raises(FaceLabError, match=bad):
        check_settings(ridge, rtol, atol, patches, radius)
    check_settings("loo", 0.0, 0.0, 10, 0.5)  # all in range


def test_checked_mesh():
    R, F = checked_mesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.array([[0, 1, 2]], np.int32))
    assert R.dtype == np.float64 and F.dtype == np.int64
    with pytest.raises(MeshError, match="out of range"):
        checked_mesh(R, [[0, 1, 3]])
    with pytest.raises(MeshError, match="NaN"):
        checked_mesh([[0, 0, np.nan]], [[0, 0, 0]])
    with pytest.raises(MeshError, match="triangulate"):
        checked_mesh(R, [[0, 1, 2, 0]])
