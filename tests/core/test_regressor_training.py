"""Training of the lip regressor (core/lips/regressor/training.py) on the hexagonal fan of
test_regressor_operators: frames are similarity maps ``x -> s Q x + t`` of the whole mesh (mouth gradients
``s Q`` on every triangle), corrected by moving the one interior lip vertex by ``delta``."""

import numpy as np
import pytest

from facelab_addon.core.errors import FrameError, UsageError
from facelab_addon.core.lips.regressor.operators import lip_operators
from facelab_addon.core.lips.regressor.state import Settings
from facelab_addon.core.lips.regressor.training import shot_inputs, train, training_features

from .test_regressor_features import MAPS
from .test_regressor_operators import fan

DELTA = np.array([[0.0, 0.0, 0.2], [0.05, -0.1, 0.0]])
SHIFT = np.array([0.3, -0.2, 1.0])


def scene(**kw):
    V, F, mouth, lips = fan()
    st = Settings(**{**dict(center="rest", ridge=0.0, rtol=1e-4, atol=1e-4, model="auto", damping=False), **kw})
    ops = lip_operators(V, F, mouth, lips, center=st.center, patches=1, input_radius=None, backend="splu")
    captured = np.stack([V @ A.T + SHIFT for A in MAPS[:2]])
    corrected = captured.copy()
    corrected[:, 0] += DELTA
    return ops, st, captured, corrected


def test_training_features_are_the_mouth_and_lip_gradients():
    ops, st, captured, corrected = scene()
    y, x, xc = training_features(ops, st, corrected, captured)
    assert y.shape == (9 * 12, 2) and x.shape == (9 * 6, 2) and xc.shape == (9 * 6, 2)
    for i, A in enumerate(MAPS[:2]):
        np.testing.assert_allclose(y[:, i], np.tile((A - np.eye(3)).ravel(), 12), atol=1e-12)  # mouth: s Q - I
    # the captured lips are the similarity too: the correction is x minus that, nonzero only from the moved vertex
    x_cap = np.stack([np.tile((A - np.eye(3)).ravel(), 6) for A in MAPS[:2]], 1)
    np.testing.assert_allclose(xc, x - x_cap, atol=1e-12)
    assert np.abs(xc).max() > 0.05
    assert training_features(ops, st, corrected)[2] is None  # without the captured frames
    with pytest.raises(UsageError, match="captured="):
        training_features(ops, Settings("rest", 0.0, 1e-4, 1e-4, "correction", False), corrected)


def test_train_fits_the_span_and_the_blend():
    ops, st, captured, corrected = scene(model="whole")
    y, x, xc = training_features(ops, st, corrected, captured)
    tm = train(ops, st, y, x, xc)
    assert tm.data.k == 2 and tm.whole_weight == 1.0 and tm.model_errors == {} and tm.error_model is None
    np.testing.assert_allclose(tm.data.UY.T @ tm.data.UY, np.eye(tm.data.UY.shape[1]), atol=1e-12)
    np.testing.assert_allclose(tm.data.UY @ (tm.data.UY.T @ y), y, atol=1e-12)  # spans the training mouths
    # σ: the RMS over frames of ||y_i|| = sqrt(12) ||s Q - I||
    want = np.sqrt(np.mean([12 * np.sum((A - np.eye(3)) ** 2) for A in MAPS[:2]]))
    assert tm.data.sigma == pytest.approx(want, rel=1e-12)
    assert len(tm.theta_bars) == 1 and tm.Zdiv.shape == (3, tm.Mx.shape[1])
    corr = train(ops, Settings("rest", 0.0, 1e-4, 1e-4, "correction", True), y, x, xc)
    assert corr.whole_weight == 0.0 and corr.error_model is corr.expected_model is not None  # damping keeps it


def test_a_training_set_without_mouth_motion_is_refused():
    ops, st, captured, corrected = scene()
    rest = np.repeat(ops.rest[None], 2, axis=0)
    y, x, _ = training_features(ops, st, rest)
    with pytest.raises(FrameError, match="do not move the mouth") as e:
        train(ops, st, y, x)
    assert e.value.frame_indices == (0, 1)


def test_shot_inputs_only_when_the_choice_uses_them():
    ops, st, captured, corrected = scene()
    xc = np.zeros((54, 2))
    Ys, Xs = shot_inputs(ops, st, captured, False, xc)
    used = shot_inputs(ops, st, captured[:, ops.used], True, xc)
    assert Ys.shape == (2, 108) and Xs.shape == (2, 54)
    np.testing.assert_array_equal(used[0], Ys)
    np.testing.assert_array_equal(used[1], Xs)
    assert shot_inputs(ops, st, captured, False, None) is None  # no correction model: nothing to choose
    assert shot_inputs(ops, Settings("rest", 0.0, 1e-4, 1e-4, "whole", False), captured, False, xc) is None
