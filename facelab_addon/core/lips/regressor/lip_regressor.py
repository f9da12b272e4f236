"""Regression propagation of lip corrections: the learnt map from mouth to inner-lip gradients.

Dinev et al. 2018, "User-Guided Lip Correction for Facial Performance
Capture", §4 "Automatic Lip Correction Learning". The deformation gradients
``y`` of the trusted mouth region predict the gradients ``x`` of the inner-lip
region through a linear map ``x = θ y`` learnt from ``k`` corrected frames.
With ``Y = U_Y C_Y`` and ``X = U_X C_X`` (thin SVDs of the training matrices,
one column per frame), the reduced unknown ``θ̄ = U_Xᵀ θ U_Y`` (at most
``k × k``) solves the normal equations ``θ̄ C_Y C_Yᵀ = C_X C_Yᵀ``
(:mod:`.reduced`) and ``θ = U_X θ̄ U_Yᵀ`` is never formed. Predicted gradients become positions by
a sparse Poisson solve with the lip/mouth border vertices held at their
captured positions (Dirichlet).

Implementation notes (deviations are marked):

* The Poisson system is the usual gradient-domain least squares
  ``min_x Σ_t a_t ||∇_t x - F_t||²`` over the lip triangles (``∇_t`` the
  rest-pose gradient of the piecewise-linear map, ``a_t`` the rest area),
  i.e. a cotangent Laplacian. Its interior block is factored once, in
  ``__init__`` (cholespy, else SuperLU). Because the border moves every
  frame, prediction is linear in (mouth coefficients, border positions): a
  frame costs its mouth gradients and a few dense products (the solve folded
  into dense maps while they are small, else one shared back-substitution).
  The paper reports 5.15 s a frame; :meth:`LipRegressor.predict` evaluates the folded maps in
  float32, a block of frames per matrix product (0.55 ms CPU a frame at 105k vertices, load 9).
* ``center="rest"`` (default, an addition to the paper): the regression runs
  on gradients minus the identity, ``x - I = θ (y - I)``, so the rest pose
  maps to itself and a single training frame already gives a pose-scaled
  correction. ``center=None`` is the paper's model verbatim.
* ``patches=10`` (default, an addition to the paper): the lip region is
  covered by overlapping local patches, each predicted by its own reduced
  regression (the same thin SVDs and ``k × k`` θ̄) from the mouth triangles
  near it, and blended with a partition of unity. One global θ forces every
  part of the lips to use the same combination of training frames; local
  maps let, say, the left corner follow a smile while the lower lip follows
  the jaw, which matters when k is below the number of independent mouth
  motions. Still exact on the span of the training frames. ``patches=1``
  is the paper's single map. The patches are built in :mod:`.patches`. On the ICT benchmark
  (``benchmarks/propagate.py``, k = 10) the held-out inner-lip RMS error is
  21% of the uncorrected capture's with the defaults, 32% with one
  rest-centred map and 40% with the paper's uncentred map.
* Memory: frames are read in their own dtype (a float32 sequence is not
  upcast as a whole); only the mouth and lip vertices are gathered, a block of
  frames at a time. ``predict(captured, out=captured)``
  writes only the interior lip vertices. For :meth:`LipRegressor.extrapolation`
  and :func:`.suggest.suggest_frames` (the next frames worth correcting) on
  the same sequence, compute :meth:`LipRegressor.mouth_features` once and
  pass it as ``features=``.
* ``ridge`` (default 0, the paper): Tikhonov term ``λ ||θ̄||²`` in the
  reduced normal equations; ``ridge="loo"`` picks λ by leave-one-out
  prediction error of the lip gradients. Singular values below ``rtol``
  times the size of the training deformation, or below an RMS gradient
  change of ``atol`` per triangle, are dropped (relative and absolute rank
  tolerance), so round-off directions never enter the map.
* Guards: with ``center="rest"`` a training set whose mouth does not move
  (every frame in the rest pose to within ``atol``) is refused with a
  :class:`~facelab_addon.core.errors.FrameError`: the rest-centred model
  cannot learn anything from it. A patch whose own mouth input does not move
  in training reads the whole mouth instead. :meth:`LipRegressor.predict`
  checks every result before writing it: a non-finite result or a
  correction larger than the mouth region is refused with a
  :class:`~facelab_addon.core.errors.PredictionError` naming the frame
  indices, and ``out`` is left untouched.
"""

