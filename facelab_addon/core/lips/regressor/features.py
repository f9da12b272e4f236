"""Per-frame inputs of the lip regression: frame checks and mouth deformation-gradient features.

Dinev et al. 2018, "User-Guided Lip Correction for Facial Performance
Capture", §4: the input of the regression is the vector ``y`` of deformation
gradients of the trusted mouth triangles. This module holds what the
regressor (training and prediction) and :mod:`..suggest` (training-frame
suggestion) share for it: validating a (T,V,3) sequence without copying it,
the shape-matrix columns of a block of frames (vertex-major), the dense coefficient operators of a fit, and the whole-mouth feature
rows ``vec(F_t - I)``, all computed a block of ``BLOCK`` frames at a time so
a long float32 sequence is never converted whole; the per-triangle columns
are computed coordinate-major in cache-sized blocks of frames. Positions are scene units;
gradients and features are unitless, float64.
"""

from __future__ import annotations

import numpy as np

from ...errors import FaceLabError, MeshError
from ...geometry.gradients import rest_inverse, shape_matrices

__all__ = ["BLOCK", "as_frames", "frames_of", "gradients", "feature_rows", "mouth_feature_matrix",
           "fold_coefficients", "coordinate_major", "mouth_coefficients", "gradient_features", "patch_operators",
           "fold_directions", "mouth_terms"]

BLOCK = 64  # frames per block of the per-frame loops (working memory ~ block x region size)


def as_frames(a, n_vertices, what, used=None, check_finite=True):
    """Validate frames as a (T,V,3) float32 or float64 array, without copying them.

    float32 and float64 arrays are returned as they are (a (V,3) frame as a
    (1,V,3) view); other dtypes are converted to float64. Callers convert
    only the vertices they read to float64. NaNs are looked for in ``used``
    vertices only, a block of frames at a time (not at all without ``check_finite``: the caller
    checks what it reads and calls again with the check to report).
    """
    A = np.asarray(a)
    if A.dtype != np.float32 and A.dtype != np.float64:
        A = A.astype(np.float64)
    if A.ndim == 2:
        A = A[None]
    if A.ndim != 3 or A.shape[1:] != (n_vertices, 3):
        raise MeshError(
            f"The {what} have shape {np.asarray(a).shape} but the rest mesh has {n_vertices} vertices: "
            f"expected ({n_vertices},3) or (T,{n_vertices},3). The topology differs from the rest mesh; "
            "use frames of the same mesh (same vertex count and order)."
        )
    if A.shape[0] == 0:
        raise FaceLabError(f"No {what} given (0 frames); pass at least one frame.")
    bad = []
    for s in range(0, len(A) if check_finite else 0, BLOCK):
        blk = A[s : s + BLOCK] if used is None else A[s : s + BLOCK, used]
        fin = np.isfinite(blk).reshape(len(blk), -1).all(axis=1)
        bad.extend((s + np.flatnonzero(~fin)).tolist())
        if len(bad) >= 5:
            break
    if bad:
        raise MeshError(
            f"The {what} contain NaN or infinite coordinates in frames {bad[:5]}; "
            "fix or re-import those frames."
        )
    return A



def frames_of(ops, captured, what, used_only):
    """Validated frames of a regressor (:class:`.state.LipOperators` ``ops``): full (T,V,3), or with
    ``used_only`` only its used vertices (T, len(ops.used), 3). Scene units, float32 or float64, not copied."""
    if used_only:
        return as_frames(captured, len(ops.used), what + " (used vertices only)")
    return as_frames(captured, ops.n_vertices, what, ops.used)


def gradients(frames, rinv, verts, local):
    """(T,f,3,3) deformation gradients ``D D_r⁻¹`` of triangles ``local`` (f,3) over vertices ``verts`` of
    frames (T,*,3); ``rinv`` (f,3,3) the inverse rest shape matrices. Unitless, float64."""
    P = frames[:, verts, :]
    return np.matmul(shape_matrices(P, local), rinv)  # (T, f, 3, 3)


def feature_rows(G, center):
    """(T, 9f) feature rows of gradients G (T,f,3,3): flattened row-major, minus the identity when
    ``center == "rest"``."""
    T = G.shape[0]
    if center == "rest":
        G = G - np.eye(3)
    return G.reshape(T, -1)

