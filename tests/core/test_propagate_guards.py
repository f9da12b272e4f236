"""Numerical guards of the lip regression: rank cuts, no-motion training, checked outputs (issue 13, case 1)."""

import numpy as np
import pytest

from facelab_addon.core.errors import FaceLabError, FrameError, PredictionError
from facelab_addon.core.lips.regressor import LipRegressor
from facelab_addon.core.lips.regressor.reduced import thin_svd

from .test_propagate import fA, fB, grid, lip_bump, row_shift, smooth_random_deformation

MM = 0.1  # the grid is in centimetres: 1 mm


def neutral_fix(V):
    """The artist's 0.8 mm lip fix sculpted on the neutral (rest) frame."""
    e = lip_bump(V)
    return e * (0.8 * MM / np.abs(e).max())


def sequence(V):
    return np.stack([V, row_shift(V, fA), row_shift(V, fB)])


@pytest.mark.parametrize("patches", [1, 10])
def test_neutral_fix_as_only_training_frame_is_refused_naming_the_frame(patches):
    V, F, mouth, lips = grid(bumpy=True)
    reg = LipRegressor(V, F, mouth, lips, patches=patches)
    with pytest.raises(FrameError, match=r"do not move the mouth .*frame index 0.*Add corrected frames where the "
                                         r"mouth moves") as ei:
        reg.fit((V + neutral_fix(V))[None])
    assert ei.value.frame_index == 0 and ei.value.frame_indices == (0,)
    # the pipeline names the scene frame through the error's indices
    assert "frame 12 the mouth" in str(ei.value.for_frames([12]))
    assert isinstance(ei.value.for_frames([12]), FrameError)
    with pytest.raises(FaceLabError, match="call fit"):  # nothing was learnt
        reg.predict(V)


def test_refused_training_keeps_the_earlier_fit_and_the_artist_frames():
    V, F, mouth, lips = grid(bumpy=True)
    trainA = row_shift(V, fA) + lip_bump(V)
    reg = LipRegressor(V, F, mouth, lips).fit(trainA[None])
    seq = sequence(V)
    before = reg.predict(seq)
    neutral = (V + neutral_fix(V))[None]
    copy = neutral.copy()
    with pytest.raises(FrameError):
        reg.fit(neutral)
    np.testing.assert_array_equal(neutral, copy)
    assert reg.k == 1
    np.testing.assert_array_equal(reg.predict(seq), before)


def test_without_the_absolute_cut_the_neutral_case_explodes_and_predict_refuses_it_unwritten():
    """atol=0 is the relative cut alone (round-off singular values kept): the correction is ~1e11 scene units;
    predict refuses it naming the frames and leaves the in-place frames untouched."""
    V, F, mouth, lips = grid(bumpy=True)
    reg = LipRegressor(V, F, mouth, lips, atol=0.0).fit((V + neutral_fix(V))[None])
    seq = sequence(V)
    keep = seq.copy()
    with pytest.raises(PredictionError, match=r"frame indices 1 and 2 moves the lips by up to .*e\+\d\d scene units, "
                                              r"more than the whole mouth") as ei:
        reg.predict(seq, out=seq)
    assert ei.value.frame_indices == (1, 2)
    np.testing.assert_array_equal(seq, keep)
    assert "frames 31 and 32" in str(ei.value.for_frames([30, 31, 32]))



@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_in_place_blocks_already_written_are_restored_on_a_refusal(dtype):
    """In place, predict writes each block of frames once it passes its checks; a later block's refusal (an
    exploding frame, NaN coordinates) or an interruption puts every written block back, bit for bit."""
    from facelab_addon.core.errors import MeshError

    V, F, mouth, lips = grid(bumpy=True)
    reg = LipRegressor(V, F, mouth, lips, atol=0.0).fit((V + neutral_fix(V))[None])
    seq = sequence(V)  # frame 0 is the rest pose (predicted exactly, float64), 1 and 2 explode
    keep = seq.copy()
    with pytest.raises(PredictionError) as ei:
        reg.predict(seq, out=seq, chunk=1)  # frame 0 is written before frame 1 is refused
    assert ei.value.frame_indices == (1,)
    np.testing.assert_array_equal(seq, keep)
    seq = seq.astype(dtype)
    good = LipRegressor(V, F, mouth, lips).fit(np.stack([smooth_random_deformation(V, s) for s in range(3)]))
    seq[2, F[lips[0], 0], 1] = np.nan
    keep = seq.copy()
    with pytest.raises(MeshError, match="NaN.*frames \\[2\\]"):
        good.predict(seq, out=seq, chunk=1)
    np.testing.assert_array_equal(seq, keep)
    assert np.abs(good.predict(seq[:2]) - seq[:2]).max() > 1e-3 * MM  # frames 0 and 1 would change
    import facelab_addon.core.lips.regressor.prediction as feat

    calls = []

    def interrupted(*a, **k):  # the second block is interrupted (Esc, out of memory...)
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return _check(*a, **k)

    _check = feat.check_moves
    feat.check_moves = interrupted
    try:
        with pytest.raises(KeyboardInterrupt):
            good.predict(seq[:2], out=seq[:2], chunk=1)
    finally:
        feat.check_moves = _check
    np.testing.assert_array_equal(seq, keep)

