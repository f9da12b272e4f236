"""The lip regressor: the learnt map from mouth to inner-lip deformation gradients, as one object.

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

:class:`LipRegressor` composes the package's modules: :func:`.operators.lip_operators` builds the
fixed operators once (regions, Poisson factor, patches), :func:`.training.train` turns training
features into a :class:`.state.TrainedModel`, and the functions of :mod:`.prediction` evaluate it.
Its state is those plain objects (:attr:`LipRegressor.operators`, :attr:`LipRegressor.trained`).

Implementation notes (deviations are marked):

* The Poisson system is the usual gradient-domain least squares
  ``min_x Σ_t a_t ||∇_t x - F_t||²`` over the lip triangles (``∇_t`` the
  rest-pose gradient of the piecewise-linear map, ``a_t`` the rest area),
  i.e. a cotangent Laplacian. Its interior block is factored once, at
  construction (cholespy, else SuperLU). Because the border moves every
  frame, prediction is linear in (mouth coefficients, border positions): a
  frame costs its mouth gradients and a few dense products (the solve folded
  into dense maps while they are small, else one shared back-substitution).
  :meth:`LipRegressor.predict` evaluates the folded maps in float32, a block of frames per
  matrix product (:mod:`.predict32`).
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
  is the paper's single map. The patches are built in :mod:`.patches`; how the
  variants compare: docs/benchmarks.md (``benchmarks/propagate.py``).
* Memory: frames are read in their own dtype (a float32 sequence is not
  upcast as a whole); only the mouth and lip vertices are gathered, a block of
  frames at a time. ``predict(captured, out=captured)``
  writes only the interior lip vertices. For :meth:`LipRegressor.extrapolation`
  and :func:`..suggest.suggest_frames` (the next frames worth correcting) on
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

from ...errors import FaceLabError, UsageError
from . import prediction
from .features import BLOCK, as_frames, frames_of, gradients
from .guards import check_features, check_settings, checked_mesh
from .operators import lip_operators
from .reduced import MODELS
from .state import LipOperators, Settings, TrainedModel
from .training import shot_inputs, train, training_features

__all__ = ["LipRegressor"]


class LipRegressor:
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
    settings : Settings
        The checked keyword arguments (:class:`.state.Settings`).
    operators : LipOperators
        Regions, Poisson system and patches (:class:`.state.LipOperators`), fixed at construction.
    trained : TrainedModel or None
        The current fit (:class:`.state.TrainedModel`); None before :meth:`fit`.

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
        R, F = checked_mesh(rest_vertices, faces)
        if not isinstance(damping, (bool, np.bool_)):
            raise UsageError(f"damping must be True or False, got {damping!r}; use False (the paper) or True")
        if model not in MODELS:
            raise UsageError(f"model must be one of {MODELS}, got {model!r}; use 'auto' (the default)")
        if center not in ("rest", None):
            raise UsageError(f"center must be 'rest' or None, got {center!r}; use 'rest' (the default)")
        check_settings(ridge, rtol, atol, patches, input_radius)
        self.settings = Settings(center=center, ridge=ridge, rtol=float(rtol), atol=float(atol), model=model,
                                 damping=bool(damping))
        self.operators: LipOperators = lip_operators(R, F, mouth_faces, lip_faces, center=center, patches=patches,
                                                     input_radius=input_radius, backend=backend)
        self.trained: TrainedModel | None = None
        ops = self.operators
        self.rest, self.faces, self.n_vertices = ops.rest, ops.faces, ops.n_vertices
        self.mouth_faces, self.lip_faces = ops.mouth_faces, ops.lip_faces
        self.lip_vertices, self.border_vertices = ops.lip_verts, ops.border_vertices
        self.interior_vertices, self.used_vertices = ops.interior_vertices, ops.used
        self.mouth_size, self.patch_spacing, self.n_patches = ops.mouth_size, ops.patch_spacing, len(ops.patches)

    # ------------------------------------------------------------------ settings and fit, as attributes
    @property
    def center(self):
        """Feature centring: ``"rest"`` or None (:class:`.state.Settings`)."""
        return self.settings.center

    @property
    def ridge(self):
        """Ridge weight of each reduced map: a float or ``"loo"``."""
        return self.settings.ridge

    @property
    def rtol(self) -> float:
        """Relative singular-value cut-off of the thin SVDs."""
        return self.settings.rtol

    @property
    def atol(self) -> float:
        """Absolute cut-off: RMS gradient change per triangle (unitless)."""
        return self.settings.atol

    @property
    def model(self) -> str:
        """What is regressed: ``"auto"``, ``"whole"`` or ``"correction"``."""
        return self.settings.model

    @property
    def damping(self) -> bool:
        """Whether each frame's predicted correction is scaled by its expected error."""
        return self.settings.damping

    @property
    def k(self) -> int:
        """Number of training frames (0 before :meth:`fit`)."""
        return 0 if self.trained is None else self.trained.data.k

    @property
    def whole_weight(self) -> float:
        """``α`` of the fitted blend: 1 is the whole-motion model (also before :meth:`fit`)."""
        return 1.0 if self.trained is None else self.trained.whole_weight

    @property
    def model_errors(self) -> dict:
        """Predicted RMS interior lip error of each model, scene units (``model="auto"``; else empty)."""
        return {} if self.trained is None else self.trained.model_errors

    @property
    def theta_bars(self) -> list:
        """The whole-motion model's reduced maps θ̄, (rX, rY) each, one per patch."""
        return self._fitted().theta_bars

    @property
    def ridges_used(self) -> list:
        """The ridge weight each patch's map was fitted with."""
        return self._fitted().ridges_used

    @property
    def is_fitted(self) -> bool:
        """Whether :meth:`fit` has given the regressor training frames."""
        return self.trained is not None

    @property
    def feature_scale(self) -> float:
        """RMS norm of the training frames' whole-mouth features (the σ of :meth:`extrapolation`'s score)."""
        return self._fitted().data.sigma

    def _fitted(self) -> TrainedModel:
        if self.trained is None:
            raise FaceLabError("The lip regressor has no training frames; call fit() with corrected frames first.")
        return self.trained

    def require_fit(self) -> None:
        """Raise :class:`FaceLabError` (naming the fix) when the regressor has no training frames yet."""
        self._fitted()

    def check_features(self, features) -> np.ndarray:
        """(T, 9m) mouth features checked against this regressor's mouth region (m triangles)."""
        return check_features(features, len(self.mouth_faces))

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
        ops, st = self.operators, self.settings
        y, x, xc = training_features(ops, st, corrected, captured)
        self.trained = train(ops, st, y.copy(), x.copy(), xc, shot_inputs(ops, st, shot, used_only, xc))
        return self

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
        ops, st = self.operators, self.settings
        y, x, xc = training_features(ops, st, corrected, captured)
        sh = shot_inputs(ops, st, shot, used_only, xc)
        if self.trained is None:
            self.trained = train(ops, st, y.copy(), x.copy(), xc, sh)
        else:
            old = self.trained.data
            both = xc is not None and old.Xc is not None
            self.trained = train(ops, st, np.hstack([old.Y, y]), np.hstack([old.X, x]),
                                 np.hstack([old.Xc, xc]) if both else None, sh)
        return self

    # ------------------------------------------------------------------ features
    def mouth_gradients(self, frames) -> np.ndarray:
        """(T,m,3,3) deformation gradients of the mouth triangles of ``frames`` (T,V,3)."""
        ops = self.operators
        A = as_frames(frames, self.n_vertices, "frames", ops.used)
        return gradients(A, ops.mouth_rinv, ops.mouth_verts, ops.mouth_local)

    def lip_gradients(self, frames) -> np.ndarray:
        """(T,n,3,3) deformation gradients of the inner-lip triangles of ``frames`` (T,V,3)."""
        ops = self.operators
        A = as_frames(frames, self.n_vertices, "frames", ops.used)
        return gradients(A, ops.lip_rinv, ops.lip_verts, ops.lip_local)

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
        A = frames_of(self.operators, captured, "captured frames", used_only)
        out = np.empty((len(A), 9 * len(self.mouth_faces)))
        for s in range(0, len(A), BLOCK):
            out[s : s + BLOCK] = prediction.mouth_rows(self.operators, A[s : s + BLOCK], used_only)
        return out

    # ------------------------------------------------------------------ prediction
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
            1e-8 of the mouth's size, far below the 0.01 mm storage
            tolerance. Large lip regions, whose dense maps
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
        trained = self._fitted()
        return prediction.predict_frames(self.operators, trained, captured, out, chunk)

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
        trained = self._fitted()
        A = as_frames(captured, self.n_vertices, "captured frames", self.operators.used)
        return prediction.predict_lip_gradients(self.operators, trained, A)

    def lip_corrections(self, captured, *, used_only: bool = False, first: int = 0) -> np.ndarray:
        """The correction of the interior lip vertices, predicted minus captured, frame by frame.

        What :meth:`predict` adds to ``captured[:, interior_vertices]``, without writing a
        (T,V,3) result: the streaming form for long shots (the caller feeds chunks).

        Parameters
        ----------
        captured : (T,V,3) array_like, or (T, len(used_vertices), 3) with ``used_only``
            Captured frames (or only their :attr:`used_vertices`), scene units, float32 or float64.
        used_only : bool
            ``captured`` holds only the used vertices, in the order of :attr:`used_vertices`.
        first : int
            Index of the chunk's first frame in the shot, for the frame indices of errors.

        Returns
        -------
        (T, nI, 3) float64 ndarray
            Offsets of :attr:`interior_vertices`, scene units; the border vertices' are zero.

        Raises
        ------
        FaceLabError, PredictionError
            As :meth:`predict`.
        """
        trained = self._fitted()
        return prediction.lip_corrections(self.operators, trained, captured, used_only, first)

    def correct_chunk(self, captured, *, used_only: bool = False, first: int = 0):
        """:meth:`lip_corrections` and the mouth's distance from the training span, in one pass over the mouth.

        Returns ``(corrections (t,nI,3), extrapolation (t,), feature_sq (t,))``: the score of
        :meth:`extrapolation` (from ``||y||² - ||U_Yᵀ y||²``, never forming ``y``) and ``||y||²``
        (for :class:`.suggest.SuggestScreen`). Arguments as :meth:`lip_corrections`.
        """
        trained = self._fitted()
        return prediction.correct_chunk(self.operators, trained, captured, used_only, first)

    def mouth_projections(self, captured, directions, *, used_only: bool = False):
        """``(Aᵀ y (t,d), ||y||² (t,))`` of frames' mouth features ``y`` on directions ``A`` (9m, d), never forming ``y``."""
        trained = self._fitted()
        return prediction.mouth_projections(self.operators, trained, captured, directions, used_only)

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
        trained, ops = self._fitted(), self.operators
        if (captured is None) == (features is None):
            raise UsageError("extrapolation() takes captured frames or their features, not both or neither; pass one")
        if features is None:
            A = as_frames(captured, self.n_vertices, "captured frames", ops.used)
            block = lambda s: prediction.mouth_rows(ops, A[s : s + BLOCK])  # noqa: E731
        else:
            A = self.check_features(features)
            block = lambda s: A[s : s + BLOCK]  # noqa: E731
        out = np.empty(len(A))
        for s in range(0, len(A), BLOCK):
            out[s : s + BLOCK] = prediction.residual_norms(trained, block(s))
        return out / trained.data.sigma

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
        trained, ops = self._fitted(), self.operators
        if features is None:
            A = as_frames(captured, self.n_vertices, "captured frames", ops.used)
            Y = self.mouth_features(A)
        else:
            A = None
            Y = self.check_features(features)
        if trained.error_model is None:
            return np.ones(len(Y))
        if A is None:
            raise UsageError("damping_weights() needs the captured frames (the predicted correction's size); pass "
                             "captured=")
        xi, xc = prediction.undamped_interior(ops, trained, A, False)
        return prediction.frame_damping(trained, xi - xc, prediction.residual_norms(trained, Y) ** 2)

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
        trained = self._fitted()
        return prediction.expected_change(self.operators, trained, self.damping, corrections, extrapolation)

    def training_span(self) -> np.ndarray:
        """(9m, r) orthonormal basis ``U_Y`` of the training mouth features (whole mouth region)."""
        return self._fitted().data.UY
