"""Correcting a whole shot with a fitted lip regressor, a chunk of frames at a time (Dinev et al. 2018 §4).

:class:`ShotCorrector` owns the per-chunk work of Propagate once the regressor is fitted: it
predicts the interior-lip correction of each chunk of captured frames
(``LipRegressor.correct_chunk``), scores how far each frame's mouth lies outside the training
poses, estimates how each frame's error is expected to change (``LipRegressor.expected_change``),
keeps the artist's own correction on the training frames (zero correction there), gives every
split-seam twin its representative's correction, and compresses the key offsets into a few shapes
(:class:`~facelab_addon.core.lips.regressor.reduced.StreamingBasis`). It also decides how the correction can
be stored (:class:`~facelab_addon.core.geometry.compress.StorageOutcome`): as keys, or, over a capture
cache whose key offsets need more shapes than keys hold, as a patch point cache of the corrected
vertices. Reading frames and writing keys or caches is the caller's (``pipeline.propagate``).

All positions and corrections are object-local scene units. No bpy in this module.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import FaceLabError, TooManyShapesError
from ..geometry.compress import StorageOutcome
from .regressor.reduced import StreamingBasis
from .suggest import SuggestScreen

__all__ = ["ShotCorrector", "ShotCorrection", "key_shapes_over_cache", "expected_worse"]


def key_shapes_over_cache(budget: int) -> int:
    """Most greedy shapes the key offsets over a capture cache may take before the correction is stored as a
    patch cache instead (4x the key ``budget``, at least 64: the greedy basis overshoots the final one)."""
    return max(64, 4 * int(budget))


def expected_worse(change, threshold: float) -> np.ndarray:
    """Frames expected to be left worse than captured, the worst first.

    Parameters
    ----------
    change : (T,) float array_like
        Expected change of each frame's interior-lip error (``ShotCorrection.expected_change``), scene units.
    threshold : float
        Smallest expected increase reported, scene units.

    Returns
    -------
    (k,) int64 ndarray
        Positions in the shot of the frames whose ``change`` exceeds ``threshold``, largest change first
        (ties in shot order).
    """
    change = np.asarray(change, dtype=np.float64)
    flagged = np.flatnonzero(change > threshold)
    return flagged[np.argsort(-change[flagged], kind="stable")]


@dataclass
class ShotCorrection:
    """The correction of a whole shot (:meth:`ShotCorrector.finish`).

    Attributes
    ----------
    outcome : StorageOutcome
        ``KEYS``: ``basis`` and ``weights`` hold the key offsets; ``PATCH_CACHE``: they would need more shapes
        than keys hold, so the shown corrections (:meth:`ShotCorrector.add_chunk`) are to be stored as a point
        cache of the corrected vertices, and ``basis``/``weights`` are None.
    basis : (r, n, 3) float64 ndarray or None
        Key-offset shapes of the ``n`` written vertices, scene units.
    weights : (T, r) float64 ndarray or None
        The value of each shape on each frame.
    extrapolation : (T,) float64 ndarray
        How far each frame's mouth lies outside the training poses (unitless; 0 on training frames).
    expected_change : (T,) float64 ndarray
        Expected change of each frame's interior-lip error, RMS, scene units (positive: worse than the
        capture; 0 on training frames).
    """

    outcome: StorageOutcome
    basis: np.ndarray | None
    weights: np.ndarray | None
    extrapolation: np.ndarray
    expected_change: np.ndarray


class ShotCorrector:
    """Correct a shot chunk by chunk with a fitted regressor; the storage outcome and per-frame scores at the end.

    Feed the shot's frames in order with :meth:`add_chunk` (any chunk sizes: the result does not depend
    on them), then call :meth:`finish`. Memory: the key-offset shapes and weights, plus two floats a frame.

    Parameters
    ----------
    regressor : LipRegressor
        Fitted; chunks hold its ``used_vertices`` only (``used_only=True``).
    training : (T,) bool array_like
        True on the shot's training frames: their correction is zero (they keep the artist's own), as are
        their extrapolation score and expected change.
    tol : float
        Largest error of any key offset of any frame in the compressed shapes, scene units (> 0).
    take : (m,) int array_like, optional
        The written vertices: the column of the ``nI`` interior-lip corrections each takes (a split-seam
        twin takes its representative's). Default: the interior lip vertices themselves.
    max_key_shapes : int
        Most greedy shapes the key offsets may take.
    patch_cache : bool
        Past ``max_key_shapes``: True (over a capture cache) switches the outcome to ``PATCH_CACHE`` and stops
        compressing; False raises.
    suggest : bool
        Screen the frames for :meth:`suggest` (``SuggestScreen``) as they come.

    Raises
    ------
    FaceLabError
        ``tol`` not a positive distance.
    """

    def __init__(self, regressor, training, tol: float, *, take=None, max_key_shapes: int = 1024,
                 patch_cache: bool = False, suggest: bool = False):
        self.regressor = regressor
        self.training = np.asarray(training, dtype=bool).reshape(-1)
        T = len(self.training)
        self.take = None if take is None else np.asarray(take, dtype=np.int64)
        n = len(regressor.interior_vertices) if self.take is None else len(self.take)
        self.patch_cache = bool(patch_cache)
        self.outcome = StorageOutcome.KEYS
        self._basis = StreamingBasis(n, tol, max_rank=int(max_key_shapes))
        self._screen = SuggestScreen(regressor, T, exclude=np.flatnonzero(self.training)) if suggest else None
        self._score, self._change = np.empty(T), np.empty(T)
        self.done = 0

    @property
    def wants_key_offsets(self) -> bool:
        """Whether the key offsets of the next chunk are still compressed (the outcome is still ``KEYS``)."""
        return self.outcome is StorageOutcome.KEYS

    def add_chunk(self, used, to_key=None) -> np.ndarray:
        """Correct the next frames of the shot.

        Parameters
        ----------
        used : (t, nU, 3) float array_like
            The captured positions of the regressor's ``used_vertices`` on the next ``t`` frames.
        to_key : callable, optional
            Maps the shown correction (t, m, 3) to the key offsets showing it (over a capture cache, whose
            surface carries the keys); called only while :attr:`wants_key_offsets`. Default: the identity.

        Returns
        -------
        (t, m, 3) float64 ndarray
            The correction shown on the written vertices (``take``), scene units; zero on training frames.

        Raises
        ------
        FrameError
            A frame with NaN coordinates, named by its position in the shot.
        FaceLabError
            More chunks than ``training`` has frames; past ``max_key_shapes`` without ``patch_cache``
            (:class:`~facelab_addon.core.errors.TooManyShapesError`).
        """
        i = self.done
        j = i + len(used)
        if j > len(self.training):
            raise FaceLabError(f"The shot has {len(self.training)} frames; {j} were added. Add each frame once.")
        reg = self.regressor
        corr, score, feature_sq = reg.correct_chunk(used, used_only=True, first=i)
        if self._screen is not None:
            self._screen.add_scores(i, feature_sq, score)
        self._score[i:j] = score
        self._change[i:j] = reg.expected_change(corr, score)
        corr[self.training[i:j]] = 0.0  # training frames keep the artist's own correction
        if self.take is not None:  # every twin moves with its representative: the seams stay closed
            corr = corr[:, self.take]
        if self.wants_key_offsets:
            self._add_key_offsets(corr if to_key is None else to_key(corr))
        self.done = j
        return corr

    def _add_key_offsets(self, offsets) -> None:
        try:
            self._basis.add(offsets)
        except TooManyShapesError:
            if not self.patch_cache:
                raise
            self.outcome, self._basis = StorageOutcome.PATCH_CACHE, None

    def finish(self) -> ShotCorrection:
        """The key-offset shapes (``KEYS``) and the per-frame scores, once every frame was added.

        Raises
        ------
        FaceLabError
            Fewer frames added than the shot has.
        """
        T = len(self.training)
        if self.done != T:
            raise FaceLabError(f"Only {self.done} of the shot's {T} frames were corrected; add every frame.")
        basis = weights = None
        if self.outcome is StorageOutcome.KEYS:
            basis, weights = self._basis.finish()
        score, change = self._score.copy(), self._change.copy()
        score[self.training] = 0.0
        change[self.training] = 0.0
        return ShotCorrection(self.outcome, basis, weights, score, change)

    def suggest(self, count: int, read_used) -> list:
        """Positions of the ``count`` frames to correct next, best first (``SuggestScreen.select`` among the
        screened candidates, the frames farthest from the training span).

        Parameters
        ----------
        count : int
        read_used : callable
            ``read_used(idx)``: the captured positions (k, nU, 3) of the used vertices on shot positions ``idx``.
        """
        if self._screen is None:
            raise FaceLabError("This corrector screens no frames; create it with suggest=True.")

        def features_of(idx):
            return self.regressor.mouth_features(read_used(idx), used_only=True)

        return self._screen.select(count, features_of, exact=False)[0]