def mouth_feature_matrix(frames, rest_vertices, faces, mouth_faces, chunk=BLOCK):
    """(T, 9m) mouth gradients minus the identity of validated frames (any float dtype), float64."""
    F = np.asarray(faces, dtype=np.int64)[np.asarray(mouth_faces, dtype=np.int64)]
    verts, inv = np.unique(F, return_inverse=True)
    local = inv.reshape(-1, 3)
    rinv = rest_inverse(np.asarray(rest_vertices, dtype=np.float64), F, name="mouth region")
    T = len(frames)
    out = np.empty((T, 9 * len(F)))
    for s in range(0, T, chunk):
        P = frames[s : s + chunk][:, verts, :]  # shape_matrices converts these to float64
        out[s : s + chunk] = (np.matmul(shape_matrices(P, local), rinv) - np.eye(3)).reshape(len(P), -1)
    return out



def _edge_columns(frames, verts, local):
    """Shape-matrix columns of triangles ``local`` over vertices ``verts`` of frames (T,*,3), vertex-major.

    Returns three (f,3,T) float64 arrays: edge 1, edge 2 and the phantom column ``n / sqrt(|n|)``
    (``n`` the unnormalised normal; zero for a zero-area triangle), per triangle, coordinate and
    frame. Rows are gathered whole (one triangle corner = 3T contiguous numbers), several times
    faster than gathering along the last axis.
    """
    Xr = np.ascontiguousarray(frames[:, verts, :].transpose(1, 2, 0), dtype=np.float64)  # (nv, 3, T)
    return _columns(Xr, local)


def _columns(Xr, local):
    p0 = Xr[local[:, 0]]
    e1 = Xr[local[:, 1]]
    e1 -= p0
    e2 = Xr[local[:, 2]]
    e2 -= p0
    c = np.empty_like(e1)
    a0, a1, a2, b0, b1, b2 = e1[:, 0], e1[:, 1], e1[:, 2], e2[:, 0], e2[:, 1], e2[:, 2]
    np.multiply(a1, b2, out=c[:, 0])
    c[:, 0] -= a2 * b1
    np.multiply(a2, b0, out=c[:, 1])
    c[:, 1] -= a0 * b2
    np.multiply(a0, b1, out=c[:, 2])
    c[:, 2] -= a1 * b0
    s = np.einsum("fit,fit->ft", c, c)
    np.sqrt(s, out=s)
    np.sqrt(s, out=s)
    np.divide(1.0, s, out=s, where=s > 0)
    c *= s[:, None, :]
    return e1, e2, c


def fold_coefficients(local, n_verts, sels, Ws, m):
    """Fold the per-patch coefficient maps into two dense operators, once per fit.

    The reduced mouth coefficients of patch ``p`` are ``z_p = Σ_ik D[i,k] W_p[i,k]`` over the
    shape-matrix entries of its mouth triangles ``sels[p]``. The edge columns (``k = 0, 1``)
    are differences of vertex positions, so their part is one linear map of the mouth
    vertices; only the phantom column (``k = 2``) needs the per-triangle cross product.

    Parameters
    ----------
    local : (m,3) int ndarray
        Mouth triangles in local vertex indices ``0..n_verts-1``.
    n_verts : int
        Number of mouth vertices.
    sels : list of (m_p,) int ndarray
        Mouth triangles (indices into ``local``) read by each patch.
    Ws : list of (3,3,m_p,r_p) ndarray
        ``W[i,k,f,r]`` of each patch (:func:`patch_operators`).
    m : int
        Number of mouth triangles.

    Returns
    -------
    Mx : (3 n_verts, R) float64 ndarray
        ``zᵀ += Mxᵀ X`` for vertex-major positions ``X`` (n_verts, 3, T) flattened to (3 n_verts, T).
    Mc : (3m, R) float64 ndarray
        ``zᵀ += Mcᵀ c`` for the phantom columns ``c`` (m, 3, T) of :func:`_edge_columns`, flattened.
    """
    R = sum(W.shape[-1] for W in Ws)
    Mx = np.zeros((n_verts, 3, R))
    Mc = np.zeros((m, 3, R))
    o = 0
    for sel, W in zip(sels, Ws):
        r = W.shape[-1]
        L = local[sel]
        for i in range(3):
            for k in range(2):
                np.add.at(Mx[:, i, o : o + r], L[:, k + 1], W[i, k])
                np.add.at(Mx[:, i, o : o + r], L[:, 0], -W[i, k])
            Mc[sel, i, o : o + r] = W[i, 2]
        o += r
    return Mx.reshape(3 * n_verts, R), Mc.reshape(3 * m, R)


_CACHE_BLOCK = 32  # frames per pass over the mouth triangles: the (m,3,t) temporaries stay in cache
_SUB_BLOCK = 8  # frames per coordinate-major column pass: its (3,m,t) buffers stay in a 2 MB L2 at m ~ 6k


