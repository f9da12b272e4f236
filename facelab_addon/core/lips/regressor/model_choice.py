"""Which lip regression to trust: the whole-motion model, the correction model, or a blend of the two.

Dinev et al. 2018 (§4) regress the inner-lip deformation gradients themselves from the mouth's: the
*whole-motion* model, which must learn the lips' expression motion as well as the correction. With
few training frames on a wide lip band it cannot (3 frames do not span the band's expression
motion). The *correction* model regresses only corrected minus captured lip gradients (plus a
constant: a correction present in the rest pose) and adds them to the frame's captured gradients; it
needs no expression motion, but keeps whatever part of the capture error is not a linear function of
the mouth. :class:`.lip_regressor.LipRegressor` (``model="auto"``) predicts
``α · whole + (1 - α) · correction`` with ``α`` from this module. Both models and so the blend are
exact on the training frames.

The choice (an addition to the paper) estimates each model's expected error on the frames it will
correct (the *shot*), per interior lip vertex, from a simple error model:

* whole-motion model: ``a_w r²``, where ``r`` is the distance of a frame's mouth features from the
  span of the training frames (the model is exact on that span, so its error grows with ``r``);
* correction model: ``b + a_c r²``, a floor ``b`` (the capture error that is no linear function of
  the mouth, which no number of frames removes) plus the same growth.

The slopes come from leave-one-out over the k training frames (each frame predicted by the maps
fitted on the others, its Poisson-solved interior lip error against its own distance from the
others' span). The floor comes from the shot itself: on every shot frame the two models differ by
``D = (Θ - Γ) r - e`` with ``e`` the correction model's non-linear miss, so a least-squares fit of
``||D||² = c r² + b`` over the shot frames (non-negative) gives ``b = E||e||²``. Leave-one-out alone
overrates the whole model's error when the training frames are extreme poses (``suggest_frames``
picks them) and the shot lies between them; the shot's own ``r`` corrects that. The expected errors
``S_w = a_w mean(r²)`` and ``S_c = b + a_c mean(r²)`` over the shot are combined as independent
estimates: ``α = S_c / (S_w + S_c)``. Without shot frames the floor is taken as 0 and ``mean(r²)``
is that of the training frames' leave-one-out (a blend by inverse leave-one-out error).

The same error model damps the prediction frame by frame when asked (``LipRegressor(damping=True)``, Propagate's
Damp Uncertain Frames): :func:`expected_error` is its part that grows with a frame's distance from the training
span, and :func:`damping_weights` the Wiener factor ``|c|² / (|c|² + S)`` of a predicted correction ``c``.

How the three compare on held-out frames: docs/benchmarks.md (``benchmarks/lip_band.py``,
``benchmarks/propagate.py``).
"""

from __future__ import annotations

import numpy as np

from .features import gradient_features
from .reduced import loo_span_residuals

__all__ = ["shot_features", "error_model", "expected_error", "damping_weights", "choose_blend"]


def _poisson_per_frame(reg, G, k):
    """(k,) squared interior position norms of per-frame lip gradient changes G (n, 9, k), border held at 0."""
    n, nI = len(reg.lip_faces), len(reg.interior_vertices)
    rhs = reg.D_I @ G.reshape(n, 3, 3, k).transpose(0, 2, 1, 3).reshape(3 * n, 3 * k)  # columns (i, frame)
    P = reg.factor.solve(rhs).reshape(nI, 3, k)
    return np.sum(P * P, axis=(0, 1))


def _blend_patches(reg, parts, k):
    """(n, 9, k) lip gradient features blended over the patches from per-patch (9 n_p, k) arrays."""
    G = np.zeros((len(reg.lip_faces), 9, k))
    for (_, lip_sel, w), E in zip(reg.patches, parts):
        G[lip_sel] += E.reshape(len(lip_sel), 9, k) * w[:, None, None]
    return G


def shot_features(reg, frames, used_only):
    """``(Ys, Xs)``: (T, 9m) mouth and (T, 9n) captured lip features of shot frames (validated, float)."""
    mouth = reg.mouth_u if used_only else reg.mouth_verts
    lips = np.searchsorted(reg.used, reg.lip_verts) if used_only else reg.lip_verts
    center = reg.center == "rest"
    Ys = gradient_features(frames, mouth, reg.mouth_local, reg.mouth_rinv, center)
    Xs = gradient_features(frames, lips, reg.lip_local, reg.lip_rinv, center)
    return Ys, Xs


