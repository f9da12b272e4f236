"""Which frames to correct next: greedy extreme-pose selection for the lip regression.

Dinev et al. 2018, "User-Guided Lip Correction for Facial Performance
Capture", §6.2: the regression (:mod:`.propagate`) should be trained on
extreme poses. :func:`suggest_frames` proposes them by pivoted Gram-Schmidt
on the mouth deformation-gradient features of a captured sequence (one
unitless row of ``9m`` entries per frame, :mod:`.features`), starting from
the span of the frames already corrected or of a fitted regressor's
training frames. The features are projected and deflated in place a block
of rows at a time. No bpy in this module.
"""

from __future__ import annotations

import numpy as np

from ..errors import FaceLabError, UsageError
from .regressor.features import BLOCK, as_frames, mouth_feature_matrix
from .regressor import LipRegressor

__all__ = ["suggest_frames", "SuggestScreen"]


def _deflate(R, q, block=BLOCK):
    """``R -= (R q) qᵀ`` in place, a block of rows at a time (no full-size temporary)."""
    for s in range(0, len(R), block):
        b = R[s : s + block]
        b -= np.outer(b @ q, q)


def suggest_frames(captured=None, count: int = 1, *, regressor: LipRegressor | None = None, rest_vertices=None,
                   faces=None, mouth_faces=None, exclude=(), features=None,
                   overwrite_features: bool = False) -> np.ndarray:
    """Propose the next frames worth correcting.

    Greedy pivoted Gram-Schmidt in mouth-gradient space (Dinev et al. 2018,
    §6.2: train on extreme poses): each pick is the frame whose mouth
    gradients lie farthest outside the span of the frames already known, and
    its direction is then added to the span. With no regressor the span
    starts empty (features are gradients minus the identity), so the first
    pick is the most extreme pose (largest deformation from rest) and the
    next ones are the poses least explained by the earlier picks. With a
    regressor the span starts as its training span, so the first pick is the
    frame of largest :meth:`LipRegressor.extrapolation`.

    Memory: one (T, 9m) float64 array of mouth features (``m`` mouth
    triangles; about 0.1 MB a frame on ICT-FaceKit), projected and deflated
    in place a block of rows at a time. With ``features=...`` and
    ``overwrite_features=True`` the given array is that working array, so
    nothing of full size is allocated.

    Parameters
    ----------
    captured : (T,V,3) array_like, optional
        The captured sequence, scene units (float32 is read in place, a block
        of frames at a time). Required unless ``features`` is given.
    count : int
        Number of frames to propose.
    regressor : LipRegressor, optional
        A fitted regressor; supplies the rest mesh, faces, mouth region,
        feature centring and training span.
    rest_vertices : (V,3) array_like, optional
        Rest positions (needed without ``regressor`` and ``features``).
    faces : (F,3) int array_like, optional
        Triangles (needed without ``regressor`` and ``features``).
    mouth_faces : (m,) int array_like, optional
        Mouth-region triangles (needed without ``regressor`` and ``features``).
    exclude : sequence of int
        Frames never to propose (for example the ones already corrected);
        their directions are added to the starting span.
    features : (T, 9m) array_like, optional
        Instead of ``captured``: precomputed mouth features of the sequence,
        one row per frame. With a regressor, ``regressor.mouth_features(captured)``
        (the same array can first go to ``regressor.extrapolation(features=...)``,
        so the sequence is read once). Without one, the mouth deformation
        gradients minus the identity (any fixed order of the 9m entries), i.e.
        ``mouth_features`` of a ``center="rest"`` regressor on these mouth
        triangles. The result equals passing ``captured``.
    overwrite_features : bool
        Use ``features`` (if a C-contiguous float64 ndarray) as the working
        array instead of copying it; its contents are then undefined.

    Returns
    -------
    (c,) int64 ndarray
        Frame indices in order of priority, ``c = min(count, frames left)``;
        fewer when the remaining frames already lie in the span.
    """
    if (captured is None) == (features is None):
        raise UsageError("suggest_frames() takes captured frames or their features, not both or neither; pass one")
    if features is not None:
        if regressor is not None:
            F0 = regressor.check_features(features)
        else:
            F0 = np.asarray(features)
            if F0.ndim != 2 or F0.shape[1] % 9 or len(F0) == 0:
                raise FaceLabError(f"features have shape {F0.shape}, expected (T, 9m) with T >= 1 (9 per mouth "
                                   "triangle).")
            if mouth_faces is not None and F0.shape[1] != 9 * len(np.asarray(mouth_faces).ravel()):
                raise FaceLabError(f"features have {F0.shape[1]} columns but there are {len(mouth_faces)} mouth "
                                   "triangles (9 columns each); compute them on the same mouth region.")
        own = overwrite_features and isinstance(F0, np.ndarray) and F0.dtype == np.float64 and F0.flags.c_contiguous
        Rz = F0 if own else np.array(F0, dtype=np.float64, order="C")
    elif regressor is not None:
        Rz = regressor.mouth_features(captured)
    else:
        if rest_vertices is None or faces is None or mouth_faces is None:
            raise FaceLabError(
                "suggest_frames needs either a fitted regressor or rest_vertices, faces and mouth_faces; pass them."
            )
        R = np.asarray(rest_vertices, dtype=np.float64)
        A = as_frames(captured, len(R), "captured frames")
        Rz = mouth_feature_matrix(A, R, faces, mouth_faces)
    Q = regressor.training_span() if regressor is not None and regressor.is_fitted else None
    T = len(Rz)
    # feature scale (threshold of "already in the span"), then residuals after projecting on Q, in place
    sq = np.empty(T)
    for s in range(0, T, BLOCK):
        b = Rz[s : s + BLOCK]
        sq[s : s + BLOCK] = np.sum(b * b, axis=1)
        if Q is not None and Q.shape[1]:
            b -= (b @ Q) @ Q.T
    scale = max(float(np.sqrt(np.mean(sq))), 1e-300)
    excl = np.zeros(T, dtype=bool)
    ex = np.asarray(list(exclude), dtype=np.int64)
    if ex.size:
        excl[ex[(ex >= 0) & (ex < T)]] = True
    # ... and on the excluded frames
    for i in np.flatnonzero(excl):
        nv = np.linalg.norm(Rz[i])
        if nv > 1e-10 * scale:
            _deflate(Rz, Rz[i] / nv)
    picks = []
    norms = np.empty(T)
    for _ in range(int(count)):
        for s in range(0, T, BLOCK):
            norms[s : s + BLOCK] = np.linalg.norm(Rz[s : s + BLOCK], axis=1)
        norms[excl] = -1.0
        if picks:
            norms[picks] = -1.0
        i = int(np.argmax(norms))
        if norms[i] <= 1e-10 * scale:
            break
        picks.append(i)
        _deflate(Rz, Rz[i] / norms[i])
    return np.asarray(picks, dtype=np.int64)