def coordinate_major(M, n):
    """``Mᵀ`` (R, 3n) contiguous, its columns reordered from (n,3) (vertex-major) to (3,n) (coordinate-major)."""
    return np.ascontiguousarray(M.reshape(n, 3, -1).transpose(2, 1, 0).reshape(M.shape[1], 3 * n))


def _columns_cm(Xc, l0, l1, l2, edges=False):
    """Shape-matrix columns of triangles (l0, l1, l2) from coordinate-major positions Xc (3,nv,t), float64.

    Returns the phantom column ``c = n / sqrt(|n|)`` (3,m,t) (zero for a zero-area triangle), and
    with ``edges`` also ``(e1, e2, c)``. Every array operation runs over contiguous (m·t) runs,
    component by component (no ``np.cross`` temporaries).
    """
    p0 = np.take(Xc, l0, axis=1)
    e1 = np.take(Xc, l1, axis=1)
    e1 -= p0
    e2 = np.take(Xc, l2, axis=1)
    e2 -= p0
    c = p0  # p0 is no longer needed
    tmp = np.empty_like(e1[0])
    for i, (a, b) in enumerate(((1, 2), (2, 0), (0, 1))):
        np.multiply(e1[a], e2[b], out=c[i])
        np.multiply(e1[b], e2[a], out=tmp)
        c[i] -= tmp
    s = np.multiply(c[0], c[0])
    for i in (1, 2):
        np.multiply(c[i], c[i], out=tmp)
        s += tmp
    np.sqrt(s, out=s)
    np.sqrt(s, out=s)
    np.divide(1.0, s, out=s, where=s > 0)
    c *= s
    return (e1, e2, c) if edges else c


def mouth_coefficients(frames, verts, local, MxT, McT):
    """(T, R) reduced mouth coefficients (without the identity's) of frames (T,*,3), float64.

    ``verts`` are the mouth vertices' indices in ``frames``; ``local`` the triangles over them;
    ``MxT``, ``McT`` the folded maps of :func:`fold_coefficients` in :func:`coordinate_major`
    order. ``z = Mxᵀ X + Mcᵀ c``: the phantom columns ``c`` are computed :data:`_SUB_BLOCK`
    frames at a time (cache-resident), the products :data:`_CACHE_BLOCK` frames at a time.
    """
    T, m = len(frames), len(local)
    l0, l1, l2 = (np.ascontiguousarray(local[:, k]) for k in range(3))
    z = np.empty((T, MxT.shape[0]))
    for s in range(0, T, _CACHE_BLOCK):
        G = frames[s : s + _CACHE_BLOCK][:, verts, :]  # (t, nv, 3), the frames' dtype
        t = len(G)
        Xc = np.ascontiguousarray(G.transpose(2, 1, 0), dtype=np.float64)  # (3, nv, t)
        zb = MxT @ Xc.reshape(-1, t)  # (R, t)
        C = np.empty((3, m, t))
        for b in range(0, t, _SUB_BLOCK):
            C[:, :, b : b + _SUB_BLOCK] = _columns_cm(np.ascontiguousarray(Xc[:, :, b : b + _SUB_BLOCK]), l0, l1, l2)
        zb += McT @ C.reshape(3 * m, t)
        z[s : s + t] = zb.T
    return z


def gradient_features(frames, verts, local, rinv, center):
    """(T, 9m) mouth gradients ``D D_r^-1`` (minus the identity when ``center``) of frames (T,*,3), float64.

    Row-major 3×3 per triangle, the layout of ``LipRegressor.mouth_features``; computed from the
    vertex-major shape-matrix columns (no batched 3×3 products).
    """
    e = _edge_columns(frames, verts, local)
    m, T = e[0].shape[0], e[0].shape[2]
    Y = np.empty((m, 3, 3, T))
    for j in range(3):
        r0, r1, r2 = (rinv[:, k, j, None, None] for k in range(3))  # (m,1,1)
        y = Y[:, :, j, :]
        np.multiply(e[0], r0, out=y)
        y += e[1] * r1
        y += e[2] * r2
        if center:
            y[:, j, :] -= 1.0
    return np.ascontiguousarray(Y.transpose(3, 0, 1, 2)).reshape(T, 9 * m)


