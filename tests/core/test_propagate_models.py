"""LipRegressor's models (issue 11): the paper's whole-motion regression, the correction regression (corrected
minus captured lip gradients, added to the capture) and the "auto" blend chosen from the training frames and
the shot (:mod:`facelab_addon.core.lips.regressor.model_choice`). Grid face of tests/core/test_propagate.py."""

import numpy as np
import pytest

from facelab_addon.core.errors import FaceLabError, UsageError
from facelab_addon.core.geometry.gradients import deformation_gradients
from facelab_addon.core.lips.regressor import LipRegressor
from facelab_addon.core.lips.regressor.reduced import loo_residuals, loo_span_residuals, solve_theta

from .test_propagate import f32_tol, grid, lip_bump, smooth_random_deformation


def poses(V, seeds):
    return np.stack([smooth_random_deformation(V, s) for s in seeds])


def lip_error(V, F, lips, amp):
    """(T,V,3) capture errors: ``amp[t]`` times a bump on the interior lip vertices."""
    return np.asarray(amp)[:, None, None] * lip_bump(V)[None]


def fit_all(V, F, mouth, lips, truth, cap, train, shot, models=("whole", "correction", "auto")):
    """Regressors of each model trained on ``train`` (corrected = capture with the true interior lips)."""
    out = {}
    for m in models:
        reg = LipRegressor(V, F, mouth, lips, model=m)
        fixed = cap[train].copy()
        fixed[:, reg.interior_vertices] = truth[train][:, reg.interior_vertices]
        out[m] = reg.fit(fixed, captured=cap[train], shot=shot)
    return out


def lip_err(reg, X, truth):
    iv = reg.interior_vertices
    return np.sqrt(np.mean(np.sum((X[:, iv] - truth[:, iv]) ** 2, axis=2)))


def test_few_frames_cannot_span_the_expression_but_can_learn_the_correction():
    """Random expressions (3 training frames cannot span them) with a capture error that is the same bump on
    every frame: the whole-motion model misses the expression, the correction model only the bump's
    modulation; auto follows the correction model, is exact on the training frames, and 0 extrapolation there."""
    V, F, mouth, lips = grid(bumpy=True)
    truth = poses(V, range(12))
    cap = truth + lip_error(V, F, lips, 0.03 * np.ones(12))
    train, held = [0, 1, 2], np.arange(3, 12)
    regs = fit_all(V, F, mouth, lips, truth, cap, train, cap)
    e = {m: lip_err(r, r.predict(cap[held]), truth[held]) for m, r in regs.items()}
    e0 = lip_err(regs["auto"], cap[held], truth[held])
    assert e["whole"] > 0.5 * e0  # 3 frames do not span the expression
    assert e["correction"] < 0.1 * e0
    assert regs["auto"].whole_weight < 0.1 and e["auto"] < 0.15 * e0
    # every model keeps the training corrections exactly, and the training frames do not extrapolate
    for r in regs.values():
        fixed = cap[train].copy()
        fixed[:, r.interior_vertices] = truth[train][:, r.interior_vertices]
        np.testing.assert_allclose(r.predict(cap[train]), fixed, atol=f32_tol(r))
        np.testing.assert_allclose(r.extrapolation(cap[train]), 0.0, atol=1e-9)


def test_a_capture_error_that_does_not_follow_the_mouth_is_left_to_the_whole_model():
    """Expressions in the span of the training frames with a capture error of random size on every frame: the
    correction model cannot predict it (it keeps the capture's error), the whole-motion model removes it;
    auto sees the models disagree on the shot (the correction model's floor) and follows the whole model."""
    V, F, mouth, lips = grid(bumpy=True)
    rng = np.random.default_rng(3)
    basis = poses(V, range(4)) - V
    W = rng.uniform(-1, 1, (40, 4))
    truth = V + np.einsum("tk,kvc->tvc", W, basis)
    cap = truth + lip_error(V, F, lips, rng.uniform(-1, 1, 40))
    train, held = [0, 1, 2, 3, 4, 5], np.arange(6, 40)
    regs = fit_all(V, F, mouth, lips, truth, cap, train, cap)
    e = {m: lip_err(r, r.predict(cap[held]), truth[held]) for m, r in regs.items()}
    e0 = lip_err(regs["auto"], cap[held], truth[held])
    assert e["whole"] < 0.05 * e0 and e["correction"] > 0.3 * e0
    assert regs["auto"].whole_weight > 0.9 and e["auto"] < 0.1 * e0
    assert regs["auto"].model_errors["floor"] > 0


@pytest.fixture
def blend_scene():
    V, F, mouth, lips = grid(bumpy=True)
    rng = np.random.default_rng(7)
    truth = poses(V, range(10))
    cap = truth + lip_error(V, F, lips, 0.05 + 0.05 * rng.uniform(-1, 1, 10))
    return V, F, mouth, lips, truth, cap


