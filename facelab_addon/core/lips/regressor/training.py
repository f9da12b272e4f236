"""Training of a lip regressor: the reduced regressions of the corrected frames.

Dinev et al. 2018, "User-Guided Lip Correction for Facial Performance Capture", §4: the mouth
features ``y`` and inner-lip features ``x`` of the k corrected frames give, per patch, thin SVDs and
the reduced map θ̄ (:mod:`.reduced`), folded into the operators of the prediction
(:mod:`.features`). Alongside the paper's whole-motion map, the correction model (corrected minus
captured lip gradients, with a constant) is fitted from the same mouth coefficients, and the blend of
the two is chosen by :mod:`.model_choice`. :func:`train` turns training features into a
:class:`.state.TrainedModel`; it changes nothing it is given. Features are unitless (deformation
gradients); frames are in scene units.
"""

from __future__ import annotations

import numpy as np

from ...errors import FaceLabError, FrameError, UsageError
from .features import (
    as_frames,
    feature_rows,
    fold_coefficients,
    fold_directions,
    frames_of,
    gradients,
    patch_operators,
)
from .model_choice import choose_blend, error_model, shot_features
from .reduced import choose_ridge, loo_residuals, solve_theta, thin_svd
from .state import LipOperators, Settings, TrainedModel, TrainingSet

__all__ = ["training_features", "shot_inputs", "train"]


def _training_frames(ops: LipOperators, corrected):
    c = np.asarray(corrected)
    if c.size == 0 or (c.ndim == 3 and c.shape[0] == 0):
        raise FaceLabError(
            "No corrected frames were given; correct at least one frame (sketch or sculpt it) before training."
        )
    return as_frames(c, ops.n_vertices, "corrected frames", ops.used)


def training_features(ops: LipOperators, settings: Settings, corrected, captured=None):
    """Training columns of corrected frames (and of the same frames as captured).

    Parameters
    ----------
    ops : LipOperators
    settings : Settings
    corrected : (j,V,3) or (V,3) array_like
        Corrected frames, scene units.
    captured : (j,V,3) or (V,3) array_like, optional
        The same frames as captured.

    Returns
    -------
    y : (9m, j) float64 ndarray
        Mouth features, one column per frame.
    x : (9n, j) float64 ndarray
        Lip features of the corrected frames.
    xc : (9n, j) float64 ndarray or None
        Corrected minus captured lip features (None without ``captured``).
    """
    center = settings.center
    C = _training_frames(ops, corrected)
    y = feature_rows(gradients(C, ops.mouth_rinv, ops.mouth_verts, ops.mouth_local), center).T
    x = feature_rows(gradients(C, ops.lip_rinv, ops.lip_verts, ops.lip_local), center).T
    if captured is None:
        if settings.model == "correction":
            raise UsageError("model='correction' regresses corrected minus captured lips: pass the captured "
                             "training frames as fit(corrected, captured=...)")
        return y, x, None
    K = _training_frames(ops, captured)
    if K.shape != C.shape:
        raise FaceLabError(f"captured training frames have shape {K.shape}, the corrected ones {C.shape}; pass "
                           "the same frames as captured")
    xk = feature_rows(gradients(K, ops.lip_rinv, ops.lip_verts, ops.lip_local), center).T
    return y, x, x - xk


def shot_inputs(ops: LipOperators, settings: Settings, shot, used_only, xc):
    """The shot's (mouth (T, 9m), captured lip (T, 9n)) features when the model choice will use them, else None.

    ``shot`` (T,V,3) (or (T, nU, 3) of the used vertices with ``used_only``) are the frames to be
    corrected; ``xc`` the training lip corrections (None: no correction model, the shot is not needed).
    """
    if shot is None or xc is None or settings.model == "whole" or (settings.model == "correction"
                                                                   and not settings.damping):
        return None
    return shot_features(ops, frames_of(ops, shot, "shot frames", used_only), used_only)


