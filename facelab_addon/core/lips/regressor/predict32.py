"""Float32 evaluation of the fitted lip prediction: the hot path of ``LipRegressor.predict``.

Dinev et al. 2018, "User-Guided Lip Correction for Facial Performance Capture", §4: the corrected
inner lips are a Poisson reconstruction from the predicted gradients, with the lip border held at
its captured positions. :func:`.prediction.dense_solution` folds it into dense maps (interior
positions linear in the reduced mouth coefficients and the border positions); this module
evaluates those maps in float32 on changes from the rest pose, a block of frames per matrix
product, with the record gathers and scatters, the work buffers and the block check of a
prediction. Positions are scene units; the maps are unitless.
"""

from __future__ import annotations

import numpy as np

from .guards import check_prediction

__all__ = ["check_moves", "put_rows", "Float32Prediction", "PredictionWork", "F32_BLOCK"]


def check_moves(xi, xc, first, mouth_size, work=None):
    """:func:`.guards.check_prediction` of predicted and captured positions (t, n, 3), from each frame's largest
    coordinate change (a lower bound of its largest move, within sqrt 3): the exact check runs on a block only
    when one of its frames comes near the limit or is not finite. ``work``: a buffer for the changes."""
    d = np.subtract(xi, xc, out=None if work is None else work[: len(xi)]).reshape(len(xi), -1)
    big = np.maximum(d.max(axis=1), -d.min(axis=1))  # NaN when a change is NaN
    if not (np.all(np.isfinite(big)) and np.all(big * np.sqrt(3.0) <= mouth_size)):
        check_prediction(xi, xc, first, mouth_size)


F32_BLOCK = 128  # frames per float32 prediction block (products of 128 rows run near the BLAS peak)
_F32_SUB = 8  # frames per pass of the phantom columns: the (3, t, m) float32 temporaries stay in L2


def _rows(A, idx, flat=None, out=None):
    """(t, len(idx), 3) rows ``idx`` of frames A (t,V,3) in A's dtype (or into ``out``, contiguous, A's dtype);
    ``flat`` = ``3 idx + (0,1,2)`` gathers them from the (t, 3V) view as single numbers (a flat gather, cheaper
    than the fancy indexing of ``A[:, idx]``)."""
    if flat is None or A.strides[2] != A.itemsize or A.strides[1] != 3 * A.itemsize:
        if out is None:
            return A[:, idx]
        out[...] = A[:, idx]
        return out
    if out is None:
        return A.reshape(len(A), -1)[:, flat].reshape(len(A), len(idx), 3)
    np.take(A.reshape(len(A), -1), flat, axis=1, out=out.reshape(len(A), -1), mode="clip")
    return out


def put_rows(A, idx, X):
    """``A[:, idx] = X`` (X (t, len(idx), 3), cast to A's dtype), written one 3-number record per vertex
    (one void-record scatter instead of the three-number fancy assignment ``A[:, idx] = X``)."""
    if A.strides[2] != A.itemsize:
        A[:, idx] = X
        return
    vd = np.dtype((np.void, 3 * A.itemsize))
    A.view(vd)[..., 0][:, idx] = np.ascontiguousarray(X, dtype=A.dtype).view(vd)[..., 0]