def patch_operators(nI, rinv, lip_sel, w, Dp, UY, UX, th, center):
    """A fitted patch of the regressor folded into the prediction: ``(Z, W, z_ident)``.

    ``rinv`` (m_p,3,3) are the inverse rest shape matrices of the patch's mouth triangles,
    ``Dp`` the divergence of its lip triangles on the ``nI`` interior vertices, ``w`` its
    partition-of-unity weights, ``UY``, ``UX``, ``th`` its fit. ``Z`` (nI*3, rY): divergence on
    the interior vertices of the patch's weighted lip gradients per unit coefficient; ``W``
    (3, 3, m_p, rY): the mouth coefficients ``U_Yᵀ y`` as sums over shape-matrix entries;
    ``z_ident`` (rY,): the coefficients of the identity gradients (zeros unless ``center``).
    """
    rY = th.shape[1]
    # lip gradients of this patch per unit coefficient, weighted: (rY, n_p, 3, 3)
    Mp = (UX @ th).T.reshape(rY, len(lip_sel), 3, 3) * w[None, :, None, None]
    # divergence of those gradients on the interior vertices: (nI*3, rY)
    Fr = Mp.transpose(1, 3, 0, 2).reshape(3 * len(lip_sel), rY * 3)  # rows (t, a), cols (j, c): F[c, a]
    Z = (Dp @ Fr).reshape(nI, rY, 3).transpose(0, 2, 1).reshape(nI * 3, rY)
    # U_Yᵀ vec(D_d D_r^-1) = Σ_ik D_d[i,k] W[i,k]:  W[i,k,f,r] = Σ_j U[f,i,j,r] Ri[f,k,j]
    mp = len(rinv)
    U4 = UY.reshape(mp, 3, 3, rY).transpose(0, 2, 1, 3).reshape(mp, 3, 3 * rY)  # (f, j, (i, r))
    Wf = np.matmul(rinv, U4).reshape(mp, 3, 3, rY)  # (f, k, i, r)
    W = np.ascontiguousarray(Wf.transpose(2, 1, 0, 3))  # (i, k, f, r)
    z0 = np.tile(np.eye(3).ravel(), mp) @ UY if center else np.zeros(rY)
    return Z, W, z0


def fold_directions(A, rinv, local, n_verts):
    """(Mx, Mc) of :func:`fold_coefficients` giving ``Aᵀ vec(D D_r^-1)`` for feature-space directions A (9m, c)."""
    m = len(local)
    W = np.einsum("fijc,fkj->ikfc", A.reshape(m, 3, 3, -1), rinv)  # W[i,k,f,c] = Σ_j A[f,i,j,c] Ri[f,k,j]
    return fold_coefficients(local, n_verts, [np.arange(m)], [W], m)


def mouth_terms(frames, verts, local, MxT, McT, P):
    """Folded projections and squared norms of the mouth gradients of frames (T,*,3), without forming them.

    ``MxT``, ``McT``: folded maps (:func:`fold_coefficients`) in :func:`coordinate_major` order.
    Returns ``(Z, sq)``: ``Z`` (T, c) the products ``Mxᵀ X + Mcᵀ c`` (projections of
    ``vec(D D_r^-1)`` on the folded directions), ``sq`` (T,) ``Σ_f ||D_f D_r,f^-1||²`` computed
    as ``Σ_f <D_fᵀ D_f, P_f>`` with ``P = D_r^-1 D_r^-T`` (m,3,3): six dot products per triangle.
    The columns are computed coordinate-major, :data:`_SUB_BLOCK` frames at a time (:func:`_columns_cm`).
    """
    T, m = len(frames), len(local)
    l0, l1, l2 = (np.ascontiguousarray(local[:, k]) for k in range(3))
    Pw = [(k, j, (2.0 if j > k else 1.0) * np.ascontiguousarray(P[:, k, j])) for k in range(3) for j in range(k, 3)]
    Z = np.empty((T, MxT.shape[0]))
    sq = np.zeros(T)
    for s in range(0, T, _CACHE_BLOCK):
        G = frames[s : s + _CACHE_BLOCK][:, verts, :]
        t = len(G)
        Xc = np.ascontiguousarray(G.transpose(2, 1, 0), dtype=np.float64)  # (3, nv, t)
        zb = MxT @ Xc.reshape(-1, t)
        C = np.empty((3, m, t))
        for b in range(0, t, _SUB_BLOCK):
            e = _columns_cm(np.ascontiguousarray(Xc[:, :, b : b + _SUB_BLOCK]), l0, l1, l2, edges=True)
            C[:, :, b : b + _SUB_BLOCK] = e[2]
            for k, j, w in Pw:
                g = np.einsum("imt,imt->mt", e[k], e[j])  # (m, t') column products
                sq[s + b : s + b + g.shape[1]] += w @ g
        zb += McT @ C.reshape(3 * m, t)
        Z[s : s + t] = zb.T
    return Z, sq