def train(ops: LipOperators, settings: Settings, Y, X, Xc=None, shot=None) -> TrainedModel:
    """Fit training features: the global span, each patch's maps, the blend weight, the folded operators.

    Parameters
    ----------
    ops : LipOperators
    settings : Settings
    Y : (9m, k) float64 ndarray
        Mouth features of the training frames (kept, not copied).
    X : (9n, k) float64 ndarray
        Lip features of the corrected frames (kept).
    Xc : (9n, k) float64 ndarray, optional
        Corrected minus captured lip features (kept); None fits the whole-motion model only.
    shot : tuple of (T, 9m), (T, 9n) ndarrays, optional
        :func:`shot_inputs` of the frames to be corrected, for the model choice.

    Returns
    -------
    TrainedModel

    Raises
    ------
    FrameError
        With ``center="rest"``, when no training frame moves the mouth (all in the rest pose to within
        ``atol``).
    """
    m, n = len(ops.mouth_faces), len(ops.lip_faces)
    k = Y.shape[1]
    UYg, _ = thin_svd(Y, settings.center, settings.rtol, settings.atol)
    if UYg.shape[1] == 0:
        raise FrameError(
            "The training frames do not move the mouth (in {frames} the mouth is in its rest pose to "
            f"within an RMS strain of {settings.atol:g}), so the regression cannot learn how the lips follow the "
            "mouth and would extrapolate without bound. Add corrected frames where the mouth moves (open, smile, "
            "pucker); a fix of the neutral pose itself belongs in the rest mesh.",
            range(k),
        )
    data = TrainingSet(Y, X, Xc, UYg, _span_sigma(Y, settings, m))
    Y3 = Y.reshape(m, 9, k)
    X3 = X.reshape(n, 9, k)
    Xc3 = None if Xc is None else Xc.reshape(n, 9, k)
    fits = []
    for mouth_sel, lip_sel, _ in ops.patches:
        UY, CY, UX, th, lam, E = _fit_patch(Y3[mouth_sel], X3[lip_sel], settings)
        if UY.shape[1] == 0:  # this patch's mouth input does not move in training: read the whole mouth
            mouth_sel = np.arange(m)
            UY, CY, UX, th, lam, E = _fit_patch(Y3, X3[lip_sel], settings)
        corr = None if Xc3 is None or settings.model == "whole" else _fit_output(CY, Xc3[lip_sel], settings, m)
        fits.append((mouth_sel, UY, UX, th, lam, E, corr))
    a, model_errors, em = _choose_blend(ops, data, settings, fits, shot)
    B = np.zeros((n, 9))  # the correction model's constant lip gradients, blended over patches
    if a < 1.0:
        for (_, lip_sel, w), f in zip(ops.patches, fits):
            B[lip_sel] += f[6][3].reshape(len(lip_sel), 9) * w[:, None]
    x_b = ops.factor.solve(ops.D_I @ B.reshape(n, 3, 3).transpose(0, 2, 1).reshape(3 * n, 3))
    theta_bars, ridges_used, pfit, fit_mouth_sel = [], [], [], []
    Zs, Ws, zid = [], [], []
    for (_, lip_sel, w), Dp, (mouth_sel, UY, UX, th, lam, _, corr) in zip(ops.patches, ops.D_patch, fits):
        fit_mouth_sel.append(mouth_sel)
        theta_bars.append(th)
        ridges_used.append(lam)
        if a < 1.0:  # the blend's lip output per coefficient: α U_X θ̄ + (1 - α) U_Xc θ̄_c
            UX, th = np.hstack([UX, corr[0]]), np.vstack([a * th, (1.0 - a) * corr[1]])
        pfit.append((UX, th, UY))
        Z, W, z0 = patch_operators(len(ops.interior_vertices), ops.mouth_rinv[mouth_sel], lip_sel, w, Dp, UY, UX,
                                   th, settings.center == "rest")
        Zs.append(Z)
        Ws.append(W)
        zid.append(z0)
    Zdiv = np.concatenate(Zs, axis=1)  # (nI*3, Σ rY)
    Mx, Mc = fold_coefficients(ops.mouth_local, len(ops.mouth_verts), fit_mouth_sel, Ws, m)
    # the global span and the identity, folded beside the coefficients: one pass gives both (correct_chunk)
    ident = np.tile(np.eye(3).ravel(), m)[:, None]
    Ms = fold_directions(np.hstack([data.UY, ident]), ops.mouth_rinv, ops.mouth_local, len(ops.mouth_verts))
    span_ident = (ident.T @ data.UY).ravel() if settings.center == "rest" else np.zeros(data.UY.shape[1])
    return TrainedModel(
        data=data, theta_bars=theta_bars, ridges_used=ridges_used, pfit=pfit, fit_mouth_sel=fit_mouth_sel,
        whole_weight=a, model_errors=model_errors, expected_model=em, error_model=em if settings.damping else None,
        B=B, x_b=x_b, Zdiv=Zdiv, Mx=Mx, Mc=Mc, z_ident=np.concatenate(zid), Mx_all=np.hstack([Mx, Ms[0]]),
        Mc_all=np.hstack([Mc, Ms[1]]), span_ident=span_ident,
    )


