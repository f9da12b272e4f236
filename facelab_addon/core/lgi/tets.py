"""Tetrahedron geometry for local geometric indexing: quality, barycentric coordinates, closest points.

Cong, Lan and Fedkiw 2019, §4 and §4.1: every bundle's point cloud is covered
by overlapping tetrahedra. A bundle inside a tetrahedron is blended with its
barycentric weights (Eq. 1); a bundle outside every tetrahedron is projected to
the closest point of the tetrahedralized volume (:func:`closest_point_tetrahedron`)
or of the cloud's convex hull (:func:`closest_point_triangles`). Too thin
tetrahedra are found by their mean-ratio quality (:func:`tetrahedron_quality`).

Everything is vectorised over ``n`` tetrahedra given by their corners ``X``
(n,4,3) (or triangles by ``a, b, c``, each (n,3)). Flat tetrahedra, repeated
corners and triangles stored as ``(a, b, c, c)`` are handled.

Units: positions and distances in scene units (any length unit); barycentric
weights and qualities are unitless.
"""

from __future__ import annotations

import itertools

import numpy as np

from ..geometry.inv3 import inv3

__all__ = ["tetrahedron_quality", "barycentric_tetrahedron", "closest_point_tetrahedron"]


def tetrahedron_quality(X):
    """Mean-ratio quality ``12 (3 vol)^(2/3) / sum(edge^2)`` of tetrahedra.

    Parameters
    ----------
    X : (n,4,3) array_like
        Corner positions, any length unit.

    Returns
    -------
    (n,) float64 ndarray
        1 for a regular tetrahedron, 0 for a flat one; unitless.
    """
    X = np.asarray(X, dtype=np.float64)
    e = X[:, 1:] - X[:, :1]
    vol = np.abs(inv3(e, return_det=True)[1]) / 6.0
    l2 = sum(((X[:, i] - X[:, j]) ** 2).sum(1) for i, j in itertools.combinations(range(4), 2))
    with np.errstate(divide="ignore", invalid="ignore"):
        q = 12.0 * np.cbrt(3.0 * vol) ** 2 / l2
    return np.nan_to_num(q, nan=0.0)


def tet_inverse(X, rel_eps=1e-10):
    """(n,3,3) inverse edge matrices ``[x1-x0, x2-x0, x3-x0]^-1``; NaN for flat tetrahedra."""
    E = np.transpose(X[:, 1:] - X[:, :1], (0, 2, 1))  # columns = edges
    inv, det = inv3(E, return_det=True)
    L = np.linalg.norm(X[:, 1:] - X[:, :1], axis=2).max(axis=1)
    ok = np.abs(det) > rel_eps * np.maximum(L, 1e-300) ** 3
    inv[~ok] = np.nan
    return inv


def barycentric_tetrahedron(p, X):
    """Barycentric coordinates of points in tetrahedra.

    Parameters
    ----------
    p : (n,3) array_like
        Points, scene units.
    X : (n,4,3) array_like
        Tetrahedron corners, scene units.

    Returns
    -------
    (n,4) float64 ndarray
        ``w`` with ``sum(w) = 1`` and ``sum_k w_k X_k = p``; unitless. NaN for
        flat tetrahedra.
    """
    p = np.asarray(p, dtype=np.float64).reshape(-1, 3)
    X = np.asarray(X, dtype=np.float64).reshape(-1, 4, 3)
    inv = tet_inverse(X)
    w = np.einsum("nij,nj->ni", inv, p - X[:, 0])
    return np.column_stack([1 - w.sum(1), w])


TET_EDGES = list(itertools.combinations(range(4), 2))
_FACES = list(itertools.combinations(range(4), 3))