def test_any_blend_is_the_blend_of_the_two_models_on_every_path(blend_scene, monkeypatch):
    """The folded maps of a blend (forced to α = 0.4) give α · whole + (1 - α) · correction: positions through the
    float32 maps, the float64 maps, the sparse solve and the streaming chunks, and the lip gradients."""
    import facelab_addon.core.lips.regressor.prediction as feats
    import facelab_addon.core.lips.regressor.training as training

    V, F, mouth, lips, truth, cap = blend_scene
    train, held = [0, 1, 2, 3], np.arange(4, 10)
    regs = fit_all(V, F, mouth, lips, truth, cap, train, None, ("whole", "correction"))
    monkeypatch.setattr(training, "choose_blend", lambda reg, span, fits, shot: (0.4, {}, None))
    reg = fit_all(V, F, mouth, lips, truth, cap, train, None, ("auto",))["auto"]
    assert reg.whole_weight == 0.4
    X = cap[held]
    want = 0.4 * regs["whole"].predict(X) + 0.6 * regs["correction"].predict(X)
    assert np.abs(want - regs["whole"].predict(X)).max() > 1e3 * f32_tol(reg)  # the models really differ
    np.testing.assert_allclose(reg.predict(X), want, rtol=0, atol=3 * f32_tol(reg))  # float32 maps
    iv = reg.interior_vertices
    f64 = X[:, iv] + reg.lip_corrections(X)
    np.testing.assert_allclose(f64, want[:, iv], rtol=0, atol=3 * f32_tol(reg))
    corr, score, _ = reg.correct_chunk(X)
    np.testing.assert_allclose(corr, reg.lip_corrections(X), rtol=0, atol=1e-12)
    np.testing.assert_allclose(score, reg.extrapolation(X), rtol=0, atol=1e-9)
    monkeypatch.setattr(feats, "_DENSE_MAX", 0)  # the sparse back-substitution
    np.testing.assert_allclose(X[:, iv] + reg.lip_corrections(X), f64, rtol=0, atol=1e-9)
    G = 0.4 * regs["whole"].predict_lip_gradients(X) + 0.6 * regs["correction"].predict_lip_gradients(X)
    np.testing.assert_allclose(reg.predict_lip_gradients(X), G, atol=1e-9)
    # the correction model's gradients are the captured ones plus the correction: on a training frame, the truth's
    fixed = cap[train].copy()
    fixed[:, iv] = truth[train][:, iv]
    np.testing.assert_allclose(regs["correction"].predict_lip_gradients(cap[train]),
                               deformation_gradients(V, fixed, F[lips]), atol=1e-7)
    np.testing.assert_allclose(reg.predict(cap[train]), fixed, rtol=0, atol=f32_tol(reg))


def test_add_equals_fit_and_bad_settings_are_refused(blend_scene):
    V, F, mouth, lips, truth, cap = blend_scene
    ref = fit_all(V, F, mouth, lips, truth, cap, [0, 1, 2, 3], cap, ("auto",))["auto"]
    reg = LipRegressor(V, F, mouth, lips)
    iv = reg.interior_vertices
    fixed = cap.copy()
    fixed[:, iv] = truth[:, iv]
    reg.fit(fixed[:2], captured=cap[:2], shot=cap).add(fixed[2:4], captured=cap[2:4], shot=cap)
    assert reg.whole_weight == pytest.approx(ref.whole_weight, abs=1e-9)
    np.testing.assert_allclose(reg.predict(cap[4:]), ref.predict(cap[4:]), rtol=0, atol=f32_tol(reg))
    # the shot may hold only the used vertices
    sub = LipRegressor(V, F, mouth, lips).fit(fixed[:4], captured=cap[:4], shot=cap[:, reg.used_vertices],
                                              used_only=True)
    assert sub.whole_weight == pytest.approx(ref.whole_weight, abs=1e-12)
    # without the captured frames "auto" is the paper's whole-motion model, bit for bit
    paper = LipRegressor(V, F, mouth, lips, model="whole").fit(fixed[:4], captured=cap[:4])
    auto = LipRegressor(V, F, mouth, lips).fit(fixed[:4])
    assert auto.whole_weight == 1.0 and auto.model_errors == {}
    assert np.array_equal(auto.predict(cap[4:]), paper.predict(cap[4:]))
    with pytest.raises(UsageError, match="model must be one of"):
        LipRegressor(V, F, mouth, lips, model="both")
    with pytest.raises(UsageError, match="captured="):
        LipRegressor(V, F, mouth, lips, model="correction").fit(fixed[:4])
    with pytest.raises(FaceLabError, match="the same frames as captured"):
        LipRegressor(V, F, mouth, lips).fit(fixed[:4], captured=cap[:3])


def test_leave_one_out_helpers_are_exact():
    """loo_residuals: the map fitted on the other frames, applied to each frame; loo_span_residuals: the squared
    distance of each frame from the span of the others (checked against direct least squares)."""
    rng = np.random.default_rng(1)
    CY, CX = rng.standard_normal((5, 4)), rng.standard_normal((3, 4))
    E = loo_residuals(CY, CX, 0.0)
    r2 = loo_span_residuals(CY)
    for i in range(4):
        keep = np.arange(4) != i
        th = solve_theta(CY[:, keep], CX[:, keep], 0.0)
        np.testing.assert_allclose(E[:, i], th @ CY[:, i] - CX[:, i], atol=1e-12)
        c, *_ = np.linalg.lstsq(CY[:, keep], CY[:, i], rcond=None)
        assert r2[i] == pytest.approx(np.sum((CY[:, keep] @ c - CY[:, i]) ** 2), rel=1e-9)
    np.testing.assert_allclose(loo_residuals(CY[:, :1], CX[:, :1], 0.0), -CX[:, :1])  # k = 1: the empty map
    assert loo_span_residuals(np.hstack([CY[:, :2], CY[:, :1]]))[0] == pytest.approx(0.0, abs=1e-20)
