"""Sealed lips drawn on one line are a contact: the lips meet in 3D, not only in the image.

The artist draws sealed lips as the upper and lower contours on one line (the README's convention). The sketch
terms (``E_silh``) then put the upper lip's silhouette and the lower lip's on the same camera rays, which a
single view cannot tell apart in depth: the lips may still be apart along the rays, or one lip's silhouette
row in front of the other's (the capture's gap, seen from any other angle). Where the two contours coincide
(:func:`one_line`), each upper-lip silhouette vertex matched to a sample of the shared stretch is paired with the
lower-lip silhouette vertex matched to the nearest lower sample, and the pair is pulled together in 3D
(:func:`contact_terms`: ``weight * ||x_u - x_l||^2``, a two-vertex point constraint of
:class:`~facelab_addon.core.geometry.deform.PointConstraints`).

Shapes: pixels (N,2), top-left origin, y down; vertex ids int64.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..geometry.deform import PointConstraints

__all__ = ["ONE_LINE_TOL", "ONE_LINE_MIN_PX", "ONE_LINE_RUN", "CONTACT_WEIGHT", "one_line", "contact_terms"]

#: The contours are on one line where an upper sample lies within this fraction of the sketch's width of a lower
#: sample (at least :data:`ONE_LINE_MIN_PX`): about 0.4 mm on a 5 cm mouth, under the smallest gap an artist draws
#: as two lines.
ONE_LINE_TOL = 0.008
#: The least tolerance of :data:`ONE_LINE_TOL`, pixels (a hand does not place two strokes closer).
ONE_LINE_MIN_PX = 1.5
#: A stretch on one line counts when it runs over at least this fraction of the sketch's width (a crossing of two
#: contours, or their meeting at a mouth corner, is not a contact).
ONE_LINE_RUN = 0.05
#: Refine's default weight of a contact pair per sketch sample, in units of ``lambda_silh``: off. Pulling the
#: matched silhouette vertices of both lips to one point also pulls together silhouette rows that lie apart in depth
#: on the truth (a lip overhanging the other), which can dent the lip band more than the contact closes; see
#: ``benchmarks/refine_zoo.py`` (its ``contact`` variants) before turning it on.
CONTACT_WEIGHT = 0.0


def one_line(upper, lower, width: float, tol: float = ONE_LINE_TOL, min_px: float = ONE_LINE_MIN_PX,
             run: float = ONE_LINE_RUN):
    """Which upper samples lie on one line with the lower contour, and their lower partner.

    Parameters
    ----------
    upper, lower : (N,2), (M,2) float
        Resampled contours (about 1 px apart), pixels.
    width : float
        The sketch's width, pixels.
    tol, min_px, run
        See :data:`ONE_LINE_TOL`, :data:`ONE_LINE_MIN_PX`, :data:`ONE_LINE_RUN`.

    Returns
    -------
    partner : (N,) int
        For each upper sample on a shared stretch, the index of the nearest lower sample; -1 elsewhere.
    """
    U = np.asarray(upper, dtype=np.float64)
    L = np.asarray(lower, dtype=np.float64)
    out = np.full(len(U), -1, dtype=np.int64)
    if len(U) == 0 or len(L) == 0 or width <= 0:
        return out
    d, j = cKDTree(L).query(U)
    on = d <= max(float(tol) * width, float(min_px))
    # keep runs of consecutive samples on the line (a jump of more than 1.5 px ends a run) at least run * width long
    step = np.r_[np.inf, np.linalg.norm(np.diff(U, axis=0), axis=1)]
    i = 0
    while i < len(U):
        if not on[i]:
            i += 1
            continue
        k = i + 1
        while k < len(U) and on[k] and step[k] <= 1.5:
            k += 1
        if np.sum(step[i + 1:k]) >= float(run) * width:
            out[i:k] = j[i:k]
        i = k
    return out


def contact_terms(upper_vertices, lower_vertices, partner, strength, sample_weights=None):
    """Two-vertex terms ``strength * count * ||x_u - x_l||^2`` pairing the lips along the shared stretch.

    Parameters
    ----------
    upper_vertices : (N,) int
        The silhouette vertex each upper sample matched.
    lower_vertices : (M,) int
        The silhouette vertex each lower sample matched.
    partner : (N,) int
        :func:`one_line`.
    strength : float
        Weight per sample pair.
    sample_weights : (N,) float, optional
        Per upper sample (0: no term).

    Returns
    -------
    PointConstraints or None
        One row per distinct (upper, lower) vertex pair, weighted by how many samples made it.
    """
    on = np.asarray(partner) >= 0
    if sample_weights is not None:
        on &= np.asarray(sample_weights) > 0
    if not on.any():
        return None
    u = np.asarray(upper_vertices)[on]
    lw = np.asarray(lower_vertices)[np.asarray(partner)[on]]
    ok = u != lw
    if not ok.any():
        return None
    w = np.ones(int(on.sum())) if sample_weights is None else np.asarray(sample_weights, float)[on]
    pairs, inv = np.unique(np.c_[u[ok], lw[ok]], axis=0, return_inverse=True)
    cnt = np.bincount(inv.ravel(), weights=w[ok], minlength=len(pairs))
    c = len(pairs)
    return PointConstraints(pairs, np.tile([1.0, -1.0], (c, 1)), np.zeros((c, 3)),
                            np.broadcast_to(np.eye(3), (c, 3, 3)), float(strength) * cnt)