def closest_point_tetrahedron(p, X, inv=None):
    """Closest point of (possibly flat) tetrahedra to query points.

    Robust to degenerate corners (repeated points, flat tetrahedra,
    triangles stored as ``(a, b, c, c)``): the candidates are the interior
    (when the tetrahedron is not flat), the 4 face interiors and the 6 edges.

    Parameters
    ----------
    p : (n,3) array_like
        Query points, scene units.
    X : (n,4,3) array_like
        Tetrahedron corners, scene units.
    inv : (n,3,3) array_like, optional
        Precomputed inverse edge matrices (:func:`tet_inverse`).

    Returns
    -------
    distance : (n,) float64 ndarray
        Scene units.
    bary : (n,4) float64 ndarray
        Barycentric coordinates of the closest point (non-negative, sum 1).
    """
    p = np.asarray(p, dtype=np.float64).reshape(-1, 3)
    X = np.asarray(X, dtype=np.float64).reshape(-1, 4, 3)
    n = len(p)
    if inv is None:
        inv = tet_inverse(X)
    cands_d, cands_w = [], []
    # interior
    w = np.einsum("nij,nj->ni", inv, p - X[:, 0])
    w = np.column_stack([1 - w.sum(1), w])
    ok = np.isfinite(w).all(1) & (w >= -1e-12).all(1)
    d = np.where(ok, 0.0, np.inf)
    cands_d.append(d)
    cands_w.append(np.where(ok[:, None], np.clip(np.nan_to_num(w), 0, None), 0.0))
    # edges
    for i, j in TET_EDGES:
        a, e = X[:, i], X[:, j] - X[:, i]
        ee = (e * e).sum(1)
        t = np.where(ee > 0, ((p - a) * e).sum(1) / np.where(ee > 0, ee, 1.0), 0.0)
        t = np.clip(t, 0.0, 1.0)
        q = a + t[:, None] * e
        cands_d.append(np.linalg.norm(p - q, axis=1))
        ww = np.zeros((n, 4))
        ww[:, i] = 1 - t
        ww[:, j] += t
        cands_w.append(ww)
    # faces
    for i, j, k in _FACES:
        a, e1, e2 = X[:, i], X[:, j] - X[:, i], X[:, k] - X[:, i]
        r = p - a
        a11, a12, a22 = (e1 * e1).sum(1), (e1 * e2).sum(1), (e2 * e2).sum(1)
        b1, b2 = (r * e1).sum(1), (r * e2).sum(1)
        det = a11 * a22 - a12 * a12
        good = det > 1e-12 * np.maximum(a11 * a22, 1e-300)
        dd = np.where(good, det, 1.0)
        s = (a22 * b1 - a12 * b2) / dd
        t = (a11 * b2 - a12 * b1) / dd
        good &= (s >= 0) & (t >= 0) & (s + t <= 1)
        q = a + s[:, None] * e1 + t[:, None] * e2
        cands_d.append(np.where(good, np.linalg.norm(p - q, axis=1), np.inf))
        ww = np.zeros((n, 4))
        ww[:, i] = 1 - s - t
        ww[:, j] += s
        ww[:, k] += t
        cands_w.append(np.where(good[:, None], ww, 0.0))
    Dm = np.stack(cands_d, axis=1)
    best = np.argmin(Dm, axis=1)
    Wm = np.stack(cands_w, axis=1)
    return Dm[np.arange(n), best], Wm[np.arange(n), best]


def closest_point_triangles(p, a, b, c):
    """Closest points on triangles (Ericson, "Real-Time Collision Detection", 5.1.5), vectorized.

    Parameters
    ----------
    p, a, b, c : (n,3) array_like
        Query points and triangle corners, scene units.

    Returns
    -------
    distance : (n,) float64 ndarray
    bary : (n,3) float64 ndarray
        Weights of ``a, b, c`` at the closest point.
    """
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = (ab * ap).sum(1), (ac * ap).sum(1)
    bp = p - b
    d3, d4 = (ab * bp).sum(1), (ac * bp).sum(1)
    cp = p - c
    d5, d6 = (ab * cp).sum(1), (ac * cp).sum(1)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    n = len(p)
    w = np.zeros((n, 3))
    done = np.zeros(n, dtype=bool)

    def put(mask, wa, wb, wc):
        m = mask & ~done
        w[m, 0], w[m, 1], w[m, 2] = wa[m] if np.ndim(wa) else wa, wb[m] if np.ndim(wb) else wb, wc[m] if np.ndim(wc) else wc
        done[m] = True

    with np.errstate(divide="ignore", invalid="ignore"):
        put((d1 <= 0) & (d2 <= 0), 1.0, 0.0, 0.0)
        put((d3 >= 0) & (d4 <= d3), 0.0, 1.0, 0.0)
        t = np.nan_to_num(d1 / (d1 - d3))
        put((vc <= 0) & (d1 >= 0) & (d3 <= 0), 1 - t, t, 0.0)
        put((d6 >= 0) & (d5 <= d6), 0.0, 0.0, 1.0)
        t = np.nan_to_num(d2 / (d2 - d6))
        put((vb <= 0) & (d2 >= 0) & (d6 <= 0), 1 - t, 0.0, t)
        t = np.nan_to_num((d4 - d3) / ((d4 - d3) + (d5 - d6)))
        put((va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0), 0.0, 1 - t, t)
        den = va + vb + vc
        v = np.nan_to_num(vb / den)
        ww = np.nan_to_num(vc / den)
        put(np.ones(n, dtype=bool), 1 - v - ww, v, ww)
    w = np.clip(w, 0.0, 1.0)
    w /= np.maximum(w.sum(1, keepdims=True), 1e-300)
    x = w[:, :1] * a + w[:, 1:2] * b + w[:, 2:] * c
    return np.linalg.norm(p - x, axis=1), w
