"""Polylines: arc length, resampling, closest points and distances.

A polyline is an ordered (m,d) float array of points joined by straight
segments: a tracked or sketched curve in pixels (d = 2), or a chain of mesh
vertices in scene units (d = 3). Arc length is measured from the first point,
in the points' units. The closest-point and distance helpers are 2D (pixel
curves).
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "y_at",
    "arc_length",
    "resample_polyline",
    "closest_arc_length",
    "points_at_arc_length",
    "point_to_polyline_distance",
]


def arc_length(P) -> np.ndarray:
    """Cumulative arc length of a polyline.

    Parameters
    ----------
    P : (m,d) float
        Polyline points (pixels, scene units, ...).

    Returns
    -------
    (m,) float64
        Arc length from the first point to each point, in the points' units.
    """
    P = np.asarray(P, dtype=np.float64)
    d = P[1:] - P[:-1]
    S = np.empty(len(P))
    S[0] = 0.0
    np.cumsum(np.sqrt((d * d).sum(axis=1)), out=S[1:])
    return S


def resample_polyline(points, spacing: float = 1.0) -> np.ndarray:
    """Resample a polyline at (about) constant arc-length spacing.

    Parameters
    ----------
    points : (m,d) float
        Polyline points. Points closer than 1e-9 to their predecessor are
        dropped first.
    spacing : float
        Sample spacing, in the points' units; the whole length is divided
        into equal steps of at most ``spacing``.

    Returns
    -------
    (n,d) float64
        Samples including both end points; ``n >= 2`` (a single point is
        repeated).
    """
    P = np.asarray(points, dtype=np.float64)
    d = P[1:] - P[:-1]
    keep = np.sqrt((d * d).sum(axis=1)) > 1e-9
    if not keep.all():
        P = P[np.r_[True, keep]]
    s = arc_length(P)
    n = max(2, int(np.ceil(s[-1] / max(spacing, 1e-12))) + 1)
    u = np.linspace(0.0, s[-1], n)
    return np.stack([np.interp(u, s, P[:, k]) for k in range(P.shape[1])], axis=1)


def closest_arc_length(Q, C, S) -> np.ndarray:
    """Arc-length parameter of the point of a 2D polyline closest to each query point.

    Parameters
    ----------
    Q : (k,2) float
        Query points.
    C : (m,2) float
        Polyline, ``m >= 2``.
    S : (m,) float
        Its cumulative arc length (:func:`arc_length`).

    Returns
    -------
    (k,) float64
        Arc length along ``C`` of the closest point to each ``Q``, in ``C``'s units.
    """
    a = C[:-1]
    ab = C[1:] - a
    L2 = np.maximum(ab[:, 0] ** 2 + ab[:, 1] ** 2, 1e-300)
    qx = Q[:, 0, None] - a[None, :, 0]
    qy = Q[:, 1, None] - a[None, :, 1]
    t = np.clip((qx * ab[None, :, 0] + qy * ab[None, :, 1]) / L2[None], 0.0, 1.0)
    ex = qx - t * ab[None, :, 0]
    ey = qy - t * ab[None, :, 1]
    j = np.argmin(ex * ex + ey * ey, axis=1)
    return S[j] + t[np.arange(len(Q)), j] * (S[j + 1] - S[j])


def points_at_arc_length(C, S, s) -> np.ndarray:
    """Points of a 2D polyline at given arc lengths (linear between its points).

    Parameters
    ----------
    C : (m,2) float
        Polyline.
    S : (m,) float
        Its cumulative arc length (:func:`arc_length`).
    s : (k,) float
        Arc lengths, clamped to ``[0, S[-1]]``.

    Returns
    -------
    (k,2) float64
    """
    return np.stack([np.interp(s, S, C[:, 0]), np.interp(s, S, C[:, 1])], axis=1)


def point_to_polyline_distance(Q, C) -> np.ndarray:
    """Distance of each point to a 2D polyline (to its closest segment).

    Parameters
    ----------
    Q : (k,2) float ndarray
        Points.
    C : (m,2) float
        Polyline, ``m >= 1`` (a single point: the distance to it).

    Returns
    -------
    (k,) float64
        Distances, in the points' units.
    """
    C = np.asarray(C, dtype=np.float64)
    if len(C) == 1:
        return np.linalg.norm(Q - C[0], axis=1)
    ax, ay = C[:-1, 0], C[:-1, 1]
    bx, by = C[1:, 0] - ax, C[1:, 1] - ay
    L2 = np.maximum(bx * bx + by * by, 1e-300)
    qx = Q[:, 0, None] - ax[None]
    qy = Q[:, 1, None] - ay[None]
    t = np.clip((qx * bx + qy * by) / L2, 0.0, 1.0)
    ex = qx - t * bx
    ey = qy - t * by
    return np.sqrt((ex * ex + ey * ey).min(axis=1))


def y_at(x, curve) -> np.ndarray:
    """(N,) a roughly x-monotonic 2D curve's y at ``x`` (N,), linearly interpolated; NaN outside its span.

    ``curve`` (M,2): points in any order along x (pixels, or any units).
    """
    curve = np.asarray(curve, dtype=np.float64)
    x = np.asarray(x, dtype=np.float64)
    o = np.argsort(curve[:, 0], kind="stable")
    cx, cy = curve[o, 0], curve[o, 1]
    y = np.interp(x, cx, cy)
    y[(x < cx[0]) | (x > cx[-1])] = np.nan
    return y
