"""LipRegressor's ``damping`` (issue 11, Propagate's Damp Uncertain Frames): each frame's predicted correction
``c`` is scaled by ``s = |c|² / (|c|² + S)``, ``S`` the model's expected error on that frame
(:mod:`facelab_addon.core.lips.regressor.model_choice`). Grid face of tests/core/test_propagate.py, ground truth known."""

import numpy as np
import pytest

from facelab_addon.core.errors import UsageError
from facelab_addon.core.lips.regressor.model_choice import damping_weights, expected_error
from facelab_addon.core.lips.regressor import LipRegressor

from .test_propagate import f32_tol, grid, lip_bump, smooth_random_deformation


def _fit(V, F, mouth, lips, truth, cap, train, damping, model="auto"):
    reg = LipRegressor(V, F, mouth, lips, damping=damping, model=model)
    fixed = cap[train].copy()
    fixed[:, reg.interior_vertices] = truth[train][:, reg.interior_vertices]
    return reg.fit(fixed, captured=cap[train], shot=cap)


def _frame_rms(reg, X, truth):
    iv = reg.interior_vertices
    return np.sqrt(np.mean(np.sum((X[:, iv] - truth[:, iv]) ** 2, axis=2), axis=1))


@pytest.fixture(scope="module")
def extrapolated_scene():
    """Five smooth motions; the 4 training frames use the first four only. The capture error (a lip bump) fades
    to 0 where the fifth motion is large: those held-out frames are captured exactly, and lie outside the
    training span, where the learnt correction (the bump of every training frame) does not apply."""
    V, F, mouth, lips = grid(bumpy=True)
    basis = np.stack([smooth_random_deformation(V, s) for s in range(5)]) - V
    W = np.random.default_rng(0).uniform(-1, 1, (60, 5))
    train, held = np.arange(4), np.arange(4, 60)
    W[train, 4] = 0.0
    amp = 0.05 * np.clip(1 - np.abs(W[:, 4]) / 0.5, 0, 1)
    truth = V + np.einsum("tk,kvc->tvc", W, basis)
    cap = truth + amp[:, None, None] * lip_bump(V)[None]
    return V, F, mouth, lips, truth, cap, train, held, amp


def test_a_well_captured_frame_far_from_the_training_poses_keeps_most_of_its_capture(extrapolated_scene):
    """Without damping, the frames captured exactly get most of the learnt bump: damage 75-85 % of the bump's
    RMS. With damping at most X = 0.75 of it: measured 0.69. X follows from the weights: the damage on each such
    frame is exactly ``s`` times the undamped one (the truth is the capture there), and ``s`` is 0.77-0.92 on
    these frames (the farther from the training poses, the smaller), so at most 0.92 x 0.85 = 0.78 of the bump
    could remain; 0.75 is the measured 0.69 with the weights' spread. The held-out RMS falls too (0.0067 ->
    0.0058; capture 0.0041). Nothing in the training frames says that the error fades, so the damage is
    reduced, not removed: only a training frame like these can teach that."""
    V, F, mouth, lips, truth, cap, train, held, amp = extrapolated_scene
    bump = 0.05 * np.sqrt(np.mean(np.sum(lip_bump(V) ** 2, axis=1)[LipRegressor(V, F, mouth, lips).interior_vertices]))
    off, on = (_fit(V, F, mouth, lips, truth, cap, train, d) for d in (False, True))
    X, Y = cap[held], truth[held]
    e0 = _frame_rms(off, X, Y)
    e_off, e_on = _frame_rms(off, off.predict(X), Y), _frame_rms(on, on.predict(X), Y)
    good = amp[held] == 0
    assert good.sum() >= 20 and np.all(e0[good] == 0)
    assert (e_off[good] > 0.7 * bump).all()  # the problem: the correction damages frames that were right
    assert e_on[good].max() <= 0.75 * bump  # X
    s = on.damping_weights(X)
    np.testing.assert_allclose(e_on[good], s[good] * e_off[good], rtol=1e-6, atol=10 * f32_tol(on))
    assert np.sqrt(np.mean(e_on**2)) < 0.9 * np.sqrt(np.mean(e_off**2))


def test_the_weights_follow_the_expected_error(extrapolated_scene):
    """``s = |c|² / (|c|² + S)`` with ``S = (α² a_w + (1-α)² a_c) r²`` at each frame's distance ``r`` from the
    training span, the same on every path (positions, streaming corrections, chunks); 1 without damping and on
    the training frames (r = 0: the training corrections are kept exactly)."""
    V, F, mouth, lips, truth, cap, train, held, _ = extrapolated_scene
    off, on = (_fit(V, F, mouth, lips, truth, cap, train, d) for d in (False, True))
    X = cap[held]
    c = off.lip_corrections(X)
    r2 = (on.extrapolation(X) * on.trained.data.sigma) ** 2
    S = expected_error(on.trained.error_model, on.whole_weight, r2)
    s = damping_weights(np.sum(c * c, axis=(1, 2)), S)
    np.testing.assert_allclose(on.damping_weights(X), s, rtol=1e-9)
    np.testing.assert_allclose(off.damping_weights(X), 1.0)
    np.testing.assert_allclose(on.damping_weights(cap[train]), 1.0, atol=1e-9)
    # (without damping predict runs the float32 maps)
    np.testing.assert_allclose(on.predict(cap[train]), off.predict(cap[train]), rtol=0, atol=3 * f32_tol(off))
    assert 0.7 < s.min() and s.max() < 1
    np.testing.assert_allclose(on.lip_corrections(X), s[:, None, None] * c, rtol=0, atol=1e-12)
    corr, score, _ = on.correct_chunk(X)
    np.testing.assert_allclose(corr, s[:, None, None] * c, rtol=0, atol=1e-12)
    np.testing.assert_allclose(score, on.extrapolation(X), rtol=1e-6, atol=1e-9)
    iv = on.interior_vertices
    np.testing.assert_allclose(on.predict(X)[:, iv], X[:, iv] + s[:, None, None] * c, rtol=0, atol=1e-12)


def test_a_correction_the_model_is_sure_of_is_kept():
    """A capture error that is the same bump on every frame, expressions in the span of 6 training frames
    (the whole-motion model is exact, the correction model too): the expected error is ~0, so damping keeps
    the correction (s > 0.99) and the held-out error (under 5 % of the capture's) within 1 % of the undamped one."""
    V, F, mouth, lips = grid(bumpy=True)
    basis = np.stack([smooth_random_deformation(V, s) for s in range(4)]) - V
    W = np.random.default_rng(1).uniform(-1, 1, (30, 4))
    truth = V + np.einsum("tk,kvc->tvc", W, basis)
    cap = truth + 0.05 * lip_bump(V)[None]
    train, held = np.arange(6), np.arange(6, 30)
    for model in ("auto", "whole", "correction"):
        off, on = (_fit(V, F, mouth, lips, truth, cap, train, d, model) for d in (False, True))
        X, Y = cap[held], truth[held]
        e0 = np.sqrt(np.mean(_frame_rms(off, X, Y) ** 2))
        assert on.damping_weights(X).min() > 0.99, model
        e_off, e_on = (np.sqrt(np.mean(_frame_rms(r, r.predict(X), Y) ** 2)) for r in (off, on))
        assert e_off < 0.05 * e0 and e_on <= 1.01 * e_off + f32_tol(on), model


def test_damping_must_be_a_bool():
    V, F, mouth, lips = grid()
    with pytest.raises(UsageError, match="damping"):
        LipRegressor(V, F, mouth, lips, damping="yes")
