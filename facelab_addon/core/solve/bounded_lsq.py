"""Bounded least squares for the blendshape weights (Bhat et al. 2013, §4.3, Eq. 3).

"High fidelity facial animation capture and retargeting with contours": the
blendshape fit minimises the marker and contour energies subject to
``-1 <= w <= 1``, a bounded linear least-squares problem. With ``S`` shapes
(tens to a few hundred) it is solved on the ``S x S`` normal equations by
:func:`box_least_squares`, a primal active-set method (exact for convex box
QPs, finite steps) warm-started from the previous frame's weights, with
``scipy.optimize.lsq_linear`` (BVLS) as the fallback.

Dense NumPy/SciPy, no bpy.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg

__all__ = ["box_least_squares"]


def box_least_squares(H, g, lo, hi, w0=None, *, max_iter: int | None = None):
    """Minimise ``0.5 wᵀHw - gᵀw`` subject to ``lo <= w <= hi`` (H SPD, small).

    A primal active-set method (exact for convex box QPs, finite steps);
    warm-started from ``w0`` (clipped into the box). Falls back to
    ``scipy.optimize.lsq_linear`` if it does not converge.

    Parameters
    ----------
    H : (S,S) float
        Normal matrix ``JᵀJ`` (plus ridge), symmetric positive definite.
    g : (S,) float
        ``Jᵀb``.
    lo, hi : (S,) float
        Bounds.
    w0 : (S,) float, optional
        Warm start.

    Returns
    -------
    w : (S,) float64
    n_iter : int
        Active-set iterations taken.
    """
    S = len(g)
    lo = np.broadcast_to(np.asarray(lo, float), (S,))
    hi = np.broadcast_to(np.asarray(hi, float), (S,))
    w = np.zeros(S) if w0 is None else np.clip(np.asarray(w0, float).copy(), lo, hi)
    at_lo = w <= lo
    at_hi = w >= hi
    scale = max(float(np.abs(np.diag(H)).max()), 1e-300)
    tol = 1e-10 * scale * max(1.0, float(np.abs(hi - lo).max()))
    max_iter = 6 * S + 10 if max_iter is None else max_iter
    for it in range(1, max_iter + 1):
        free = ~(at_lo | at_hi)
        target = w.copy()
        if free.any():
            fi = np.flatnonzero(free)
            rhs = g[fi] - H[np.ix_(fi, np.flatnonzero(~free))] @ w[~free]
            Hff = H[np.ix_(fi, fi)]
            try:
                c = scipy.linalg.cho_factor(Hff, lower=True, check_finite=False)
                target[fi] = scipy.linalg.cho_solve(c, rhs, check_finite=False)
            except np.linalg.LinAlgError:  # singular (no ridge, unobserved shapes): least-norm step
                target[fi] = np.linalg.lstsq(Hff, rhs, rcond=1e-12)[0]
        d = target - w
        # longest feasible step along d
        with np.errstate(divide="ignore", invalid="ignore"):
            a_lo = np.where(free & (d < 0), (lo - w) / d, np.inf)
            a_hi = np.where(free & (d > 0), (hi - w) / d, np.inf)
        a = np.minimum(a_lo, a_hi)
        k = int(np.argmin(a))
        if a[k] < 1.0:
            w = w + max(a[k], 0.0) * d
            if a_lo[k] <= a_hi[k]:
                w[k] = lo[k]
                at_lo[k] = True
            else:
                w[k] = hi[k]
                at_hi[k] = True
            continue
        w = target
        grad = H @ w - g
        viol = np.where(at_lo, -grad, 0.0) + np.where(at_hi, grad, 0.0)  # > 0: wants to move inward
        j = int(np.argmax(viol))
        if viol[j] <= tol:
            return np.clip(w, lo, hi), it
        at_lo[j] = at_hi[j] = False
    # fallback (should not happen for SPD H)
    from scipy.optimize import lsq_linear

    ev, U = np.linalg.eigh(0.5 * (H + H.T))
    ev = np.maximum(ev, 1e-14 * max(float(ev.max()), 1e-300))
    R = (U * np.sqrt(ev)).T  # RᵀR = H
    b = (U.T @ g) / np.sqrt(ev)
    res = lsq_linear(R, b, bounds=(lo, hi), method="bvls")
    return np.clip(res.x, lo, hi), max_iter