def _shot_floor(reg, fits, shot, r2_shot):
    """Floor ``b`` of the correction model's error: intercept of ``||D||² = c r² + b`` over the shot frames."""
    Ys, Xs = shot
    T = len(Ys)
    m9 = Ys.reshape(T, -1, 9)
    diff = []
    for (mouth_sel, lip_sel, _), f in zip(reg.patches, fits):
        sel, UY, UX, th, corr = f[0], f[1], f[2], f[3], f[6]
        z = m9[:, sel].reshape(T, -1) @ UY  # (T, rY) the patch's mouth coefficients
        UXc, thc, _, b = corr
        Xp = Xs.reshape(T, -1, 9)[:, lip_sel].reshape(T, -1)
        diff.append((UX @ (th @ z.T)) - (UXc @ (thc @ z.T)) - b[:, None] - Xp.T)  # whole - correction
    d2 = _poisson_per_frame(reg, _blend_patches(reg, diff, T), T)
    A = np.stack([r2_shot, np.ones(T)], axis=1)
    if T < 2 or np.ptp(r2_shot) <= 1e-12 * max(float(np.max(r2_shot)), 1e-300):
        return float(min(np.mean(d2), np.min(d2)))
    from scipy.optimize import nnls

    (_, b), _ = nnls(A, d2)
    return float(b)


def error_model(reg, span, fits, shot=None):
    """The expected-error model of both regressions: ``{"a_w", "a_c", "floor", "mean_r2"}``.

    A frame at squared distance ``r²`` from the training span (mouth features, unitless) is expected to
    miss the interior lip positions by ``a_w r²`` (whole-motion model) and ``floor + a_c r²`` (correction
    model), squared and summed over the interior lip vertices (scene units²). ``mean_r2`` is the mean
    ``r²`` over the shot (over the training frames' leave-one-out without one). Without the correction
    model (``fits[i][6]`` None) ``a_c`` and ``floor`` are 0.

    Parameters
    ----------
    reg, span, fits, shot
        As :func:`choose_blend`.

    Returns
    -------
    dict of float
    """
    k = span.k
    ew = _poisson_per_frame(reg, _blend_patches(reg, [f[5] for f in fits], k), k)
    r2 = loo_span_residuals(span.UY.T @ span.Y)  # each training mouth's distance from the others' span
    has_c = fits[0][6] is not None
    if shot is None:
        r2_shot, floor = r2, 0.0
    else:
        res = shot[0] - (shot[0] @ span.UY) @ span.UY.T
        r2_shot = np.sum(res * res, axis=1)
        floor = _shot_floor(reg, fits, shot, r2_shot) if has_c else 0.0
    denom = max(float(np.sum(r2)), 1e-30)
    a_c = 0.0
    if has_c:
        ec = _poisson_per_frame(reg, _blend_patches(reg, [f[6][2] for f in fits], k), k)
        a_c = max(float(np.sum(ec)) - k * floor, 0.0) / denom
    out = {"a_w": float(np.sum(ew)) / denom, "a_c": a_c, "floor": floor, "mean_r2": float(np.mean(r2_shot))}
    # the slopes the damping uses: fitted with an intercept, so a miss that does not grow with the distance (two
    # near-duplicate training poses corrected a little differently) is not read as a steep growth
    out["a_w_growth"] = _growth(r2, ew)
    out["a_c_growth"] = _growth(r2, ec - floor) if has_c else 0.0
    # and never more than the worst leave-one-out miss: a far frame's expected error is capped there, so a slope
    # read from a few close poses cannot switch every correction off
    out["worst_w"], out["worst_c"] = float(np.max(ew)), float(np.max(ec)) if has_c else 0.0
    return out