class Float32Prediction:
    """A fitted prediction (:class:`.state.TrainedModel`) folded into float32 maps of displacements from the rest pose.

    ``x_I = K z + x0 - H x_B`` (:func:`.prediction.dense_solution`) with the coefficients
    ``z = Mxᵀ X + Mcᵀ c - z_ident`` (:func:`.features.fold_coefficients`) is evaluated in float32 on the
    displacements ``d = X - X_rest`` (formed in float64, so float32 and float64 frames of the same
    positions give the same result) and on the phantom columns' changes ``c - c_rest`` (``c`` from
    positions about the mouth's centre): every float32 number is a change from the rest pose, and the
    constant ``x_I(X_rest)`` is added in float64 (the rest pose itself predicts exactly what the float64
    maps do). A block of t frames costs two products for the coefficients (``d @ Mx``, ``c @ Mc``) and
    two for the positions: the border displacements of all three coordinates as 3t rows times ``-α Hᵀ``,
    and ``z @ K``; with the correction model (``α < 1``) the captured interior's change from rest, times
    ``1 - α``, is added in float64. Float32 rounding moves a predicted vertex by
    about 1e-8 of the mouth's size (``benchmarks/scale.py``), far below the 0.01 mm storage tolerance.
    """

    def __init__(self, ops, model, dense):
        K, H, x0 = dense
        f32 = np.float32
        mv, bv, iv = ops.mouth_verts, ops.border_vertices, ops.interior_vertices
        m, nI, nB, R = len(ops.mouth_local), len(iv), len(bv), model.Mx.shape[1]
        ref = ops.rest
        self.idx = (mv, bv, iv)
        self.flat = tuple((3 * x[:, None] + np.arange(3)).ravel() for x in self.idx)
        self.ref = (ref[mv], ref[bv])
        self.l = tuple(np.ascontiguousarray(ops.mouth_local[:, k]) for k in range(3))
        Rm = ref[mv]
        e1, e2 = Rm[self.l[1]] - Rm[self.l[0]], Rm[self.l[2]] - Rm[self.l[0]]
        c = np.cross(e1, e2)
        c /= np.sqrt(np.linalg.norm(c, axis=1))[:, None]  # rest triangles are not degenerate (rest_inverse)
        # the phantom columns are computed from positions relative to the mouth's centre (a few cm: float32
        # edges to 1e-5 relative, far below any capture noise); the rest's columns are computed the same way,
        # so the rest pose gives c - c_rest = 0 exactly
        self.rest_local = np.ascontiguousarray((Rm - Rm.mean(axis=0)).T[:, None, :], dtype=f32)  # (3, 1, nv)
        self.rest_c = 0.0
        self.rest_c = self._phantom(self.rest_local, np.empty((3, 1, m), f32), PredictionWork())
        self.Mx = model.Mx.astype(f32)  # (3nv, R), rows (vertex, coordinate)
        self.Mc = np.ascontiguousarray(model.Mc.reshape(m, 3, R).transpose(1, 0, 2), dtype=f32)  # (3, m, R)
        z_ref = model.Mx.T @ Rm.ravel() + model.Mc.T @ c.ravel() - model.z_ident  # (R,) coefficients of X_rest
        K3 = K.reshape(nI, 3, R)
        self.K = np.ascontiguousarray(K3.transpose(2, 1, 0).reshape(R, 3 * nI), dtype=f32)  # columns (coordinate, vertex)
        # the blend of the whole-motion and correction models (LipRegressor.whole_weight α):
        # x_I = K z + α (x0 - H x_B) + (1 - α) x_captured,I
        a = self.alpha = float(model.whole_weight)
        self.Ht = np.ascontiguousarray(-a * H.T, dtype=f32)  # (nB, nI)
        self.ref_i = ref[iv]
        self.base = K3 @ z_ref + a * (-H @ ref[bv] + (0.0 if x0 is None else x0)) + (1 - a) * (self.ref_i + model.x_b)

    def _phantom(self, Xc, out, w):
        """``c - c_rest`` (3, t, m) float32 into ``out`` from coordinate-major mouth positions Xc (3, t, nv)
        (``rest_local`` frame), with work buffers ``w`` (:class:`PredictionWork`). Indices are valid, so the gathers use
        ``mode="clip"`` (unbuffered); contiguous corner arrays, no masked division and no fresh temporaries
        (each would be page-faulted in anew).
        """
        t, m = out.shape[1], out.shape[2]
        l0, l1, l2 = self.l
        c = np.take(Xc, l0, axis=2, out=out, mode="clip")  # p0, then the cross product
        e1 = np.take(Xc, l1, axis=2, out=w.get("e1", (3, t, m))[:, :t], mode="clip")
        e1 -= c
        e2 = np.take(Xc, l2, axis=2, out=w.get("e2", (3, t, m))[:, :t], mode="clip")
        e2 -= c
        tmp, s = w.get("tmp", (t, m))[:t], w.get("s", (t, m))[:t]
        for i, (a, b) in enumerate(((1, 2), (2, 0), (0, 1))):
            np.multiply(e1[a], e2[b], out=c[i])
            np.multiply(e1[b], e2[a], out=tmp)
            c[i] -= tmp
        np.multiply(c[0], c[0], out=s)
        for i in (1, 2):
            np.multiply(c[i], c[i], out=tmp)
            s += tmp
        np.sqrt(s, out=s)
        np.sqrt(s, out=s)
        np.maximum(s, np.finfo(np.float32).tiny, out=s)  # a zero-area triangle: c = 0 / tiny = 0
        c /= s
        c -= self.rest_c
        return c

    def interior(self, Ab, xi, xc=None, w=None):
        """``(xi, xc)``: predicted and captured interior lip positions (t,nI,3) of frames Ab (t,V,3), written into
        ``xi`` (any float dtype) and ``xc`` (Ab's dtype; a new array if None); None when a row read (mouth,
        border or interior lip vertex) is not finite. ``w``: work buffers (:class:`PredictionWork`) kept across blocks."""
        mv, bv, iv = self.idx
        t, f32, w = len(Ab), np.float32, PredictionWork() if w is None else w
        nv, nB, m, R = len(mv), len(bv), self.Mc.shape[1], self.Mx.shape[1]
        G = _rows(Ab, mv, self.flat[0], w.get("G", (t, nv, 3), Ab.dtype)[:t])
        GB = _rows(Ab, bv, self.flat[1], w.get("GB", (t, nB, 3), Ab.dtype)[:t])
        xc = _rows(Ab, iv, self.flat[2], xc)
        if not (np.isfinite(G).all() and np.isfinite(GB).all() and np.isfinite(xc).all()):
            return None
        rm, rb = self.ref  # float64: float32 and float64 frames of the same positions give the same displacements
        D = w.get("D", (t, nv, 3))[:t]
        np.copyto(D, np.subtract(G, rm, out=w.get("D64", (t, nv, 3), np.float64)[:t]))
        z, zc = w.get("z", (t, R))[:t], w.get("zc", (t, R))[:t]
        np.matmul(D.reshape(t, -1), self.Mx, out=z)
        Xc = np.add(D.transpose(2, 0, 1), self.rest_local, out=w.get("Xc", (3, t, nv))[:, :t])  # about the centre
        C = w.get("C", (3, t, m))[:, :t]
        for b in range(0, t, _F32_SUB):
            self._phantom(Xc[:, b : b + _F32_SUB], C[:, b : b + _F32_SUB], w)
        for i in range(3):
            z += np.matmul(C[i], self.Mc[i], out=zc)
        dB = w.get("dB", (t, 3, nB))[:t]
        np.copyto(dB, np.subtract(GB, rb, out=w.get("dB64", (t, nB, 3), np.float64)[:t]).transpose(0, 2, 1))
        P = np.matmul(dB.reshape(3 * t, nB), self.Ht, out=w.get("P", (3 * t, len(iv)))[: 3 * t])
        P += np.matmul(z, self.K, out=w.get("PK", (t, 3 * len(iv)))[:t]).reshape(3 * t, -1)
        P = P.reshape(t, 3, -1)  # (t, 3, nI) interior displacements from x_I(X_rest)
        for i in range(3):
            np.add(P[:, i], self.base[:, i], out=xi[:, :, i])
        if self.alpha != 1.0:  # the correction model's captured interior, as a change from the rest pose
            xi += (1.0 - self.alpha) * np.subtract(xc, self.ref_i, dtype=np.float64)
        return xi, xc


class PredictionWork(dict):
    """Work buffers kept across the blocks of one prediction (a fresh large temporary would be page-faulted in anew
    on every block). One per prediction: a buffer keeps the dtype it was made with."""

    def get(self, name, shape, dtype=np.float32):
        """A buffer of at least ``shape`` (allocated on first use, or when larger; callers take a slice)."""
        if name not in self or any(a < b for a, b in zip(self[name].shape, shape)):
            self[name] = np.empty(shape, dtype)
        return self[name]
