"""Prediction of a fitted lip regressor (core/lips/regressor/prediction.py).

On the hexagonal fan (one interior lip vertex, test_regressor_training) the regression is exact on its
training frames: the captured frame ``x -> s Q x + t`` predicts the corrected interior vertex ``t + delta``.
The float32 maps, the float64 dense maps and the sparse back-substitution are compared on the bumpy grid of
test_propagate."""

import numpy as np
import pytest

from facelab_addon.core.lips.regressor import LipRegressor, prediction

from .test_propagate import grid, lip_bump, smooth_random_deformation
from .test_regressor_features import MAPS
from .test_regressor_operators import fan
from .test_regressor_training import DELTA, SHIFT


def fitted(model):
    V, F, mouth, lips = fan()
    cap = np.stack([V @ A.T + SHIFT for A in MAPS])  # MAPS[2] is the identity: the rest pose, shifted
    fixed = cap.copy()
    fixed[:2, 0] += DELTA
    reg = LipRegressor(V, F, mouth, lips, patches=1, model=model).fit(fixed[:2], captured=cap[:2])
    return reg, cap


@pytest.mark.parametrize("model", ["whole", "correction", "auto"])
def test_training_frames_get_their_own_correction(model):
    reg, cap = fitted(model)
    ops, tm = reg.operators, reg.trained
    xi, xc = prediction.interior(ops, tm, cap[:2])
    np.testing.assert_allclose(xi[:, 0], SHIFT + DELTA, atol=1e-12)
    np.testing.assert_allclose(xc[:, 0], SHIFT + 0 * DELTA, atol=1e-12)
    np.testing.assert_allclose(prediction.lip_corrections(ops, tm, cap[:2])[:, 0], DELTA, atol=1e-12)
    out = prediction.predict_frames(ops, tm, cap[:2], None, 256)  # float32 maps
    np.testing.assert_allclose(out[:, 0], SHIFT + DELTA, atol=1e-6)
    np.testing.assert_array_equal(out[:, 1:], cap[:2, 1:])  # nothing else moves
    # on the span (extrapolation 0) the whole correction is expected to remove its own size: -|delta| (nI = 1)
    c, score, sq = prediction.correct_chunk(ops, tm, cap[:2])
    np.testing.assert_allclose(c[:, 0], DELTA, atol=1e-12)
    np.testing.assert_allclose(score, 0.0, atol=1e-7)
    np.testing.assert_allclose(sq, [12 * np.sum((A - np.eye(3)) ** 2) for A in MAPS[:2]], rtol=1e-10)
    want = -np.linalg.norm(DELTA, axis=1)
    np.testing.assert_allclose(prediction.expected_change(ops, tm, False, c, score), want, rtol=1e-6)


def test_the_rest_pose_predicts_itself_and_its_features_are_zero():
    """Rest-centred: the shifted rest pose (the identity map) has zero mouth features and no correction."""
    reg, cap = fitted("whole")
    ops, tm = reg.operators, reg.trained
    assert np.abs(prediction.mouth_rows(ops, cap[2:])).max() <= 1e-12
    np.testing.assert_allclose(prediction.lip_corrections(ops, tm, cap[2:]), 0.0, atol=1e-12)
    np.testing.assert_allclose(prediction.residual_norms(tm, prediction.mouth_rows(ops, cap[2:])), 0.0, atol=1e-12)
    G = prediction.predict_lip_gradients(ops, tm, cap[2:])
    np.testing.assert_allclose(G, np.broadcast_to(np.eye(3), G.shape), atol=1e-12)


def test_mouth_projections_are_the_features_projections():
    reg, cap = fitted("whole")
    ops, tm = reg.operators, reg.trained
    Y = prediction.mouth_rows(ops, cap)
    D = np.random.default_rng(4).standard_normal((Y.shape[1], 3))
    P, sq = prediction.mouth_projections(ops, tm, cap, D)
    np.testing.assert_allclose(P, Y @ D, atol=1e-10)
    np.testing.assert_allclose(sq, np.sum(Y * Y, axis=1), atol=1e-10)


def test_dense_maps_and_sparse_solve_agree(monkeypatch):
    V, F, mouth, lips = grid(bumpy=True)
    train = np.stack([smooth_random_deformation(V, s) for s in range(3)])
    cap = np.stack([smooth_random_deformation(V, s) + lip_bump(V) for s in range(5, 9)])
    reg = LipRegressor(V, F, mouth, lips, patches=3).fit(train, captured=train + lip_bump(V))
    ops, tm = reg.operators, reg.trained
    K, H, x0 = prediction.dense_solution(ops, tm)
    nI, nB = len(ops.interior_vertices), len(ops.border_vertices)
    assert K.shape == (3 * nI, tm.Zdiv.shape[1]) and H.shape == (nI, nB) and x0.shape == (nI, 3)
    np.testing.assert_allclose(ops.L_II @ H, ops.L_IB.toarray(), atol=1e-10)  # H = L_II⁻¹ L_IB
    dense = prediction.lip_corrections(ops, tm, cap)
    monkeypatch.setattr(prediction, "_DENSE_MAX", 0)
    assert prediction.dense_solution(ops, tm) is None
    np.testing.assert_allclose(prediction.lip_corrections(ops, tm, cap), dense, rtol=0, atol=1e-10)
    assert np.abs(dense).max() > 1e-2  # a real correction
