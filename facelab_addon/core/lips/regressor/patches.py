"""Overlapping local patches of the inner-lip region for the lip regression.

Dinev et al. 2018, "User-Guided Lip Correction for Facial Performance
Capture", §4 learns one linear map from the mouth gradients to the lip
gradients. :class:`.lip_regressor.LipRegressor` with ``patches > 1`` (an addition
to the paper) covers the lip region with overlapping patches instead, each
predicted by its own reduced regression from the mouth triangles near it.
This module builds them: patch centres by geodesic (edge-path) farthest-point
sampling on the lip triangles, partition-of-unity weights (per lip vertex,
falling off linearly with the edge-path distance to each centre, normalised
over the patches, averaged per triangle), and the mouth triangles within the
input radius of each patch. Distances are in scene units.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

__all__ = ["lip_patches"]

_OVERLAP = 1.0


def lip_patches(rest, faces, mouth_faces, lip_faces, count, input_radius):
    """Overlapping local patches of the lip region and the mouth triangles that feed each one.

    Returns a list of ``(mouth_sel, lip_sel, lip_weight)``: indices into
    ``mouth_faces`` and ``lip_faces`` and the (n_p,) partition-of-unity weight
    of each lip triangle in the patch (weights of a triangle sum to 1 over
    patches), plus the patch spacing (scene units).
    """
    from scipy.sparse.csgraph import dijkstra

    R = rest
    nv = len(R)
    LT = faces[lip_faces]
    MT = faces[mouth_faces]
    if count <= 1:
        return [(np.arange(len(MT)), np.arange(len(LT)), np.ones(len(LT)))], np.inf

    def graph(tris):
        e = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
        w = np.linalg.norm(R[e[:, 0]] - R[e[:, 1]], axis=1)
        return sp.coo_matrix((np.r_[w, w], (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])), shape=(nv, nv)).tocsr()

    lv = np.unique(LT)
    G = graph(LT)
    # farthest-point sampling of patch centres, geodesic on the lip region
    c0 = int(lv[np.argmax(np.linalg.norm(R[lv] - R[lv].mean(axis=0), axis=1))])
    centres = [c0]
    dmin = dijkstra(G, directed=False, indices=c0)[lv]
    big = 1e300
    for _ in range(int(count) - 1):
        i = int(np.argmax(np.where(np.isfinite(dmin), dmin, big)))
        if dmin[i] <= 0:
            break
        centres.append(int(lv[i]))
        dmin = np.minimum(dmin, dijkstra(G, directed=False, indices=lv[i])[lv])
    D = dijkstra(G, directed=False, indices=np.asarray(centres))[:, lv]  # (P, nL)
    P = len(centres)
    Dc = D[:, np.searchsorted(lv, centres)]
    np.fill_diagonal(Dc, np.inf)
    nn = Dc.min(axis=1)
    spacing = float(np.median(nn[np.isfinite(nn)])) if np.isfinite(nn).any() else float(np.ptp(R[lv], axis=0).max())
    cover = float(np.max(np.min(D, axis=0)))
    radius = max(_OVERLAP * spacing, 1.05 * cover)
    Wv = np.clip(1.0 - D / radius, 0.0, None)  # (P, nL)
    Wv /= Wv.sum(axis=0, keepdims=True)
    loc = np.searchsorted(lv, LT)  # (n, 3) into lv
    Wt = Wv[:, loc].mean(axis=2)  # (P, n), columns sum to 1
    rho = spacing if input_radius is None else float(input_radius)
    Gfull = graph(faces)
    out = []
    for p in range(P):
        lip_sel = np.flatnonzero(Wt[p] > 0)
        support = np.unique(LT[lip_sel])
        d = dijkstra(Gfull, directed=False, indices=support, min_only=True, limit=rho)
        mouth_sel = np.flatnonzero(np.isfinite(d[MT]).all(axis=1))
        if len(mouth_sel) < 3:
            mouth_sel = np.arange(len(MT))
        out.append((mouth_sel, lip_sel, Wt[p, lip_sel]))
    return out, spacing
