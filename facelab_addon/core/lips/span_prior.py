"""A prior from the face's own shapes: the lips' correction as a mix of the face's expression offsets.

One camera sees the lips' silhouettes across its rays only; how the rest of the lip band (and the depth) follows is
the prior's choice. The face's own expression shapes (its shape keys: jaw open, lips pressed, rolled, puckered...)
say how this face's lips move together: a correction made of them moves the whole band, and in depth, as the
face does. :func:`span_columns` restricts the offsets to the free lip region, tapered to zero at its held border
(so nothing outside moves and the border is met smoothly); :func:`fit_span` finds the mix whose silhouettes best
match the sketch (the same point-to-ray terms as ``E_silh``, re-matched each iteration), with a ridge that keeps
the mix small. The Laplacian solve of :mod:`~facelab_addon.core.lips.sketch` then starts from that shape.

Shapes: vertices (V,3) float64 scene units; a basis (K,V,3) of offsets in scene units.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse.csgraph import dijkstra

from ..errors import UsageError
from ..geometry.deform import PointConstraints
from ..geometry.mesh import edge_length_graph

__all__ = ["SPAN_REG", "taper", "span_columns", "fit_span"]

#: Ridge of :func:`fit_span`, relative to the mean diagonal of the data term (dimensionless: any units, any number of
#: sketch samples).
SPAN_REG = 0.01


def taper(vertices, faces, region) -> np.ndarray:
    """(V,) weights in [0, 1]: 0 off ``region`` and at its border, rising smoothly inward (smoothstep of the
    geodesic distance to the border over half the region's largest such distance)."""
    V = np.asarray(vertices, dtype=np.float64)
    F = np.asarray(faces, dtype=np.int64)
    region = np.asarray(region, bool)
    n = len(V)
    outside = ~region
    touch = np.zeros(n, bool)
    tri = region[F].any(axis=1) & outside[F].any(axis=1)
    touch[F[tri].ravel()] = True
    src = np.flatnonzero(touch & outside)
    if len(src) == 0:
        return region.astype(np.float64)
    G = edge_length_graph(V, F[region[F].any(axis=1)], n, min_length=1e-12)[0]
    d = dijkstra(G, directed=False, indices=src, min_only=True)
    d = np.where(region & np.isfinite(d), d, 0.0)
    top = 0.5 * float(d.max())
    if top <= 0:
        return np.zeros(n)
    u = np.clip(d / top, 0.0, 1.0)
    return u * u * (3.0 - 2.0 * u)


def span_columns(basis, weights, scale: float) -> np.ndarray:
    """(V,3,S) the basis offsets times ``weights`` (V,), each scaled to an RMS of ``scale`` over the weighted
    vertices; offsets that do not move them are dropped.

    Parameters
    ----------
    basis : (K,V,3) float
        Offsets, scene units (e.g. each expression shape minus the rest shape).
    weights : (V,) float
        :func:`taper` of the free region.
    scale : float
        Scene units (the mouth width): the columns' size, so the ridge means the same in any unit.
    """
    B = np.asarray(basis, dtype=np.float64)
    w = np.asarray(weights, dtype=np.float64)
    if B.ndim != 3 or B.shape[1:] != (len(w), 3) or not np.isfinite(B).all():
        raise UsageError(f"basis must be finite (K,{len(w)},3) offsets of the mesh's vertices, got {B.shape}; pass "
                         "the face's expression shapes minus its rest shape.")
    on = w > 0
    if not on.any():
        return np.zeros((len(w), 3, 0))
    U = B[:, on, :] * w[None, on, None]
    rms = np.sqrt(np.mean(np.sum(U * U, axis=2), axis=1))
    keep = rms > 1e-9 * max(float(np.abs(B).max()), 1e-300)
    U = U[keep] / rms[keep, None, None] * float(scale)
    out = np.zeros((len(w), 3, int(keep.sum())))
    out[on] = np.transpose(U, (1, 2, 0))
    return out


def fit_span(X0, U, constraints_at, iterations: int, reg: float = SPAN_REG):
    """The mix ``X = X0 + U a`` whose silhouettes best match the sketch.

    Parameters
    ----------
    X0 : (V,3) float
        The capture, scene units.
    U : (V,3,S) float
        :func:`span_columns`.
    constraints_at : callable
        ``constraints_at(X) -> list of PointConstraints``: the sketch terms matched on ``X``.
    iterations : int
        Match / solve rounds.
    reg : float
        Ridge on ``a``, relative to the data term's mean diagonal.

    Returns
    -------
    X : (V,3) float
    a : (S,) float
    """
    X0 = np.asarray(X0, dtype=np.float64)
    S = U.shape[2]
    a = np.zeros(S)
    X = X0
    if S == 0:
        return X, a
    for _ in range(int(iterations)):
        C = PointConstraints.concat(constraints_at(X))
        if C is None:
            break
        H = C.strength[:, None, None] * np.einsum("cji,cjk->cik", C.metrics, C.metrics)
        g = np.einsum("ck,ckd->cd", C.bary, X0[C.vertices]) - C.targets  # (c,3)
        G = np.einsum("ck,ckds->cds", C.bary, U[C.vertices])  # (c,3,S)
        HG = np.einsum("cij,cjs->cis", H, G)
        A = np.einsum("cis,cit->st", G, HG)
        b = -np.einsum("cis,ci->s", HG, g)
        A[np.diag_indices(S)] += float(reg) * max(float(np.mean(np.diag(A))), 1e-300)
        a = np.linalg.solve(A, b)
        X = X0 + U @ a
    return X, a
