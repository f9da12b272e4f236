"""The reduced regression of the lip-correction learning: thin SVDs and the small map θ̄.

Dinev et al. 2018, "User-Guided Lip Correction for Facial Performance
Capture", §4: with ``Y = U_Y C_Y`` and ``X = U_X C_X`` (thin SVDs of the
training feature matrices, one column per corrected frame), the reduced
unknown ``θ̄ = U_Xᵀ θ U_Y`` (at most ``k × k``) solves the normal equations
``θ̄ C_Y C_Yᵀ = C_X C_Yᵀ``. :func:`thin_svd` computes the factorisations with
a rank tolerance, :func:`solve_theta` the normal equations (with an optional
Tikhonov term) and :func:`choose_ridge` its weight by leave-one-out error.
All quantities are unitless (deformation gradients). Used by
:func:`.training.train`, once per patch.
"""

from __future__ import annotations

import numpy as np

from ...errors import FaceLabError, TooManyShapesError

__all__ = ["thin_svd", "solve_theta", "choose_ridge", "loo_residuals", "loo_span_residuals", "MODELS",
           "StreamingBasis"]

MODELS = ("auto", "whole", "correction")  # what the lip regression predicts (LipRegressor ``model``)


def thin_svd(M, center, rtol, atol=0.0):
    """Thin SVD ``M = U C`` (``C = Σ Vᵀ``) of a feature matrix (rows = 9 per triangle, k columns).

    Two rank cuts: singular values below ``rtol`` times the size of the
    *deformation* (the Frobenius norm of ``M`` minus the identity gradients,
    so the uncentred paper model is not dominated by the identity) are
    dropped (relative cut), and so are those below ``atol * sqrt(f)``, a
    deformation whose RMS gradient change per triangle is below ``atol``
    (absolute cut). The absolute cut removes round-off directions (a frame
    in the rest pose gives singular values of about 1e-15, which the
    relative cut alone would keep and the regression would then divide by).
    Computed through the k×k Gram matrix (``O(rows·k²)``, several times
    faster than LAPACK on tall matrices); its precision, ``sqrt(eps)``
    times the largest singular value, is far below the rank tolerance.

    Parameters
    ----------
    M : (9f, k) float64 ndarray
        Features of f triangles (unitless gradients), one column per training frame.
    center : {"rest", None}
        ``"rest"``: ``M`` holds gradients minus the identity; ``None``: plain gradients.
    rtol : float
        Relative singular-value cut-off (at least 1e-7).
    atol : float
        Absolute cut-off: RMS Frobenius norm per triangle of a gradient change (unitless).

    Returns
    -------
    U : (9f, r) float64 ndarray
        Orthonormal columns.
    C : (r, k) float64 ndarray
        Coefficients ``Σ Vᵀ`` of the frames in ``U``.
    """
    w, Vv = np.linalg.eigh(M.T @ M)
    w, Vv = w[::-1], np.ascontiguousarray(Vv[:, ::-1])  # descending; contiguous for BLAS
    s = np.sqrt(np.clip(w, 0.0, None))
    if center == "rest":
        ref = float(np.sqrt(np.sum(M * M)))
    else:
        ident = np.tile(np.eye(3).ravel(), M.shape[0] // 9)[:, None]
        ref = float(np.linalg.norm(M - ident))
    ref = max(ref, 1e-12 * (s[0] if s.size else 0.0), 1e-300)
    cut = max(max(rtol, 1e-7) * ref, float(atol) * np.sqrt(M.shape[0] / 9.0))
    r = int(np.sum(s > cut)) if s.size else 0
    U = (M @ Vv[:, :r]) / s[:r]
    return U, s[:r, None] * Vv[:, :r].T


def solve_theta(CY, CX, lam, free: int = 0):
    """Reduced map ``θ̄`` from the normal equations ``θ̄ (C_Y C_Yᵀ + λ' I) = C_X C_Yᵀ``.

    Parameters
    ----------
    CY : (rY, k) ndarray
        Mouth coefficients ``C_Y`` of the k training frames (from :func:`thin_svd`).
    CX : (rX, k) ndarray
        Lip coefficients ``C_X``.
    lam : float
        Ridge weight, relative to the mean of ``diag(C_Y C_Yᵀ)`` (``λ' = lam * mean``); 0 is the paper.
    free : int
        The last ``free`` rows of ``C_Y`` (an intercept) are neither penalized nor counted in the mean.

    Returns
    -------
    (rX, rY) float64 ndarray
        ``θ̄`` (zeros when either rank is 0); unitless.
    """
    rY = CY.shape[0]
    if rY == 0 or CX.shape[0] == 0:
        return np.zeros((CX.shape[0], rY))
    A = CY @ CY.T  # (rY, rY)
    B = CX @ CY.T  # (rX, rY)
    if lam > 0 and rY > free:
        pen = np.r_[np.ones(rY - free), np.zeros(free)]
        A = A + lam * np.mean(np.diag(A)[: rY - free]) * np.diag(pen)
    # θ̄ A = B  <=>  A θ̄ᵀ = Bᵀ (A symmetric). The rank was already cut at rtol in the thin SVD
    # (A = diag(s²) up to rounding); lstsq only guards against exact singularity.
    sol, *_ = np.linalg.lstsq(A, B.T, rcond=1e-12)
    return sol.T


def choose_ridge(CY, CX, ridge, free: int = 0):
    """The ridge weight for one reduced map: ``ridge`` itself, or picked by leave-one-out.

    Parameters
    ----------
    CY, CX : (rY, k), (rX, k) ndarray
        Mouth and lip coefficients of the k training frames.
    ridge : float or "loo"
        A fixed weight (see :func:`solve_theta`), or ``"loo"``: the weight of
        ``(0, 1e-4, 1e-3, 1e-2, 3e-2, 0.1, 0.3, 1)`` with the smallest
        leave-one-out error on the lip coefficients (0 with fewer than 3 frames).
    free : int
        As :func:`solve_theta`.

    Returns
    -------
    float
    """
    if ridge != "loo":
        return float(ridge)
    k = CY.shape[1]
    if k < 3:
        return 0.0
    best, best_err = 0.0, np.inf
    for lam in (0.0, 1e-4, 1e-3, 1e-2, 3e-2, 1e-1, 3e-1, 1.0):
        err = 0.0
        for i in range(k):
            keep = np.arange(k) != i
            th = solve_theta(CY[:, keep], CX[:, keep], lam, free)
            err += float(np.sum((th @ CY[:, i] - CX[:, i]) ** 2))
        if err < best_err * (1 - 1e-9):
            best, best_err = lam, err
    return best


def loo_residuals(CY, CX, lam, free: int = 0):
    """Leave-one-out residuals of a reduced map: frame ``i`` predicted by the map fitted on the others.

    Exact for the reduced model (the k-1 frame map applied to frame ``i``'s mouth coefficients is the
    k-1 frame regression on the full features: ``C_Y`` holds every frame's exact coordinates). With
    one training frame the map fitted on no frames is 0, so the residual is minus the frame itself.

    Parameters
    ----------
    CY, CX : (rY, k), (rX, k) ndarray
        Mouth and output coefficients of the k training frames (:func:`thin_svd`).
    lam : float
        Ridge weight (as :func:`solve_theta`).
    free : int
        As :func:`solve_theta`.

    Returns
    -------
    (rX, k) float64 ndarray
        ``θ̄₋ᵢ C_Y[:, i] - C_X[:, i]`` per column (unitless, in the ``U_X`` basis).
    """
    k = CY.shape[1]
    out = -np.array(CX, dtype=np.float64)
    if k < 2:
        return out
    for i in range(k):
        keep = np.arange(k) != i
        out[:, i] += solve_theta(CY[:, keep], CX[:, keep], lam, free) @ CY[:, i]
    return out


def loo_span_residuals(C):
    """Squared distance of each training frame from the span of the others.

    Parameters
    ----------
    C : (r, k) ndarray
        Coefficients of the k frames in an orthonormal basis (:func:`thin_svd`), so distances are exact.

    Returns
    -------
    (k,) float64 ndarray
        ``||c_i - P₋ᵢ c_i||²`` with ``P₋ᵢ`` the projection on the other columns (``||c_i||²`` for k = 1).
    """
    C = np.asarray(C, dtype=np.float64)
    k = C.shape[1]
    out = np.empty(k)
    for i in range(k):
        c = C[:, i]
        if k > 1:
            Q, s, _ = np.linalg.svd(np.delete(C, i, axis=1), full_matrices=False)
            Q = Q[:, s > 1e-12 * max(s[0], 1e-300)] if s.size else Q[:, :0]
            c = c - Q @ (Q.T @ c)
        out[i] = float(c @ c)
    return out


class StreamingBasis:
    """A few corrective shapes and per-frame weights for a long shot, built a chunk of frames at a time.

    The propagated corrections of the interior lips (Dinev et al. 2018 §4) are a linear
    function of the reduced mouth coefficients plus the capture's own lip detail, so a
    shot of thousands of frames is well described by a handful of shapes. This class
    finds them without holding the (T, n, 3) corrections: each frame is projected on the
    shapes found so far, and a frame that the shapes miss by more than a quarter of the tolerance
    adds its residual as a new shape (a pivoted Gram-Schmidt in frame order, so the result
    does not depend on how the shot is split into chunks). :meth:`finish` then rotates the
    shapes by the SVD of the weights and drops the weakest while every frame stays within
    the tolerance. Memory: the shapes (r, 3n) and the weights (T, r).

    Parameters
    ----------
    n : int
        Vertices per frame.
    tol : float
        Largest reconstruction error of any vertex in any frame, scene units (> 0).
    max_rank : int
        Most shapes kept; a shot that needs more raises :class:`~facelab_addon.core.errors.TooManyShapesError`.
    """

    def __init__(self, n: int, tol: float, *, max_rank: int = 1024):
        if not (tol > 0 and np.isfinite(tol)):
            raise FaceLabError(f"The compression tolerance must be a positive distance in scene units, got {tol}.")
        self.n, self.tol, self.max_rank = int(n), float(tol), int(max_rank)
        self._U = np.zeros((0, 3 * self.n))  # orthonormal rows
        self._W = []  # per chunk: (t, r at the end of that chunk)

    @property
    def frames(self) -> int:
        """Frames added so far."""
        return sum(len(w) for w in self._W)

    def add(self, deltas) -> None:
        """Add the corrections of the next frames.

        Parameters
        ----------
        deltas : (t, n, 3) array_like
            Per-frame offsets, scene units, in shot order.

        Raises
        ------
        TooManyShapesError
            The frames need more than ``max_rank`` shapes.
        """
        X = np.asarray(deltas, dtype=np.float64).reshape(len(deltas), 3 * self.n)
        t, gtol = len(X), 0.25 * self.tol
        U = self._U
        P = X @ U.T  # (t, r)
        Rs = X - P @ U
        err = np.sqrt(np.max(np.sum(Rs.reshape(t, self.n, 3) ** 2, axis=2), axis=1)) if self.n else np.zeros(t)
        new, cols = [], []
        i = 0
        while True:
            bad = np.flatnonzero(err[i:] > gtol)
            if not bad.size:
                break
            i += int(bad[0])
            q = Rs[i].copy()
            for B in (U, np.asarray(new).reshape(-1, 3 * self.n)):  # re-orthogonalise against round-off
                q -= (B @ q) @ B
            q /= np.linalg.norm(q)
            c = np.zeros(t)
            c[i:] = Rs[i:] @ q  # frames before i never see the new shape (order, not chunking, decides)
            Rs[i:] -= np.outer(c[i:], q)
            err[i:] = np.sqrt(np.max(np.sum(Rs[i:].reshape(t - i, self.n, 3) ** 2, axis=2), axis=1))
            new.append(q)
            cols.append(c)
            if len(U) + len(new) > self.max_rank:
                raise TooManyShapesError(
                    f"The corrections need more than {self.max_rank} corrective shapes to stay within "
                    f"{self.tol:.3g} scene units (they do not compress: a noisy capture?); smooth the capture's "
                    "lips or store the result as a point cache.")
        if new:
            self._U = np.vstack([U, np.asarray(new)])
            P = np.hstack([P, np.stack(cols, 1)])
        self._W.append(P)

    def finish(self):
        """The shapes and weights, rotated to the weights' SVD and truncated within the tolerance.

        Returns
        -------
        basis : (r, n, 3) float64 ndarray
            Corrective shapes, scene units, scaled so each weight peaks at magnitude 1.
        weights : (T, r) float64 ndarray
            Per-frame weights in [-1, 1]; ``r`` is 0 when every frame is within the tolerance of zero.
        """
        r = len(self._U)
        T = self.frames
        W = np.zeros((T, r))
        o = 0
        for w in self._W:
            W[o : o + len(w), : w.shape[1]] = w
            o += len(w)
        if r == 0:
            return np.zeros((0, self.n, 3)), W
        _, V = np.linalg.eigh(W.T @ W)
        V = np.ascontiguousarray(V[:, ::-1])  # a reversed view would take numpy's slow non-BLAS matmul
        Wr = W @ V
        Ur = V.T @ self._U  # rotated shapes (r, 3n), orthonormal

        # per frame: the L2 norm of its dropped weights bounds every vertex's error from above, and
        # from below after dividing by sqrt(n); only frames above the budget are reconstructed
        budget = 0.75 * self.tol  # the greedy residual already used a quarter of the tolerance
        C = np.zeros((T, r + 1))
        C[:, :r] = np.sqrt(np.cumsum((Wr * Wr)[:, ::-1], axis=1)[:, ::-1])  # C[t, k]: keeping k shapes
        tail = C.max(axis=0) if T else np.zeros(r + 1)

        def fits(k):  # every vertex of every frame within the budget when the first k shapes are kept
            for s in np.array_split(np.flatnonzero(C[:, k] > budget), max(1, T // 512)):
                D = Wr[s, k:] @ Ur[k:]
                if len(s) and np.max(np.sum(D.reshape(len(s), self.n, 3) ** 2, axis=2)) > budget * budget:
                    return False
            return True

        hi = int(np.flatnonzero(tail <= budget)[0])
        lo = int(np.flatnonzero(tail <= budget * np.sqrt(max(self.n, 1)))[0])
        if (hi - lo) * T * self.n > 2e9:  # exact search too costly (a correction that does not compress)
            lo = hi
        while lo < hi:
            mid = (lo + hi) // 2
            if fits(mid):
                hi = mid
            else:
                lo = mid + 1
        k = hi
        basis = Ur[:k].reshape(k, self.n, 3)
        weights = Wr[:, :k]
        peak = np.max(np.abs(weights), axis=0) if T else np.ones(k)
        peak = np.where(peak > 0, peak, 1.0)
        return basis * peak[:, None, None], weights / peak
