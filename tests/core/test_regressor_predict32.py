"""The float32 prediction maps (core/lips/regressor/predict32.py) against the float64 prediction."""

import numpy as np
import pytest

from facelab_addon.core.errors import PredictionError
from facelab_addon.core.lips.regressor import LipRegressor, prediction
from facelab_addon.core.lips.regressor.predict32 import check_moves, Float32Prediction, PredictionWork, put_rows

from .test_propagate import grid, lip_bump, smooth_random_deformation


@pytest.mark.parametrize("model", ["whole", "correction"])
def test_float32_maps_match_the_float64_prediction(model):
    V, F, mouth, lips = grid(bumpy=True)
    train = np.stack([smooth_random_deformation(V, s) for s in range(3)])
    reg = LipRegressor(V, F, mouth, lips, patches=3, model=model).fit(train, captured=train + lip_bump(V))
    ops, tm = reg.operators, reg.trained
    maps = Float32Prediction(ops, tm, prediction.dense_solution(ops, tm))
    cap = np.stack([V] + [smooth_random_deformation(V, s) + lip_bump(V) for s in range(5, 9)])
    want, _ = prediction.undamped_interior(ops, tm, cap)
    for A in (cap, cap.astype(np.float32)):  # float32 and float64 frames give the same displacements
        w = PredictionWork()  # one prediction's buffers (the frames' dtype), kept across its blocks
        xi, xc = maps.interior(A, np.empty(want.shape), None, w)
        np.testing.assert_array_equal(maps.interior(A, np.empty(want.shape), None, w)[0], xi)
        np.testing.assert_array_equal(xc, A[:, ops.interior_vertices])
        np.testing.assert_allclose(xi, want, rtol=0, atol=1e-7 * ops.mouth_size)
        if model == "whole":  # the rest pose predicts itself (rest-centred) to float64 round-off
            np.testing.assert_allclose(xi[0], V[ops.interior_vertices], rtol=0, atol=1e-9 * ops.mouth_size)
    assert np.abs(want[1:] - cap[1:, ops.interior_vertices]).max() > 1e-2  # a real correction
    bad = cap.copy()
    bad[2, ops.border_vertices[0], 1] = np.nan
    assert maps.interior(bad, np.empty(want.shape)) is None


def test_put_rows_and_check_moves():
    A = np.zeros((2, 5, 3), np.float32)
    put_rows(A, np.array([1, 3]), np.arange(12.0).reshape(2, 2, 3))
    np.testing.assert_array_equal(A[:, [0, 2, 4]], 0)
    np.testing.assert_array_equal(A[:, [1, 3]], np.arange(12.0).reshape(2, 2, 3))
    xc = np.zeros((3, 2, 3))
    xi = xc.copy()
    xi[2, 1] = [2.0, 2.0, 1.0]  # moves 3 scene units
    check_moves(xi, xc, 0, 3.0)
    with pytest.raises(PredictionError, match="frame index 7"):
        check_moves(xi, xc, 5, 2.9)


def test_work_buffers_are_reused_and_grown():
    w = PredictionWork()
    a = w.get("x", (4, 3))
    assert w.get("x", (2, 3)) is a and a.dtype == np.float32
    assert w.get("x", (8, 3)).shape == (8, 3)
