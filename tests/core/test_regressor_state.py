"""The regressor's state (core/lips/regressor/state.py) is plain data: the settings, the operators and the fit
are all a LipRegressor holds, so a fit carries over to another regressor on the same mesh, and a refused fit
leaves the earlier one in place."""

import numpy as np
import pytest

from facelab_addon.core.errors import FrameError
from facelab_addon.core.lips.regressor import LipRegressor
from facelab_addon.core.lips.regressor.state import TrainingSet

from .test_propagate import grid, lip_bump, smooth_random_deformation


def test_the_fit_is_all_the_state_a_prediction_reads():
    V, F, mouth, lips = grid(bumpy=True)
    train = np.stack([smooth_random_deformation(V, s) for s in range(3)])
    cap = np.stack([smooth_random_deformation(V, s) + lip_bump(V) for s in range(5, 8)])
    a = LipRegressor(V, F, mouth, lips, patches=3).fit(train, captured=train + lip_bump(V), shot=cap)
    b = LipRegressor(V, F, mouth, lips, patches=3)
    assert b.trained is None and b.k == 0 and b.whole_weight == 1.0
    b.trained = a.trained
    np.testing.assert_array_equal(b.predict(cap), a.predict(cap))
    np.testing.assert_array_equal(b.correct_chunk(cap)[0], a.correct_chunk(cap)[0])
    assert (b.k, b.whole_weight, b.model_errors) == (3, a.whole_weight, a.model_errors)
    assert a.operators.n_vertices == len(V) and a.trained.data.k == 3
    # a refused fit (no mouth motion) keeps the earlier one
    before = a.trained
    with pytest.raises(FrameError):
        a.fit(np.repeat(V[None], 2, axis=0))
    assert a.trained is before


def test_training_set_counts_its_columns():
    Y = np.zeros((18, 4))
    assert TrainingSet(Y, np.zeros((9, 4)), None, np.zeros((18, 1)), 1.0).k == 4