class SuggestScreen:
    """:func:`suggest_frames` for a shot too long to hold its features: one streaming pass, then a few frames.

    :meth:`add` takes the mouth features of each chunk of frames and keeps only their
    norms outside the span (the regressor's training span, then ``directions``). :meth:`select`
    re-reads the features of the ``candidates`` frames of largest norm (and of the excluded
    frames) through a callback and runs the greedy selection of :func:`suggest_frames` on
    them. A pick is exact (the one :func:`suggest_frames` makes on the whole shot) when its
    norm after deflation is at least the largest norm of the frames not re-read; the first
    pick always is. When a later pick is not, :meth:`select` stops there and returns the
    directions to deflate by, for another pass (a new screen with ``directions``).

    Parameters
    ----------
    regressor : LipRegressor
        A fitted regressor (features and training span).
    n_frames : int
        Frames in the shot (indices ``0..n_frames-1``).
    exclude : sequence of int
        Frames never proposed (training frames; their directions join the span).
    directions : (d, 9m) ndarray, optional
        Orthonormal directions to deflate by first (from an earlier :meth:`select`).
    candidates : int
        Frames re-read per pass (besides the excluded ones).
    """

    def __init__(self, regressor, n_frames: int, exclude=(), directions=None, candidates: int = 128):
        regressor.require_fit()
        self.reg, self.T = regressor, int(n_frames)
        self.excl = np.zeros(self.T, dtype=bool)
        ex = np.asarray(list(exclude), dtype=np.int64)
        self.excl[ex[(ex >= 0) & (ex < self.T)]] = True
        self.dirs = np.zeros((0, 9 * len(regressor.mouth_faces))) if directions is None else np.asarray(directions)
        self.K = int(candidates)
        self.sq = np.zeros(self.T)  # ||y||²: the feature scale of suggest_frames
        self.res = np.zeros(self.T)  # norm outside the span and the directions

    def add(self, start: int, features) -> None:
        """Record frames ``start..start+t-1`` from their (t, 9m) mouth features (not kept)."""
        Y = np.asarray(features, dtype=np.float64)
        Q = self.reg.training_span()
        r = Y - (Y @ Q) @ Q.T
        if len(self.dirs):
            r -= (r @ self.dirs.T) @ self.dirs
        self.sq[start : start + len(Y)] = np.sum(Y * Y, axis=1)
        self.res[start : start + len(Y)] = np.sqrt(np.sum(r * r, axis=1))

    def add_scores(self, start: int, feature_sq, extrapolation) -> None:
        """Record frames from ``||y||²`` and :meth:`LipRegressor.extrapolation` (a screen without directions).

        What :meth:`LipRegressor.correct_chunk` returns beside the corrections, so the first pass
        costs nothing more.
        """
        if len(self.dirs):
            raise FaceLabError("This screen deflates by directions; record its frames with add() or add_frames().")
        n = len(feature_sq)
        self.sq[start : start + n] = feature_sq
        self.res[start : start + n] = np.asarray(extrapolation) * self.reg.feature_scale

    def add_frames(self, start: int, frames, *, used_only: bool = False) -> None:
        """Record frames from their positions (T,V,3) (or used vertices): features projected, never formed."""
        A = np.hstack([self.reg.training_span(), self.dirs.T])
        P, sq = self.reg.mouth_projections(frames, A, used_only=used_only)
        self.sq[start : start + len(sq)] = sq
        self.res[start : start + len(sq)] = np.sqrt(np.clip(sq - np.sum(P * P, axis=1), 0.0, None))

    def select(self, count: int, features_of, scale: float | None = None, *, exact: bool = True):
        """Greedy picks among the candidates, as far as they are exact.

        Parameters
        ----------
        count : int
            Frames wanted.
        features_of : callable((k,) int ndarray) -> (k, 9m) ndarray
            Mouth features of the given frame indices (re-read from the shot).
        scale : float, optional
            Feature scale (from the first pass; default this screen's).
        exact : bool
            Stop at the first pick a frame not re-read could beat (``done`` False: run another
            pass). False: keep picking among the candidates (one pass; the picks are the greedy
            choice among the ``candidates`` frames farthest from the span).

        Returns
        -------
        picks : list of int
            Frame indices, best first.
        done : bool
            False when the next pick could lie outside the candidates: run another pass.
        directions : (d, 9m) ndarray
            This screen's directions plus the excluded frames' and the picks'.
        scale : float
        """
        scale = max(float(np.sqrt(np.mean(self.sq))), 1e-300) if scale is None else scale
        free = np.flatnonzero(~self.excl)
        order = free[np.argsort(-self.res[free], kind="stable")]
        cand, rest = order[: self.K], order[self.K :]
        tau = float(self.res[rest].max()) if rest.size else -1.0
        ex = np.flatnonzero(self.excl)
        idx = np.concatenate([ex, np.sort(cand)]).astype(np.int64)
        F = np.array(features_of(idx), dtype=np.float64) if idx.size else np.zeros((0, self.dirs.shape[1]))
        Q = self.reg.training_span()
        F -= (F @ Q) @ Q.T
        if len(self.dirs):
            F -= (F @ self.dirs.T) @ self.dirs
        dirs = list(self.dirs)
        for i in range(len(ex)):  # the excluded frames join the span, in frame order
            nv = np.linalg.norm(F[i])
            if nv > 1e-10 * scale:
                q = F[i] / nv
                _deflate(F, q)
                dirs.append(q)
        picks, done = [], True
        pickable = np.r_[np.zeros(len(ex), bool), np.ones(len(idx) - len(ex), bool)]
        for _ in range(int(count)):
            norms = np.where(pickable, np.linalg.norm(F, axis=1), -1.0)
            if not norms.size:
                break
            j = int(np.argmax(norms))
            if norms[j] <= 1e-10 * scale and tau <= 1e-10 * scale:
                break
            if exact and norms[j] < tau:  # a frame not re-read may beat it: deflate by the picks so far, pass again
                done = False
                break
            picks.append(int(idx[j]))
            pickable[j] = False
            q = F[j] / norms[j]
            _deflate(F, q)
            dirs.append(q)
        return picks, done, np.asarray(dirs).reshape(-1, self.dirs.shape[1]), scale
