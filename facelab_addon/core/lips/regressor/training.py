"""Training of :class:`.propagate.LipRegressor`: the reduced regressions of the corrected frames.

Dinev et al. 2018, "User-Guided Lip Correction for Facial Performance Capture", §4: the mouth
features ``y`` and inner-lip features ``x`` of the k corrected frames give, per patch, thin SVDs and
the reduced map θ̄ (:mod:`.reduced`), folded into the operators of the prediction
(:mod:`.features`). Alongside the paper's whole-motion map, the correction model (corrected minus
captured lip gradients, with a constant) is fitted from the same mouth coefficients, and the blend of
the two is chosen by :mod:`.model_choice`. Features are unitless (deformation gradients); frames are
in scene units.

Package-internal (a mixin of ``LipRegressor``): the public API is :class:`.propagate.LipRegressor`.
"""

from __future__ import annotations

import numpy as np

from ..errors import FaceLabError, FrameError, UsageError
from .features import (
    as_frames as _as_frames,
    fold_coefficients as _fold_coefficients,
    fold_directions as _fold_directions,
    patch_operators as _patch_operators,
)
from .model_choice import choose_blend, error_model, shot_features
from .reduced import choose_ridge, loo_residuals, solve_theta, thin_svd

__all__: list[str] = []


class RegressorTraining:
    """The training methods of :class:`.propagate.LipRegressor` (mixed into it)."""

    # ------------------------------------------------------------------ training
    def fit(self, corrected, captured=None, *, shot=None, used_only=False):
        """Fit the reduced regression(s) on corrected frames, replacing any earlier training.

        Parameters
        ----------
        corrected : (k,V,3) array_like
            Corrected (ground-truth) frames, scene units. For each, the mouth
            gradients give ``y`` (the mouth is trusted, so corrected = captured
            there) and the lip gradients give ``x``.
        captured : (k,V,3) array_like, optional
            The same frames as captured: their lip gradients give the
            correction model's output ``x - x_captured`` (``model`` "auto" or
            "correction"). Without them only the whole-motion model is fitted
            (``model="correction"`` is refused).
        shot : (T,V,3) array_like, optional
            Captured frames the model will correct (the shot, or an even
            sample of it: a few dozen frames suffice), for ``model="auto"``:
            their distance from the training poses and the two models'
            disagreement on them set the blend (:mod:`.model_choice`).
        used_only : bool
            ``shot`` holds only the :attr:`used_vertices` of each frame.

        Returns
        -------
        self

        Raises
        ------
        FaceLabError
            With fewer than one training frame, a topology that differs from
            the rest mesh, or NaN coordinates.
        FrameError
            With ``center="rest"``, when no training frame moves the mouth
            (all in the rest pose to within ``atol``); the earlier fit is kept.
        """
        y, x, xc = self._training_features(corrected, captured)
        self._refit(y.copy(), x.copy(), xc, self._shot(shot, used_only, xc))
        return self

    def _shot(self, shot, used_only, xc):
        """The shot's (mouth, captured lip) features when the "auto" choice will use them, else None."""
        if shot is None or xc is None or self.model == "whole" or (self.model == "correction" and not self.damping):
            return None
        return shot_features(self, self._frames(shot, "shot frames", used_only), used_only)

    def add(self, corrected, captured=None, *, shot=None, used_only=False):
        """Add corrected frame(s) to the training set and update the fit.

        Re-runs the thin SVDs on the stacked ``k+1`` columns (cost
        ``O(9m k²)`` per patch, milliseconds); the result equals :meth:`fit`
        on all frames.

        Parameters
        ----------
        corrected : (V,3) or (j,V,3) array_like
            New corrected frame(s), scene units.
        captured : (V,3) or (j,V,3) array_like, optional
            The same frames as captured (as :meth:`fit`); needed for the
            correction model when the earlier frames had them.
        shot, used_only
            As :meth:`fit`.

        Returns
        -------
        self
        """
        y, x, xc = self._training_features(corrected, captured)
        sh = self._shot(shot, used_only, xc)
        if self._Y is None:
            self._refit(y.copy(), x.copy(), xc, sh)
        else:
            both = xc is not None and self._Xc is not None
            self._refit(np.hstack([self._Y, y]), np.hstack([self._X, x]), np.hstack([self._Xc, xc]) if both else None,
                        sh)
        return self

    def _training_frames(self, corrected):
        c = np.asarray(corrected)
        if c.size == 0 or (c.ndim == 3 and c.shape[0] == 0):
            raise FaceLabError(
                "No corrected frames were given; correct at least one frame (sketch or sculpt it) before training."
            )
        return _as_frames(c, self.n_vertices, "corrected frames", self._used)

    def _training_features(self, corrected, captured=None):
        """``(y, x, x - x_captured)``: (9m, j) mouth, (9n, j) lip features and lip corrections (None without
        ``captured``) of corrected frames, one column per frame."""
        C = self._training_frames(corrected)
        y = self._feat(self._grad(C, self._mouth_rinv, self._mouth_verts, self._mouth_local)).T
        x = self._feat(self._grad(C, self._lip_rinv, self._lip_verts_all, self._lip_local)).T
        if captured is None:
            if self.model == "correction":
                raise UsageError("model='correction' regresses corrected minus captured lips: pass the captured "
                                 "training frames as fit(corrected, captured=...)")
            return y, x, None
        K = self._training_frames(captured)
        if K.shape != C.shape:
            raise FaceLabError(f"captured training frames have shape {K.shape}, the corrected ones {C.shape}; pass "
                               "the same frames as captured")
        xk = self._feat(self._grad(K, self._lip_rinv, self._lip_verts_all, self._lip_local)).T
        return y, x, x - xk

    def _refit(self, Y, X, Xc=None, shot=None):
        """Refit on training features ``Y`` (9m, k), ``X`` (9n, k), lip corrections ``Xc`` (9n, k) or None: global
        span, each patch's maps, the blend weight (:meth:`_choose_blend`), then the folded operators.

        Refuses (:class:`FrameError`, nothing changed) a rest-centred training set without mouth motion.
        """
        m, n = len(self.mouth_faces), len(self.lip_faces)
        k = Y.shape[1]
        UYg, _ = thin_svd(Y, self.center, self.rtol, self.atol)
        if UYg.shape[1] == 0:
            raise FrameError(
                "The training frames do not move the mouth (in {frames} the mouth is in its rest pose to "
                f"within an RMS strain of {self.atol:g}), so the regression cannot learn how the lips follow the mouth "
                "and would extrapolate without bound. Add corrected frames where the mouth moves (open, smile, "
                "pucker); a fix of the neutral pose itself belongs in the rest mesh.",
                range(k),
            )
        self._Y, self._X, self._Xc, self.k = Y, X, Xc, k
        Y3 = Y.reshape(m, 9, self.k)
        X3 = X.reshape(n, 9, self.k)
        Xc3 = None if Xc is None else Xc.reshape(n, 9, self.k)
        self._fit_span(Y, UYg)
        self.theta_bars, self.ridges_used = [], []
        self._pfit, self._fit_mouth_sel = [], []
        fits = []
        for mouth_sel, lip_sel, _ in self._patches:
            UY, CY, UX, th, lam, E = self._fit_patch(Y3[mouth_sel], X3[lip_sel])
            if UY.shape[1] == 0:  # this patch's mouth input does not move in training: read the whole mouth
                mouth_sel = np.arange(m)
                UY, CY, UX, th, lam, E = self._fit_patch(Y3, X3[lip_sel])
            corr = None if Xc3 is None or self.model == "whole" else self._fit_output(CY, Xc3[lip_sel])
            fits.append((mouth_sel, UY, UX, th, lam, E, corr))
        self.whole_weight = self._choose_blend(fits, shot)
        a = self.whole_weight
        B = np.zeros((n, 9))  # the correction model's constant lip gradients, blended over patches
        if a < 1.0:
            for (_, lip_sel, w), f in zip(self._patches, fits):
                B[lip_sel] += f[6][3].reshape(len(lip_sel), 9) * w[:, None]
        self._B = B
        self._x_b = self._factor.solve(self._D_I @ B.reshape(n, 3, 3).transpose(0, 2, 1).reshape(3 * n, 3))
        Zs, Ws, zid = [], [], []
        for (_, lip_sel, w), Dp, (mouth_sel, UY, UX, th, lam, _, corr) in zip(self._patches, self._D_patch, fits):
            self._fit_mouth_sel.append(mouth_sel)
            self.theta_bars.append(th)
            self.ridges_used.append(lam)
            if a < 1.0:  # the blend's lip output per coefficient: α U_X θ̄ + (1 - α) U_Xc θ̄_c
                UX, th = np.hstack([UX, corr[0]]), np.vstack([a * th, (1.0 - a) * corr[1]])
            self._pfit.append((UX, th, UY))
            Z, W, z0 = _patch_operators(len(self.interior_vertices), self._mouth_rinv[mouth_sel], lip_sel, w, Dp, UY, UX,
                                        th, self.center == "rest")
            Zs.append(Z)
            Ws.append(W)
            zid.append(z0)
        self._Zdiv = np.concatenate(Zs, axis=1)  # (nI*3, Σ rY)
        self._Mx, self._Mc = _fold_coefficients(self._mouth_local, len(self._mouth_verts), self._fit_mouth_sel, Ws, m)
        self._z_ident = np.concatenate(zid)
        # the global span and the identity, folded beside the coefficients: one pass gives both (correct_chunk)
        ident = np.tile(np.eye(3).ravel(), m)[:, None]
        Ms = _fold_directions(np.hstack([self._UY, ident]), self._mouth_rinv, self._mouth_local, len(self._mouth_verts))
        self._Mx_all, self._Mc_all = np.hstack([self._Mx, Ms[0]]), np.hstack([self._Mc, Ms[1]])
        self._span_ident = (ident.T @ self._UY).ravel() if self.center == "rest" else np.zeros(self._UY.shape[1])
        self._dir_fold = (None, None)

    def _fit_span(self, Y, UY):
        """Global span ``U_Y`` and RMS deformation of the mouth features: extrapolation score and suggest_frames.

        The RMS deformation is floored at the absolute rank cut, so the score stays bounded.
        """
        m = len(self.mouth_faces)
        self._UY = UY
        Yd = Y if self.center == "rest" else Y - np.tile(np.eye(3).ravel(), m)[:, None]
        self._sigma = max(float(np.sqrt(np.mean(np.sum(Yd * Yd, axis=0)))), self.atol * np.sqrt(m), 1e-12)

    def _fit_patch(self, Yp, Xp):
        """One patch's reduced regression from its (m_p,9,k) mouth and (n_p,9,k) lip features.

        Returns ``(U_Y, C_Y, U_X, θ̄, λ, E)``: the mouth basis and coefficients, the lip basis, the (rX, rY)
        reduced map, the ridge used and the leave-one-out residuals ``E`` (9 n_p, k) of the lip features.
        """
        UY, CY = thin_svd(Yp.reshape(-1, self.k), self.center, self.rtol, self.atol)
        UX, CX = thin_svd(Xp.reshape(-1, self.k), self.center, self.rtol, self.atol)
        lam = choose_ridge(CY, CX, self.ridge)
        th = solve_theta(CY, CX, lam)  # (rX, rY)
        E = UX @ loo_residuals(CY, CX, lam)  # the expected-error model (damping, expected_change)
        return UY, CY, UX, th, lam, E

    def _fit_output(self, CY, Xp):
        """The correction model of a patch: ``(U_Xc, θ̄_c, E_c, b)`` for lip corrections Xp (n_p,9,k), same mouth
        input plus a constant (the intercept ``b`` (9 n_p,), a correction present in the rest pose). Its ridge weight
        is ``ridge`` (with ``"loo"`` its own leave-one-out choice); the intercept is never penalized."""
        # a difference (centred already), small beside the motion: only round-off is cut (1e-7 of its size), so a
        # correction far smaller than the absolute cut of the motion is still reproduced on the training frames
        UX, CX = thin_svd(Xp.reshape(-1, self.k), "rest", 1e-7, 0.0)
        s = np.sqrt(3.0 * len(self.mouth_faces))  # the norm of the mouth's identity gradients (paper's uncentred y)
        CYa = np.vstack([CY, np.full((1, self.k), s)])
        lam = choose_ridge(CYa, CX, self.ridge, free=1)  # its own ridge; the intercept is never shrunk
        E = UX @ loo_residuals(CYa, CX, lam, free=1)
        th = solve_theta(CYa, CX, lam, free=1)
        return UX, th[:, :-1], E, UX @ th[:, -1] * s

    def _choose_blend(self, fits, shot):
        """``α`` of the model (1: whole, 0: correction; "auto": :func:`.model_choice.choose_blend`), and with
        ``damping`` the expected-error model of the prediction (:func:`.model_choice.error_model`)."""
        self.model_errors = {}
        if self.model == "auto" and fits[0][6] is not None:
            a, self.model_errors, em = choose_blend(self, fits, shot)
        else:
            a = 0.0 if self.model == "correction" else 1.0
            em = error_model(self, fits, shot if a == 0.0 else None)
        self._expected_model = em  # the expected error of every prediction (LipRegressor.expected_change)
        self._error_model = em if self.damping else None
        return a