def _span_sigma(Y, settings, m):
    """RMS deformation of the mouth features (extrapolation score, suggest_frames), floored at the absolute rank
    cut so the score stays bounded."""
    Yd = Y if settings.center == "rest" else Y - np.tile(np.eye(3).ravel(), m)[:, None]
    return max(float(np.sqrt(np.mean(np.sum(Yd * Yd, axis=0)))), settings.atol * np.sqrt(m), 1e-12)


def _fit_patch(Yp, Xp, settings):
    """One patch's reduced regression from its (m_p,9,k) mouth and (n_p,9,k) lip features.

    Returns ``(U_Y, C_Y, U_X, θ̄, λ, E)``: the mouth basis and coefficients, the lip basis, the (rX, rY)
    reduced map, the ridge used and the leave-one-out residuals ``E`` (9 n_p, k) of the lip features.
    """
    k = Yp.shape[-1]
    UY, CY = thin_svd(Yp.reshape(-1, k), settings.center, settings.rtol, settings.atol)
    UX, CX = thin_svd(Xp.reshape(-1, k), settings.center, settings.rtol, settings.atol)
    lam = choose_ridge(CY, CX, settings.ridge)
    th = solve_theta(CY, CX, lam)  # (rX, rY)
    E = UX @ loo_residuals(CY, CX, lam)  # the expected-error model (damping, expected_change)
    return UY, CY, UX, th, lam, E


def _fit_output(CY, Xp, settings, m):
    """The correction model of a patch: ``(U_Xc, θ̄_c, E_c, b)`` for lip corrections Xp (n_p,9,k), same mouth
    input plus a constant (the intercept ``b`` (9 n_p,), a correction present in the rest pose). Its ridge weight
    is ``ridge`` (with ``"loo"`` its own leave-one-out choice); the intercept is never penalized."""
    k = Xp.shape[-1]
    # a difference (centred already), small beside the motion: only round-off is cut (1e-7 of its size), so a
    # correction far smaller than the absolute cut of the motion is still reproduced on the training frames
    UX, CX = thin_svd(Xp.reshape(-1, k), "rest", 1e-7, 0.0)
    s = np.sqrt(3.0 * m)  # the norm of the mouth's identity gradients (paper's uncentred y)
    CYa = np.vstack([CY, np.full((1, k), s)])
    lam = choose_ridge(CYa, CX, settings.ridge, free=1)  # its own ridge; the intercept is never shrunk
    E = UX @ loo_residuals(CYa, CX, lam, free=1)
    th = solve_theta(CYa, CX, lam, free=1)
    return UX, th[:, :-1], E, UX @ th[:, -1] * s


def _choose_blend(ops, data, settings, fits, shot):
    """``(α, model_errors, expected-error model)``: α of the model (1: whole, 0: correction; "auto":
    :func:`.model_choice.choose_blend`) and the expected-error model (:func:`.model_choice.error_model`)."""
    model_errors = {}
    if settings.model == "auto" and fits[0][6] is not None:
        a, model_errors, em = choose_blend(ops, data, fits, shot)
    else:
        a = 0.0 if settings.model == "correction" else 1.0
        em = error_model(ops, data, fits, shot if a == 0.0 else None)
    return a, model_errors, em