from __future__ import annotations

import numpy as np

from ..errors import FaceLabError, FrameError, PredictionError, UsageError
from ..geometry.gradients import rest_inverse, shape_matrices
from ..geometry.laplacian import poisson_operator
from ..geometry.linsolve import SPDFactor
from .features import (
    BLOCK as _BLOCK,
    as_frames as _as_frames,
    coordinate_major as _coordinate_major,
    gradient_features as _gradient_features,
    mouth_coefficients as _mouth_coefficients,
    StreamingPrediction as _StreamingPrediction,
)
from .guards import check_settings as _check_settings, checked_mesh as _checked_mesh
from .patches import lip_patches as _lip_patches
from .reduced import MODELS
from .regions import region_border, validate_regions
from .training import RegressorTraining as _Training

__all__ = ["LipRegressor"]



class LipRegressor(_Training, _StreamingPrediction):
    """Learn inner-lip deformation gradients from the mouth region (Dinev et al. 2018, §4).

    Parameters
    ----------
    rest_vertices : (V,3) array_like
        Rest (neutral) positions, scene units.
    faces : (F,3) int array_like
        Triangles.
    mouth_faces : (m,) int array_like
        Triangles of the trusted mouth region (vertex group ``FL_mouth``).
    lip_faces : (n,) int array_like
        Triangles of the inner-lip region (``FL_lips``), predicted.
    patches : int
        Number of local regressions. 1 is the paper's single global map from
        the whole mouth region to the whole lip region. With ``P > 1`` the lip
        region is covered by ``P`` overlapping patches (geodesic
        farthest-point centres, partition-of-unity weights) and each patch is
        predicted by its own reduced regression from the mouth triangles
        within ``input_radius`` of it, so, for example, the left corner and
        the lower lip can combine the training frames differently. Default 10.
    input_radius : float, optional
        Geodesic reach (scene units) of each patch's mouth input. Default:
        the spacing between patch centres (about 1 cm on ICT-FaceKit).
    center : {"rest", None}
        ``"rest"`` (default) regresses gradient offsets from the identity, so
        the rest pose predicts itself; ``None`` is the paper's uncentred model.
    ridge : float or "loo"
        Tikhonov weight on each reduced map (unitless, relative to the mean
        squared singular value of the training mouth matrix); ``"loo"`` picks
        it per patch by leave-one-out error. 0 (default) is the paper.
    rtol : float
        Relative singular-value cut-off for the thin SVDs (rank tolerance).
    atol : float
        Absolute cut-off: deformation directions whose RMS gradient change per
        triangle (Frobenius norm, unitless) is below ``atol`` are dropped.
        Default 1e-4 (0.01 % strain), far above round-off and float32 noise.
    backend : {"auto", "cholespy", "splu"}
        Sparse factorisation of the Poisson system.
    model : {"auto", "whole", "correction"}
        What is regressed. ``"whole"`` (the paper): the lip gradients themselves, the band's whole
        motion, expression included. ``"correction"``: corrected minus captured lip gradients, added
        to the frame's captured gradients (needs ``captured=`` in :meth:`fit`). ``"auto"`` (default):
        the blend ``α · whole + (1 - α) · correction`` whose leave-one-out error over the training
        frames, measured on the Poisson-solved interior lip positions, is smallest
        (:mod:`.model_choice`); without ``captured=`` it is the whole model.
    damping : bool
        False (default, the paper): every frame gets the predicted correction ``c``. True: ``c`` is
        scaled by ``s = |c|² / (|c|² + S)``, where ``S`` is the error the fitted model is expected to make
        on that frame by extrapolating beyond the training frames (:func:`.model_choice.expected_error`:
        the leave-one-out errors of the training frames against their distance from the others' span,
        times the frame's own squared distance from the training span), so a frame whose predicted
        correction is no larger than that stays near its capture (:func:`.model_choice.damping_weights`).
        Training frames and frames in their span (distance 0) keep the whole correction. Applies to
        positions (:meth:`predict`, :meth:`lip_corrections`, :meth:`correct_chunk`), not to
        :meth:`predict_lip_gradients`; :meth:`predict` then runs the float64 maps.

    Attributes
    ----------
    lip_vertices : (nL,) int64
        Vertices of the lip triangles.
    border_vertices : (nB,) int64
        Lip vertices also used by a non-lip triangle; kept at captured positions.
    interior_vertices : (nI,) int64
        Lip vertices that are solved for.
    k : int
        Number of training frames.
    theta_bars : list of (rX, rY) ndarrays
        The reduced maps θ̄ of the whole-motion model's patches (one for ``patches=1``).
    whole_weight : float
        ``α`` of the fitted blend: 1 is the whole-motion model, 0 the correction model.
    model_errors : dict
        With ``model="auto"``: the predicted RMS error of the interior lip vertices over the shot
        (scene units) of ``"whole"``, ``"correction"``, ``"blend"`` and the correction model's
        ``"floor"`` (:mod:`.model_choice`); empty otherwise.

    Raises
    ------
    RegionError, MeshError
        On empty/overlapping regions, a lip region with no border, degenerate
        triangles or bad shapes (messages say how to fix them).
    FaceLabError
        On settings out of range (``patches < 1``, negative ``ridge``, ``rtol`` or ``atol``).
    """

    def __init__(self, rest_vertices, faces, mouth_faces, lip_faces, *, patches: int = 10, input_radius=None,
                 center="rest", ridge=0.0, rtol=1e-4, atol=1e-4, backend="auto", model="auto", damping=False):
        R, F = _checked_mesh(rest_vertices, faces)
        if not isinstance(damping, (bool, np.bool_)):
            raise UsageError(f"damping must be True or False, got {damping!r}; use False (the paper) or True")
        self.damping = bool(damping)
        self._error_model = None
        self._expected_model = None
        if model not in MODELS:
            raise UsageError(f"model must be one of {MODELS}, got {model!r}; use 'auto' (the default)")
        self.model = model
        if center not in ("rest", None):
            raise UsageError(f"center must be 'rest' or None, got {center!r}; use 'rest' (the default)")
        _check_settings(ridge, rtol, atol, patches, input_radius)
        self.rest = R
        self.faces = F
        self.n_vertices = len(R)
        self.center = center
        self.ridge = ridge
        self.rtol = float(rtol)
        self.atol = float(atol)
        self._setup_regions(mouth_faces, lip_faces)
        self._setup_poisson(backend)
        self._setup_patches(patches, input_radius)
        self._Y = None  # (9m, k) training mouth features
        self._X = None  # (9n, k) training lip features
        self._Xc = None  # (9n, k) corrected minus captured lip features (None: captured not given)
        self.k = 0
        self.whole_weight = 1.0  # α: weight of the whole-motion model in the fitted blend
        self.model_errors = {}  # predicted RMS interior lip error of each model (scene units)

    def _setup_regions(self, mouth_faces, lip_faces):
        """Validated regions, their rest-pose inverse shape matrices and local vertex indexing."""
        R, F = self.rest, self.faces
        self.mouth_faces, self.lip_faces = validate_regions(F, mouth_faces, lip_faces, len(R), R)
        self._mouth_tris = F[self.mouth_faces]
        self._lip_tris = F[self.lip_faces]
        self._mouth_rinv = rest_inverse(R, self._mouth_tris, name="mouth region")
        self._mouth_P = np.matmul(self._mouth_rinv, self._mouth_rinv.transpose(0, 2, 1))  # ||D R^-1||² = <DᵀD, P>
        self._lip_rinv = rest_inverse(R, self._lip_tris, name="inner-lip region")
        self._mouth_verts, inv = np.unique(self._mouth_tris, return_inverse=True)
        self._mouth_local = inv.reshape(-1, 3)
        self._lip_verts_all, inv = np.unique(self._lip_tris, return_inverse=True)
        self._lip_local = inv.reshape(-1, 3)
        self._used = np.union1d(self._mouth_verts, self._lip_verts_all)  # vertices read per frame
        self.used_vertices = self._used
        self._mouth_u = np.searchsorted(self._used, self._mouth_verts)  # the same in a (T, len(used), 3) array
        # the largest plausible correction: the extent of the mouth and lip regions (scene units)
        self.mouth_size = float(np.ptp(R[self._used], axis=0).max())

    def _setup_poisson(self, backend):
        """Poisson system on the lip triangles, Dirichlet on the border: interior block factored once."""
        R, F = self.rest, self.faces
        L, D = poisson_operator(R, F, self.lip_faces)
        self.lip_vertices = self._lip_verts_all
        self.border_vertices = region_border(F, self.lip_faces, len(R))
        interior = np.setdiff1d(self.lip_vertices, self.border_vertices)
        if interior.size == 0:
            raise FaceLabError(
                "Every inner-lip vertex is on the border, so nothing would be predicted; widen 'FL_lips' "
                "(Auto Regions with a larger lip width)."
            )
        self.interior_vertices = interior
        self._iv_u = np.searchsorted(self._used, interior)
        self._bv_u = np.searchsorted(self._used, self.border_vertices)
        L = L.tocsr()
        self._L_II = L[interior][:, interior].tocsc()
        self._L_IB = L[interior][:, self.border_vertices].tocsr()
        self._D_I = D[interior].tocsr()  # (nI, 3n)
        try:
            self._factor = SPDFactor(self._L_II, backend, what="lip Poisson system")
        except Exception as e:  # pragma: no cover - validated regions make L_II SPD
            raise FaceLabError(
                f"The inner-lip Poisson system could not be factored ({e}); check for degenerate or "
                "disconnected triangles in 'FL_lips'."
            ) from e
        # divergence of the identity gradients: the constant part for center="rest"
        ident = np.broadcast_to(np.eye(3), (len(self.lip_faces), 3, 3))
        self._b_ident = self._D_I @ ident.transpose(0, 2, 1).reshape(-1, 3)  # (nI, 3)

    def _setup_patches(self, patches, input_radius):
        """Local patches of the lip region (:mod:`.patches`) and the divergence operator of each."""
        R, F = self.rest, self.faces
        self._patches, self.patch_spacing = _lip_patches(R, F, self.mouth_faces, self.lip_faces, int(patches),
                                                        input_radius)
        self.n_patches = len(self._patches)
        Dc = self._D_I.tocsc()
        self._D_patch = [Dc[:, (3 * ls[:, None] + np.arange(3)).ravel()].tocsr() for _, ls, _ in self._patches]

    # ------------------------------------------------------------------ features
    def _grad(self, frames, rinv, verts, local):
        P = frames[:, verts, :]
        return np.matmul(shape_matrices(P, local), rinv)  # (T, f, 3, 3)

    def mouth_gradients(self, frames) -> np.ndarray:
        """(T,m,3,3) deformation gradients of the mouth triangles of ``frames`` (T,V,3)."""
        A = _as_frames(frames, self.n_vertices, "frames", self._used)
        return self._grad(A, self._mouth_rinv, self._mouth_verts, self._mouth_local)

    def lip_gradients(self, frames) -> np.ndarray:
        """(T,n,3,3) deformation gradients of the inner-lip triangles of ``frames`` (T,V,3)."""
        A = _as_frames(frames, self.n_vertices, "frames", self._used)
        return self._grad(A, self._lip_rinv, self._lip_verts_all, self._lip_local)

    def _feat(self, G):
        T = G.shape[0]
        if self.center == "rest":
            G = G - np.eye(3)
        return G.reshape(T, -1)

    def _mouth_feat(self, frames, used_only=False):
        """(T, 9m) mouth features of validated frames (any float dtype; computed in float64)."""
        verts = self._mouth_u if used_only else self._mouth_verts
        return _gradient_features(frames, verts, self._mouth_local, self._mouth_rinv, self.center == "rest")

    def _frames(self, captured, what, used_only):
        """Validated frames, full (T,V,3) or, with ``used_only``, (T, len(used_vertices), 3)."""
        if used_only:
            return _as_frames(captured, len(self._used), what + " (used vertices only)")
        return _as_frames(captured, self.n_vertices, what, self._used)

    def mouth_features(self, captured, *, used_only: bool = False) -> np.ndarray:
        """Whole-mouth feature vectors ``y`` of frames, one row per frame.

        The deformation gradients of the mouth triangles (order of
        ``mouth_faces``, each 3×3 flattened row-major), minus the identity
        when ``center="rest"``. They are what :meth:`extrapolation` and
        :func:`suggest_frames` compare with the training span: compute them
        once and pass them to both as ``features=`` so the sequence is read
        once. Needs no fit.

        Parameters
        ----------
        captured : (T,V,3) or (V,3) array_like
            Frames, scene units. float32 frames are read in place (only the
            mouth vertices are converted to float64, a block at a time).
        used_only : bool
            ``captured`` holds only the :attr:`used_vertices` (T, len(used_vertices), 3),
            e.g. a chunk read from a cache for just those vertices.

        Returns
        -------
        (T, 9m) float64 ndarray
            Unitless; ``m = len(mouth_faces)``. 72·m bytes a frame (about
            0.1 MB on ICT-FaceKit, 100 MB for 1000 frames).

        Raises
        ------
        FaceLabError
            If no frames are given, or they have a different topology or NaN
            coordinates in the mouth or lip region (``MeshError``).
        """
        A = self._frames(captured, "captured frames", used_only)
        out = np.empty((len(A), 9 * len(self.mouth_faces)))
        for s in range(0, len(A), _BLOCK):
            out[s : s + _BLOCK] = self._mouth_feat(A[s : s + _BLOCK], used_only)
        return out

    def _check_features(self, features):
        Y = np.asarray(features)
        d = 9 * len(self.mouth_faces)
        if Y.ndim != 2 or Y.shape[1] != d:
            raise FaceLabError(
                f"features have shape {Y.shape}, expected (T, {d}) (9 per mouth triangle); compute them with "
                "mouth_features() of this regressor."
            )
        if len(Y) == 0:
            raise FaceLabError("No features given (0 frames); pass at least one frame.")
        if not np.issubdtype(Y.dtype, np.floating):
            raise FaceLabError(f"features have dtype {Y.dtype}, expected floats; compute them with mouth_features().")
        bad = np.flatnonzero(~np.isfinite(Y).all(axis=1))
        if bad.size:
            raise FrameError("The features of {frames} contain NaN or infinite values; recompute them with "
                             "mouth_features() from frames without NaN coordinates.", bad[:20])
        return Y

    def _require_fit(self):
        if self._Y is None:
            raise FaceLabError("The lip regressor has no training frames; call fit() with corrected frames first.")

    # ------------------------------------------------------------------ prediction
    def _coefficients(self, frames, used_only=False):
        """Reduced coefficients ``z_p = U_Y,pᵀ y_p`` of all patches, (T, Σ rY), for validated frames.

        ``y = vec(D_d D_r^-1)`` is linear in the shape matrix ``D_d``, so
        ``U_Yᵀ y = Σ D_d[i,k] W[i,k]`` with ``W`` folded at fit time; the edge columns of ``D_d``
        are linear in the positions, so a frame costs one product with its mouth vertices, the
        phantom columns of its mouth triangles and three more products
        (:func:`.features._fold_coefficients`).
        """
        verts = self._mouth_u if used_only else self._mouth_verts
        if getattr(self, "_cm", (None,))[0] is not self._Mx:
            nv, m = len(self._mouth_verts), len(self.mouth_faces)
            self._cm = (self._Mx, _coordinate_major(self._Mx, nv), _coordinate_major(self._Mc, m))
        return _mouth_coefficients(frames, verts, self._mouth_local, *self._cm[1:]) - self._z_ident

    def _interior(self, A, used_only=False, z=None, r2=None):
        """``(xi, xc)``: predicted and captured interior lip positions (t, nI, 3) float64 of validated frames.

        With ``damping`` the correction ``xi - xc`` is scaled per frame (``r2`` (t,): the frames' squared
        distances from the training span, computed from ``A`` when not given).
        """
        xi, xc = self._undamped_interior(A, used_only, z)
        if self._error_model is not None:
            if r2 is None:
                r2 = self._residual_norms(self._mouth_feat(A, used_only)) ** 2
            xi = self._damp(xi, xc, r2)
        return xi, xc

    def damping_weights(self, captured=None, *, features=None) -> np.ndarray:
        """(T,) the factor each frame's predicted correction is scaled by (1 everywhere without ``damping``).

        Parameters
        ----------
        captured, features
            As :meth:`extrapolation`.

        Returns
        -------
        (T,) float64 ndarray
            In (0, 1]; see ``damping`` in the class description.
        """
        self._require_fit()
        if features is None:
            A = _as_frames(captured, self.n_vertices, "captured frames", self._used)
            Y = self.mouth_features(A)
        else:
            A = None
            Y = self._check_features(features)
        if self._error_model is None:
            return np.ones(len(Y))
        if A is None:
            raise UsageError("damping_weights() needs the captured frames (the predicted correction's size); pass "
                             "captured=")
        xi, xc = self._undamped_interior(A, False)
        return self._damp_weights(xi - xc, self._residual_norms(Y) ** 2)

    def _damp_weights(self, c, r2):
        from .model_choice import damping_weights, expected_error

        S = expected_error(self._error_model, self.whole_weight, r2)
        return damping_weights(np.einsum("tij,tij->t", c, c), S)

    def _damp(self, xi, xc, r2):
        """``xc + s (xi - xc)`` with the damping weights ``s`` of each frame (t,)."""
        c = xi - xc
        return xc + self._damp_weights(c, r2)[:, None, None] * c

    def _undamped_interior(self, A, used_only=False, z=None):
        """:meth:`_interior` without damping."""
        iv, bv = (self._iv_u, self._bv_u) if used_only else (self.interior_vertices, self.border_vertices)
        nI, t = len(iv), len(A)
        z = self._coefficients(A, used_only) if z is None else z
        xb = np.asarray(A[:, bv, :], dtype=np.float64).transpose(1, 0, 2).reshape(len(bv), 3 * t)
        # the blend α·whole + (1-α)·correction: x_I = K z + α (x_0 - H x_B) + (1 - α) x_captured,I
        a = self.whole_weight
        xc = np.asarray(A[:, iv, :], dtype=np.float64)
        dense = self._dense_solution()
        if dense is not None:  # two dense products instead of a sparse solve
            K, H, x0 = dense
            xi = (K @ z.T).reshape(nI, 3, t).transpose(0, 2, 1).reshape(nI, 3 * t)
            xi -= (a * H) @ xb if a != 1.0 else H @ xb
            xi = xi.reshape(nI, t, 3).transpose(1, 0, 2)
            if x0 is not None:
                xi += a * x0[None]
        else:
            rhs = (self._Zdiv @ z.T).reshape(nI, 3, t).transpose(0, 2, 1)  # (nI, t, 3)
            if self.center == "rest":
                rhs = rhs + a * self._b_ident[:, None, :]
            rhs = rhs.reshape(nI, 3 * t) - a * (self._L_IB @ xb)
            xi = self._factor.solve(rhs).reshape(nI, t, 3).transpose(1, 0, 2)
        if a != 1.0:
            xi += (1.0 - a) * (xc + self._x_b[None])
        return xi, xc

    def _residual_norms(self, Y):
        """(T,) norms of mouth features ``Y`` (T, 9m) outside the global training span."""
        r = Y - (Y @ self._UY) @ self._UY.T
        return np.sqrt(np.sum(r * r, axis=1))

    def predict_lip_gradients(self, captured) -> np.ndarray:
        """Predicted inner-lip deformation gradients ``x = θ y`` (blended over patches and models).

        Parameters
        ----------
        captured : (T,V,3) or (V,3) array_like
            Captured frames, scene units.

        Returns
        -------
        (T,n,3,3) float64 ndarray
            One unitless 3×3 gradient per lip triangle (order of ``lip_faces``).
        """
        self._require_fit()
        A = _as_frames(captured, self.n_vertices, "captured frames", self._used)
        T = len(A)
        z = self._coefficients(A)
        x = np.zeros((T, len(self.lip_faces), 9))
        o = 0
        for (_, lip_sel, w), (UX, th, _) in zip(self._patches, self._pfit):
            r = th.shape[1]
            xp = (z[:, o : o + r] @ th.T) @ UX.T  # (T, 9 n_p)
            x[:, lip_sel] += xp.reshape(T, len(lip_sel), 9) * w[None, :, None]
            o += r
        x = x.reshape(T, -1, 3, 3)
        a = self.whole_weight
        if self.center == "rest":
            x = x + a * np.eye(3)
        if a != 1.0:  # the correction model adds the captured gradients
            x = x + (1.0 - a) * (self._grad(A, self._lip_rinv, self._lip_verts_all, self._lip_local)
                                 + self._B.reshape(-1, 3, 3))
        bad = np.flatnonzero(~np.isfinite(x).reshape(T, -1).all(axis=1))
        if bad.size:
            raise PredictionError("The predicted lip gradients of {frames} are not finite; check those frames "
                                  "for extreme mouth shapes and retrain with frames like them.", bad[:20])
        return x

    def predict(self, captured, *, out=None, chunk: int = 256) -> np.ndarray:
        """Correct the inner lips of captured frames.

        Parameters
        ----------
        captured : (T,V,3) or (V,3) array_like
            Captured frames, scene units, same topology as the rest mesh.
            float32 or float64 arrays are read without a copy; only the
            mouth and lip vertices are read, a block of frames at a time.
            The fitted maps run in float32 on the changes from the rest pose
            (formed in float64, so float32 and float64 frames of the same
            positions give the same result): rounding moves a vertex by about
            1e-8 of the mouth's size (at most 3e-5 mm on ICT-FaceKit), far below
            the 0.01 mm storage tolerance. Large lip regions, whose dense maps
            would not fit, are solved in float64 (sparse back-substitution).
        out : (T,V,3) ndarray, optional
            Where to write the result, float32 or float64 (the shape of the
            frames; a (V,3) array for a single (V,3) frame). It may be
            ``captured`` itself, for in-place correction of long sequences:
            then only the interior lip vertices are written (each block's
            captured interior is read first: the correction model adds to it). Another array first receives a copy of
            ``captured``. Default: a new float64 array. In place, each block
            is written as soon as it passes the checks, and the captured
            interior lip positions it replaced are kept (the frames' dtype:
            12 bytes per interior lip vertex and frame for float32) until
            every frame has passed; a refusal or error puts them back. The
            working memory is otherwise a few tens of MB (the float32 maps
            and one block of 128 frames).
        chunk : int
            Frames per batch (working memory ~ chunk × lip size); at most
            128 on the float32 path.

        Returns
        -------
        (T,V,3) ndarray
            ``out`` (float64 when not given): captured positions everywhere
            except the interior lip vertices, which are the Poisson
            reconstruction from ``θ y`` with the border vertices held at
            their captured positions (scene units). A single (V,3) frame
            gives a (1,V,3) result (``out`` itself when given).

        Raises
        ------
        FaceLabError
            If the regressor was not fitted, the frames have a different
            topology or NaN coordinates in the mouth or lip region, or
            ``out`` is not a writeable float32/float64 array of their shape.
        PredictionError
            If a frame's result is not finite, or moves a lip vertex further
            than the size of the mouth region (:attr:`mouth_size`); it names
            the frame indices and ``out`` is left unchanged.
        """
        return self._predict_frames(captured, out, chunk)

    def extrapolation(self, captured=None, *, features=None) -> np.ndarray:
        """How far each frame's mouth gradients lie outside the span of the training frames.

        ``e = ||y - U_Y U_Yᵀ y|| / σ`` where ``y`` is the frame's whole-mouth
        feature vector (gradients minus the identity when ``center="rest"``),
        ``U_Y`` an orthonormal basis of the training features, and ``σ`` the
        RMS deformation ``||y_i - I||`` of the training mouths. It is 0 on
        training frames and their linear combinations (where the regression
        is exact), scale-free (gradients are unitless and do not change with
        the scene unit), and about 1 when a frame departs from the training
        span as much as a typical training pose departs from rest.

        Parameters
        ----------
        captured : (T,V,3) or (V,3) array_like, optional
            Frames, scene units (read a block at a time, never copied whole).
        features : (T, 9m) array_like, optional
            Instead of ``captured``: their :meth:`mouth_features`, for
            example to share them with :func:`suggest_frames`. Not modified.

        Returns
        -------
        (T,) float64 ndarray
        """
        self._require_fit()
        if (captured is None) == (features is None):
            raise UsageError("extrapolation() takes captured frames or their features, not both or neither; pass one")
        if features is None:
            A = _as_frames(captured, self.n_vertices, "captured frames", self._used)
            block = lambda s: self._mouth_feat(A[s : s + _BLOCK])  # noqa: E731
        else:
            A = self._check_features(features)
            block = lambda s: A[s : s + _BLOCK]  # noqa: E731
        out = np.empty(len(A))
        for s in range(0, len(A), _BLOCK):
            out[s : s + _BLOCK] = self._residual_norms(block(s))
        return out / self._sigma

    def expected_change(self, corrections, extrapolation) -> np.ndarray:
        """(t,) how much a frame's interior lip error is expected to change with its predicted correction, RMS
        over the interior lip vertices, scene units (positive: expected worse than the capture).

        The fitted error model (:func:`.model_choice.error_model`) gives the error ``S`` the prediction makes
        on a frame: its part that grows with the frame's distance from the training span, plus the correction
        model's floor (weighted as in the blend). A predicted correction ``c = c* + n`` of the true one ``c*``
        with an independent error of size ``S`` has ``|c*|² ≈ |c|² - S``; applying ``s c`` (``s`` the damping
        weight, 1 without ``damping``) leaves ``(1 - s)² |c*|² + s² S``, against ``|c*|²`` for the capture.

        Parameters
        ----------
        corrections : (t, nI, 3) float array_like
            The corrections :meth:`correct_chunk` returned for the frames (damped when ``damping``).
        extrapolation : (t,) float array_like
            Their extrapolation scores (:meth:`correct_chunk`, :meth:`extrapolation`).

        Returns
        -------
        (t,) float64 ndarray
        """
        from .model_choice import expected_error

        self._require_fit()
        c = np.asarray(corrections, dtype=np.float64)
        cd2 = np.einsum("tij,tij->t", c, c)
        r2 = (np.asarray(extrapolation, dtype=np.float64) * self._sigma) ** 2
        em, a = self._expected_model, self.whole_weight
        S = expected_error(em, a, r2) if em else np.zeros_like(r2)
        miss = S + ((1.0 - a) ** 2 * em["floor"] if em else 0.0)  # with the correction model's floor: every frame
        if self.damping:  # undo the damping: |s c|² = c2³ / (c2 + S)² is increasing in c2 (bisection, log scale)
            lo, hi = np.maximum(cd2, 1e-300), np.maximum(cd2 + 2 * S + np.sqrt(cd2 * S) * 4, 1e-300)
            for _ in range(60):
                mid = np.sqrt(lo * hi)
                big = mid ** 3 / np.maximum(mid + S, 1e-300) ** 2 > cd2
                hi, lo = np.where(big, mid, hi), np.where(big, lo, mid)
            c2 = np.sqrt(lo * hi)
            s = np.divide(c2, c2 + S, out=np.ones_like(c2), where=c2 + S > 0)
        else:
            c2, s = cd2, np.ones_like(cd2)
        C = np.maximum(c2 - miss, 0.0)
        after = (1 - s) ** 2 * C + s * s * miss
        nI = max(len(self.interior_vertices), 1)
        return np.sqrt(after / nI) - np.sqrt(C / nI)

    def training_span(self) -> np.ndarray:
        """(9m, r) orthonormal basis ``U_Y`` of the training mouth features (whole mouth region)."""
        self._require_fit()
        return self._UY