def _growth(r2, err) -> float:
    """Slope ``a >= 0`` of ``err ≈ b + a r2`` (``b >= 0``) over the training frames' leave-one-out."""
    r2, err = np.asarray(r2, np.float64), np.maximum(np.asarray(err, np.float64), 0.0)
    if len(r2) < 2 or np.ptp(r2) <= 1e-12 * max(float(np.max(r2)), 1e-300):
        return float(np.sum(err) / max(float(np.sum(r2)), 1e-30))
    from scipy.optimize import nnls

    (a, _), _ = nnls(np.stack([r2, np.ones_like(r2)], axis=1), err)
    return float(a)


def expected_error(model, alpha, r2):
    """(T,) the part of the blend's expected squared interior lip error that grows with ``r2`` (T,).

    ``(α² a_w + (1 - α)² a_c) r²``, with the slopes fitted with an intercept (``a_w_growth``, ``a_c_growth`` of
    :func:`error_model`) and capped at the worst leave-one-out miss of the training frames (``worst_w``,
    ``worst_c``) (scene units², summed over the interior lip vertices; the two models'
    errors taken as independent, :func:`error_model`): the error of extrapolating beyond the training
    frames. The correction model's floor is left out: it is the same on every frame, training frames and
    frames in their span included, where the prediction is as good as the training frames make it; so ``S``
    is 0 there (``r2`` 0) and the damping (:func:`damping_weights`) leaves those frames' corrections whole.
    """
    r2 = np.asarray(r2, dtype=np.float64)
    a_w, a_c = model.get("a_w_growth", model["a_w"]), model.get("a_c_growth", model["a_c"])
    S = (alpha * alpha * a_w + (1.0 - alpha) ** 2 * a_c) * r2
    if "worst_w" in model:
        S = np.minimum(S, alpha * alpha * model["worst_w"] + (1.0 - alpha) ** 2 * model["worst_c"])
    return S


def damping_weights(c2, S):
    """(T,) weights ``s = |c|² / (|c|² + S)`` in [0, 1) of predicted corrections of squared size ``c2`` (T,).

    The scalar that minimises the expected error ``E|s c - c*|²`` of a prediction ``c = c* + n`` of the
    true correction ``c*`` with an independent error ``n`` of expected size ``S`` (T,), taking
    ``|c|²`` for the correction's own size (Wiener). A correction well above its expected error is kept
    (``s → 1``); one no larger than it is halved or less, toward the capture.
    """
    c2 = np.asarray(c2, dtype=np.float64)
    S = np.asarray(S, dtype=np.float64)
    den = c2 + S
    return np.divide(c2, den, out=np.ones_like(den), where=den > 0)


def choose_blend(reg, span, fits, shot=None):
    """``(α, report, model)``: the whole-motion model's weight in the blend, the estimates behind it, the error model.

    Parameters
    ----------
    reg : LipOperators
        The regressor's regions, patches and Poisson factor (:class:`.state.LipOperators`).
    span : TrainingSet
        The training features and their global span (``Y``, ``UY``, ``k``; :class:`.state.TrainingSet`).
    fits : list
        Per patch ``(mouth_sel, U_Y, U_X, θ̄, λ, E_w, (U_Xc, θ̄_c, E_c, b))``: the two models' maps and
        leave-one-out residuals ``E`` (9 n_p, k) of the lip features.
    shot : tuple of (T, 9m), (T, 9n) ndarrays, optional
        Mouth and captured lip features of the frames to be corrected (:func:`shot_features`).

    Returns
    -------
    alpha : float
        In [0, 1]; 1 is the whole-motion model.
    report : dict
        Predicted RMS interior lip error of each model and of the blend over the shot (scene units),
        ``"whole"``, ``"correction"``, ``"blend"``, and the correction floor ``"floor"``.
    model : dict
        :func:`error_model`.
    """
    nI = len(reg.interior_vertices)
    em = error_model(reg, span, fits, shot)
    S_w = em["a_w"] * em["mean_r2"]
    S_c = em["floor"] + em["a_c"] * em["mean_r2"]
    alpha = 1.0 if S_w + S_c <= 0 else S_c / (S_w + S_c)
    S_b = alpha * alpha * S_w + (1 - alpha) ** 2 * S_c
    rms = lambda S: float(np.sqrt(max(S, 0.0) / nI))  # noqa: E731
    report = {"whole": rms(S_w), "correction": rms(S_c), "blend": rms(S_b), "floor": rms(em["floor"])}
    return float(alpha), report, em