def test_round_off_singular_values_are_cut_absolutely():
    rng = np.random.default_rng(0)
    M = np.zeros((9 * 50, 2))
    M[:, 0] = rng.standard_normal(450) * 1e-15
    U, C = thin_svd(M, "rest", 1e-4)  # relative cut only: the round-off direction is kept
    assert U.shape[1] >= 1
    U, C = thin_svd(M, "rest", 1e-4, atol=1e-4)
    assert U.shape == (450, 0) and C.shape == (0, 2)
    M[:, 1] = rng.standard_normal(450) * 0.05  # a real motion (5 % strain) survives both cuts
    U, C = thin_svd(M, "rest", 1e-4, atol=1e-4)
    assert U.shape[1] == 1
    np.testing.assert_allclose(U @ C, np.c_[np.zeros(450), M[:, 1]], atol=1e-12)


def test_uncentred_model_with_a_neutral_fix_predicts_the_fix_bounded():
    """The paper's uncentred model can learn a constant fix from the neutral frame: reproduced there, and
    every other frame moves by about the fix (0.8 mm), never more than 1 mm."""
    V, F, mouth, lips = grid(bumpy=True)
    fix = neutral_fix(V)
    reg = LipRegressor(V, F, mouth, lips, center=None).fit((V + fix)[None])
    seq = sequence(V)
    out = reg.predict(seq)
    np.testing.assert_allclose(out[0], V + fix, atol=1e-9)
    move = np.linalg.norm(out - seq, axis=2).max(axis=1)
    assert np.all(move < 1.0 * MM) and np.all(move > 0.6 * MM)
    assert np.all(np.isfinite(reg.extrapolation(seq)))


def test_patch_whose_mouth_does_not_move_reads_the_whole_mouth():
    """A training frame that moves one side of the mouth only: patches on the still side have no input motion.
    Relative cut alone: those patches explode; with the absolute cut the result is bounded and the training
    frame is reproduced."""
    V, F, mouth, lips = grid(bumpy=True)
    w = np.clip((6 - V[:, 0]) / 6, 0, None)
    train = V.copy()
    train[:, 1] += 0.5 * w * np.sin(V[:, 1])
    train += neutral_fix(V)
    seq = sequence(V)
    with pytest.raises(PredictionError):
        LipRegressor(V, F, mouth, lips, patches=10, atol=0.0).fit(train[None]).predict(seq)
    reg = LipRegressor(V, F, mouth, lips, patches=10).fit(train[None])
    np.testing.assert_allclose(reg.predict(train)[0], train, atol=1e-7 * reg.mouth_size)  # float32 arithmetic
    move = np.linalg.norm(reg.predict(seq) - seq, axis=2).max(axis=1)
    assert move[0] < 1e-9 and np.all(move < 0.8 * MM)  # the rest pose predicts itself; nothing above the fix


@pytest.mark.parametrize("out, match", [
    (np.zeros((3, 384, 3), np.int64), "dtype int64, which would round or truncate"),
    (np.zeros((3, 384, 3), np.float16), "dtype float16"),
    (np.zeros((2, 384, 3)), r"shape \(2, 384, 3\), expected \(3, 384, 3\)"),
    ([[0.0]], "must be a NumPy array"),
])
def test_predict_refuses_an_out_that_would_truncate_or_mismatch(out, match):
    V, F, mouth, lips = grid()
    assert len(V) == 384
    reg = LipRegressor(V, F, mouth, lips).fit((row_shift(V, fA) + lip_bump(V))[None])
    seq = sequence(V)
    keep = np.array(out, copy=True)
    with pytest.raises(FaceLabError, match=match):
        reg.predict(seq, out=out)
    np.testing.assert_array_equal(np.asarray(out), keep)


def test_predict_refuses_a_read_only_out_and_accepts_a_single_frame_out():
    V, F, mouth, lips = grid()
    train = row_shift(V, fA) + lip_bump(V)
    reg = LipRegressor(V, F, mouth, lips).fit(train[None])
    ro = np.zeros((1, len(V), 3))
    ro.flags.writeable = False
    with pytest.raises(FaceLabError, match="read-only"):
        reg.predict(train, out=ro)
    o = np.zeros((len(V), 3), np.float32)
    assert reg.predict(train, out=o) is o
    np.testing.assert_allclose(o, train, atol=1e-5)


@pytest.mark.parametrize("kw, match", [
    ({"ridge": -1}, "ridge must be"), ({"ridge": np.nan}, "ridge must be"), ({"rtol": 2.0}, "rtol must be"),
    ({"atol": -1e-3}, "atol must be"), ({"patches": 0}, "patches must be"), ({"input_radius": -1.0}, "input_radius"),
])
def test_settings_out_of_range_are_refused(kw, match):
    V, F, mouth, lips = grid()
    with pytest.raises(FaceLabError, match=match):
        LipRegressor(V, F, mouth, lips, **kw)


def test_extrapolation_refuses_non_finite_features_naming_the_frame():
    V, F, mouth, lips = grid()
    reg = LipRegressor(V, F, mouth, lips).fit((row_shift(V, fA) + lip_bump(V))[None])
    feats = reg.mouth_features(sequence(V))
    feats[2, 5] = np.inf
    with pytest.raises(FrameError, match="features of frame index 2 contain NaN") as ei:
        reg.extrapolation(features=feats)
    assert ei.value.frame_index == 2
