"""ShotCorrector: Propagate's per-chunk work in core. The chunked result equals the regressor on the whole shot
and does not depend on the chunking, training frames get no correction, the storage outcome turns to the patch
cache when the key offsets exceed the key budget (and only when a patch cache is allowed), and the expected-worse
frames come worst first."""

import numpy as np
import pytest

from facelab_addon.core.errors import FaceLabError
from facelab_addon.core.geometry.compress import StorageOutcome
from facelab_addon.core.lips.regressor import LipRegressor
from facelab_addon.core.lips.shot import ShotCorrector, expected_worse, key_shapes_over_cache
from facelab_addon.core.lips.suggest import suggest_frames

from .test_propagate import _sequence, grid, lip_bump

T = 24
TRAIN = [2, 9, 15, 20]
TOL = 1e-6


@pytest.fixture(scope="module")
def shot():
    """A fitted damped "auto" regressor, the captured shot (T,V,3) and its training mask."""
    V, F, mouth, lips = grid(bumpy=True)
    cap = _sequence(V, T, seed=21)  # smooth poses plus a lip bump: the capture error the training frames undo
    truth = cap[TRAIN] - lip_bump(V)[None]
    reg = LipRegressor(V, F, mouth, lips, model="auto", damping=True)
    reg.fit(truth, captured=cap[TRAIN], shot=cap)
    is_train = np.isin(np.arange(T), TRAIN)
    return reg, cap, is_train


def _run(reg, cap, is_train, sizes, **kw):
    c = ShotCorrector(reg, is_train, TOL, **kw)
    used = cap[:, reg.used_vertices]
    shown, s = [], 0
    for n in sizes:
        shown.append(c.add_chunk(used[s : s + n]))
        s += n
    return c, np.concatenate(shown), c.finish()


@pytest.mark.parametrize("sizes", [[5] * 4 + [4], [1] * T, [7, 13, 4]])
def test_chunked_equals_one_shot_and_the_regressor(shot, sizes):
    reg, cap, is_train = shot
    _, whole, one = _run(reg, cap, is_train, [T])
    _, got, res = _run(reg, cap, is_train, sizes)
    assert res.outcome is StorageOutcome.KEYS and one.outcome is StorageOutcome.KEYS
    np.testing.assert_allclose(got, whole, rtol=0, atol=1e-12)
    np.testing.assert_allclose(res.basis.shape[0], one.basis.shape[0])
    np.testing.assert_allclose(res.weights @ res.basis.reshape(len(res.basis), -1),
                               one.weights @ one.basis.reshape(len(one.basis), -1), rtol=0, atol=1e-12)
    np.testing.assert_allclose(res.extrapolation, one.extrapolation, rtol=0, atol=1e-12)
    np.testing.assert_allclose(res.expected_change, one.expected_change, rtol=0, atol=1e-12)

    # the values themselves: the regressor's correction of every other frame, none on the training frames
    want = reg.lip_corrections(cap)
    held = ~is_train
    assert np.abs(want[held]).max() > 1e-2  # a real correction
    np.testing.assert_allclose(got[held], want[held], rtol=0, atol=1e-9)
    assert not got[is_train].any()
    # the keys reproduce the shown correction within the tolerance, training frames included
    R = np.einsum("tr,rnc->tnc", res.weights, res.basis)
    assert np.sqrt(np.sum((R - got) ** 2, axis=2)).max() <= TOL
    score = reg.extrapolation(features=reg.mouth_features(cap))
    np.testing.assert_allclose(res.extrapolation[held], score[held], rtol=1e-6, atol=2e-6)
    assert not res.extrapolation[is_train].any() and not res.expected_change[is_train].any()
    corr, sc, _ = reg.correct_chunk(cap, first=0)
    np.testing.assert_allclose(res.expected_change[held], reg.expected_change(corr, sc)[held], rtol=1e-12)
    assert np.abs(res.expected_change[held]).max() > 0


def test_twins_take_their_representatives_correction(shot):
    reg, cap, is_train = shot
    n = len(reg.interior_vertices)
    take = np.r_[np.arange(n), [0, 5, n - 1]]  # three split-seam twins
    _, plain, _ = _run(reg, cap, is_train, [10, 14])
    _, got, res = _run(reg, cap, is_train, [10, 14], take=take)
    np.testing.assert_array_equal(got, plain[:, take])
    assert res.basis.shape[1] == n + 3
    R = np.einsum("tr,rnc->tnc", res.weights, res.basis)
    np.testing.assert_allclose(R[:, n:], R[:, [0, 5, n - 1]], rtol=0, atol=TOL)


def test_key_offsets_past_the_key_budget_turn_to_the_patch_cache(shot):
    reg, cap, is_train = shot
    _, want, keys = _run(reg, cap, is_train, [8, 8, 8])
    assert len(keys.basis) > 1  # needs more than one shape
    calls = []

    def to_key(corr):
        calls.append(len(corr))
        return 2.0 * corr  # any map: only its rank matters here

    c, got, res = _run(reg, cap, is_train, [8, 8, 8], max_key_shapes=1, patch_cache=True)
    assert res.outcome is StorageOutcome.PATCH_CACHE and res.basis is None and res.weights is None
    np.testing.assert_array_equal(got, want)  # the shown correction (the patch cache's) is unchanged
    np.testing.assert_array_equal(res.extrapolation, keys.extrapolation)
    # once the outcome is the patch cache, the key offsets are no longer mapped
    c = ShotCorrector(reg, is_train, TOL, max_key_shapes=1, patch_cache=True)
    used = cap[:, reg.used_vertices]
    for s in (0, 8, 16):
        c.add_chunk(used[s : s + 8], to_key)
    assert calls == [8] and not c.wants_key_offsets
    # off a capture cache there is no patch cache: refused, naming the fix
    c = ShotCorrector(reg, is_train, TOL, max_key_shapes=1)
    with pytest.raises(FaceLabError, match="more than 1 corrective shapes"):
        c.add_chunk(used)


def test_every_frame_once():
    V, F, mouth, lips = grid(bumpy=True)
    cap = _sequence(V, 6)
    reg = LipRegressor(V, F, mouth, lips).fit(cap[:3] - lip_bump(V)[None])
    c = ShotCorrector(reg, np.zeros(6, bool), TOL)
    c.add_chunk(cap[:4, reg.used_vertices])
    with pytest.raises(FaceLabError, match="Only 4 of the shot's 6 frames"):
        c.finish()
    with pytest.raises(FaceLabError, match="6 frames; 8 were added"):
        c.add_chunk(cap[:4, reg.used_vertices])


def test_suggestions_are_suggest_frames_on_the_whole_shot(shot):
    reg, cap, is_train = shot
    c, _, _ = _run(reg, cap, is_train, [5] * 4 + [4], suggest=True)
    used = cap[:, reg.used_vertices]
    picks = c.suggest(3, lambda idx: used[idx])
    want = suggest_frames(None, 3, regressor=reg, features=reg.mouth_features(cap), exclude=TRAIN)
    assert list(picks) == list(want) and not set(picks) & set(TRAIN)


def test_expected_worse_and_key_budget():
    change = np.array([0.0, 3.0, 1.0, 3.0, 0.5, -2.0])
    np.testing.assert_array_equal(expected_worse(change, 0.75), [1, 3, 2])  # worst first, ties in shot order
    assert expected_worse(change, 5.0).size == 0
    assert key_shapes_over_cache(24) == 96 and key_shapes_over_cache(3) == 64
