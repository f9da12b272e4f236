"""Prediction of a fitted lip regressor: interior lip positions of captured frames, whole or a chunk at a time.

Dinev et al. 2018, "User-Guided Lip Correction for Facial Performance Capture", §4: the corrected
inner lips are the Poisson reconstruction of the predicted gradients ``x = θ y`` with the lip border
held at its captured positions. Prediction is linear in (reduced mouth coefficients ``z``, border
positions ``x_B``): ``x_I = L_II⁻¹ (Zdiv z + b_ident - L_IB x_B)``, evaluated through dense maps
while they are small (:func:`dense_solution`, float32 in :mod:`.predict32`), else one shared sparse
back-substitution. The functions take the regressor's :class:`.state.LipOperators` ``ops`` and
:class:`.state.TrainedModel` ``model`` and change neither (except ``model.cache`` and ``ops.H``, the
operators derived on first use). Positions are scene units; features are unitless.
"""

from __future__ import annotations

import numpy as np

from ...errors import FaceLabError, PredictionError
from ...geometry.linsolve import idle_core, one_blas_thread
from .features import (
    as_frames,
    coordinate_major,
    fold_directions,
    frames_of,
    gradient_features,
    gradients,
    mouth_coefficients,
    mouth_terms,
)
from .guards import check_prediction, checked_out, same_array
from .model_choice import damping_weights, expected_error
from .predict32 import F32_BLOCK, check_moves, Float32Prediction, PredictionWork, put_rows
from .state import LipOperators, TrainedModel

__all__ = ["mouth_rows", "coefficients", "residual_norms", "interior", "undamped_interior", "frame_damping",
           "dense_solution", "predict_frames", "predict_lip_gradients", "lip_corrections", "correct_chunk",
           "mouth_projections", "expected_change"]

_DENSE_MAX = 20_000_000  # numbers in the dense Poisson maps of dense_solution (160 MB)


def _blas_threads():
    """One BLAS thread on a busy machine (more threads would only spin on the shared cores), all of them when a
    core is idle."""
    import contextlib

    return contextlib.nullcontext() if idle_core() else one_blas_thread()


def mouth_rows(ops: LipOperators, frames, used_only=False) -> np.ndarray:
    """(T, 9m) mouth features of validated frames (T,*,3) (any float dtype; computed in float64), unitless.

    ``frames`` are full frames, or with ``used_only`` only the used vertices (``ops.used``).
    """
    verts = ops.mouth_u if used_only else ops.mouth_verts
    return gradient_features(frames, verts, ops.mouth_local, ops.mouth_rinv, ops.center == "rest")


def coefficients(ops: LipOperators, model: TrainedModel, frames, used_only=False) -> np.ndarray:
    """Reduced coefficients ``z_p = U_Y,pᵀ y_p`` of all patches, (T, Σ rY) float64, for validated frames.

    ``y = vec(D_d D_r^-1)`` is linear in the shape matrix ``D_d``, so
    ``U_Yᵀ y = Σ D_d[i,k] W[i,k]`` with ``W`` folded at fit time; the edge columns of ``D_d``
    are linear in the positions, so a frame costs one product with its mouth vertices, the
    phantom columns of its mouth triangles and three more products
    (:func:`.features.fold_coefficients`).
    """
    verts = ops.mouth_u if used_only else ops.mouth_verts
    if "cm" not in model.cache:
        nv, m = len(ops.mouth_verts), len(ops.mouth_faces)
        model.cache["cm"] = (coordinate_major(model.Mx, nv), coordinate_major(model.Mc, m))
    return mouth_coefficients(frames, verts, ops.mouth_local, *model.cache["cm"]) - model.z_ident


def residual_norms(model: TrainedModel, Y) -> np.ndarray:
    """(T,) norms of mouth features ``Y`` (T, 9m) outside the global training span (unitless)."""
    UY = model.data.UY
    r = Y - (Y @ UY) @ UY.T
    return np.sqrt(np.sum(r * r, axis=1))


def interior(ops: LipOperators, model: TrainedModel, A, used_only=False, z=None, r2=None):
    """``(xi, xc)``: predicted and captured interior lip positions (t, nI, 3) float64 of validated frames A.

    With damping (``model.error_model`` set) the correction ``xi - xc`` is scaled per frame (``r2`` (t,): the
    frames' squared distances from the training span, computed from ``A`` when not given); ``z`` the frames'
    :func:`coefficients` when already known.
    """
    xi, xc = undamped_interior(ops, model, A, used_only, z)
    if model.error_model is not None:
        if r2 is None:
            r2 = residual_norms(model, mouth_rows(ops, A, used_only)) ** 2
        c = xi - xc
        xi = xc + frame_damping(model, c, r2)[:, None, None] * c
    return xi, xc


def frame_damping(model: TrainedModel, c, r2) -> np.ndarray:
    """(t,) damping weights of corrections c (t, nI, 3) at squared span distances r2 (t,)
    (:func:`.model_choice.damping_weights` against :func:`.model_choice.expected_error`)."""
    S = expected_error(model.error_model, model.whole_weight, r2)
    return damping_weights(np.einsum("tij,tij->t", c, c), S)


def undamped_interior(ops: LipOperators, model: TrainedModel, A, used_only=False, z=None):
    """:func:`interior` without damping."""
    iv, bv = (ops.iv_u, ops.bv_u) if used_only else (ops.interior_vertices, ops.border_vertices)
    nI, t = len(iv), len(A)
    z = coefficients(ops, model, A, used_only) if z is None else z
    xb = np.asarray(A[:, bv, :], dtype=np.float64).transpose(1, 0, 2).reshape(len(bv), 3 * t)
    # the blend α·whole + (1-α)·correction: x_I = K z + α (x_0 - H x_B) + (1 - α) x_captured,I
    a = model.whole_weight
    xc = np.asarray(A[:, iv, :], dtype=np.float64)
    dense = dense_solution(ops, model)
    if dense is not None:  # two dense products instead of a sparse solve
        K, H, x0 = dense
        xi = (K @ z.T).reshape(nI, 3, t).transpose(0, 2, 1).reshape(nI, 3 * t)
        xi -= (a * H) @ xb if a != 1.0 else H @ xb
        xi = xi.reshape(nI, t, 3).transpose(1, 0, 2)
        if x0 is not None:
            xi += a * x0[None]
    else:
        rhs = (model.Zdiv @ z.T).reshape(nI, 3, t).transpose(0, 2, 1)  # (nI, t, 3)
        if ops.center == "rest":
            rhs = rhs + a * ops.b_ident[:, None, :]
        rhs = rhs.reshape(nI, 3 * t) - a * (ops.L_IB @ xb)
        xi = ops.factor.solve(rhs).reshape(nI, t, 3).transpose(1, 0, 2)
    if a != 1.0:
        xi += (1.0 - a) * (xc + model.x_b[None])
    return xi, xc


def dense_solution(ops: LipOperators, model: TrainedModel):
    """``(K, H, x0)`` of the Poisson solve as dense maps, or None when they would be large.

    The interior positions are linear in the coefficients ``z`` and the border positions:
    ``x_I = L_II⁻¹ (Zdiv z + b_ident - L_IB x_B) = K z + x0 - H x_B`` with ``K = L_II⁻¹ Zdiv``
    (nI*3, R) (per coordinate), ``H = L_II⁻¹ L_IB`` (nI, nB) and ``x0 = L_II⁻¹ b_ident`` (nI, 3) (None
    unless ``center="rest"``). Built once per fit from the factor (``H`` once per regressor, kept in
    ``ops.H``); two dense products per chunk replace the chunk's sparse back-substitution. Used while
    ``K`` and ``H`` together stay below :data:`_DENSE_MAX` numbers.
    """
    nI, nB, R = len(ops.interior_vertices), len(ops.border_vertices), model.Zdiv.shape[1]
    if nI * (nB + 3 * R) > _DENSE_MAX:
        return None
    if "dense" in model.cache:
        return model.cache["dense"]
    if ops.H is None:
        ops.H = ops.factor.solve(ops.L_IB.toarray())  # (nI, nB)
    Zr = model.Zdiv.reshape(nI, 3 * R)  # rows: vertex; columns: (coordinate, coefficient)
    K = ops.factor.solve(Zr).reshape(nI, 3, R).reshape(3 * nI, R)
    x0 = ops.factor.solve(ops.b_ident) if ops.center == "rest" else None
    model.cache["dense"] = (K, ops.H, x0)
    return model.cache["dense"]


def _float32_maps(ops, model):
    """The :class:`.predict32.Float32Prediction` of the fit, or None when the dense maps would be large."""
    dense = dense_solution(ops, model)
    if dense is None:
        return None
    if model.cache.get("f32", (None,))[0] is not dense:
        model.cache["f32"] = (dense, Float32Prediction(ops, model, dense))
    return model.cache["f32"][1]


def predict_frames(ops: LipOperators, model: TrainedModel, captured, out, chunk):
    """``LipRegressor.predict``: check every frame's result, then write (see its docstring for the arguments).

    In place, each block of frames is written while its rows are still in cache and the captured
    interior positions are kept (frames' dtype): a refusal or any error restores them, so ``out``
    ends as it was.
    """
    A = as_frames(captured, ops.n_vertices, "captured frames", ops.used, check_finite=False)
    T, chunk = len(A), int(chunk)
    if chunk < 1:
        raise FaceLabError(f"chunk must be at least 1 frame, got {chunk}; use the default 256.")
    out3 = None if out is None else checked_out(out, A)
    iv = ops.interior_vertices
    in_place = out3 is not None and same_array(out3, A)
    # in place: the captured interior (to restore); else the checked results, written at the end
    keep = np.empty((T, len(iv), 3), A.dtype if in_place else np.float64 if out3 is None else out3.dtype)
    maps = None if model.error_model is not None else _float32_maps(ops, model)  # damping: the float64 path
    done, bad = 0, False
    step = min(chunk, F32_BLOCK, T) if maps is not None else min(chunk, T)
    xbuf = np.empty((step, len(iv), 3), A.dtype) if in_place else None  # one block's result
    work = np.empty((step, len(iv), 3), np.result_type(keep.dtype, A.dtype))  # its changes (checks)
    ws = PredictionWork()  # the float32 maps' work buffers
    try:
        with _blas_threads():
            for s in range(0, T, step):
                Ab = A[s : s + step]
                t = len(Ab)
                if maps is None:
                    r = _interior_checked(ops, model, Ab)
                else:  # in place: the captured rows go straight to keep; else the result does
                    r = maps.interior(Ab, xbuf[:t], keep[s : s + t], ws) if in_place else maps.interior(
                        Ab, keep[s : s + t], None, ws)
                if r is None:
                    bad = True
                    break
                check_moves(*r, s, ops.mouth_size, work)
                if in_place:
                    if maps is None:
                        keep[s : s + t] = r[1]
                    put_rows(Ab, iv, r[0])
                    done = s + t
                elif maps is None:
                    keep[s : s + t] = r[0]
    except BaseException:
        if done:
            put_rows(A[:done], iv, keep[:done])
        raise
    if bad:  # raises MeshError naming the frames with NaNs (the whole shot is scanned for them)
        if done:
            put_rows(A[:done], iv, keep[:done])
        as_frames(captured, ops.n_vertices, "captured frames", ops.used)
    if in_place:
        return out
    if out is None:
        out3 = A.astype(np.float64)  # always a copy
    elif not same_array(out3, A):
        out3[...] = A
    put_rows(out3, iv, keep)
    return out3 if out is None else out


def _interior_checked(ops, model, Ab):
    """``(xi, xc)`` of frames Ab (t,V,3) through the sparse solve (float64), None when a used row is not finite."""
    U = Ab[:, ops.used]
    return interior(ops, model, U, used_only=True) if np.isfinite(U).all() else None


def predict_lip_gradients(ops: LipOperators, model: TrainedModel, A) -> np.ndarray:
    """(T,n,3,3) float64 predicted lip gradients ``x = θ y`` of validated frames A (T,V,3), blended over patches
    and models; unitless. Raises PredictionError naming frames whose gradients are not finite."""
    T = len(A)
    z = coefficients(ops, model, A)
    x = np.zeros((T, len(ops.lip_faces), 9))
    o = 0
    for (_, lip_sel, w), (UX, th, _) in zip(ops.patches, model.pfit):
        r = th.shape[1]
        xp = (z[:, o : o + r] @ th.T) @ UX.T  # (T, 9 n_p)
        x[:, lip_sel] += xp.reshape(T, len(lip_sel), 9) * w[None, :, None]
        o += r
    x = x.reshape(T, -1, 3, 3)
    a = model.whole_weight
    if ops.center == "rest":
        x = x + a * np.eye(3)
    if a != 1.0:  # the correction model adds the captured gradients
        x = x + (1.0 - a) * (gradients(A, ops.lip_rinv, ops.lip_verts, ops.lip_local) + model.B.reshape(-1, 3, 3))
    bad = np.flatnonzero(~np.isfinite(x).reshape(T, -1).all(axis=1))
    if bad.size:
        raise PredictionError("The predicted lip gradients of {frames} are not finite; check those frames "
                              "for extreme mouth shapes and retrain with frames like them.", bad[:20])
    return x


def lip_corrections(ops: LipOperators, model: TrainedModel, captured, used_only=False, first=0) -> np.ndarray:
    """(T, nI, 3) float64 predicted minus captured interior lip positions of frames, scene units.

    ``captured`` (T,V,3), or (T, len(ops.used), 3) with ``used_only``; ``first`` the index of its first
    frame in the shot (for the frame indices of a PredictionError).
    """
    A = frames_of(ops, captured, "captured frames", used_only)
    xi, xc = interior(ops, model, A, used_only)
    check_prediction(xi, xc, first, ops.mouth_size)
    xi -= xc
    return xi


def _norms(ops, model, Z, sq):
    """``(U_Yᵀ y, ||y||²)`` from folded projections ``Z`` whose last column is the identity's."""
    c = 1.0 if ops.center == "rest" else 0.0
    return Z[:, :-1] - model.span_ident, sq - 2 * c * Z[:, -1] + 3 * c * len(ops.mouth_faces)


def correct_chunk(ops: LipOperators, model: TrainedModel, captured, used_only=False, first=0):
    """:func:`lip_corrections` and the mouth's distance from the training span, in one pass over the mouth.

    Returns ``(corrections (t,nI,3) scene units, extrapolation (t,), feature_sq (t,))``: the extrapolation
    score (from ``||y||² - ||U_Yᵀ y||²``, never forming ``y``, over ``model.data.sigma``) and ``||y||²``.
    Arguments as :func:`lip_corrections`.
    """
    A = frames_of(ops, captured, "captured frames", used_only)
    verts = ops.mouth_u if used_only else ops.mouth_verts
    if "cm_all" not in model.cache:
        nv, m = len(ops.mouth_verts), len(ops.mouth_faces)
        model.cache["cm_all"] = (coordinate_major(model.Mx_all, nv), coordinate_major(model.Mc_all, m))
    with _blas_threads():
        Z, sq = mouth_terms(A, verts, ops.mouth_local, *model.cache["cm_all"], ops.mouth_P)
        R = model.Mx.shape[1]
        zU, sq = _norms(ops, model, Z[:, R:], sq)
        r2 = np.clip(sq - np.sum(zU * zU, axis=1), 0.0, None)
        xi, xc = interior(ops, model, A, used_only, z=Z[:, :R] - model.z_ident, r2=r2)
    check_prediction(xi, xc, first, ops.mouth_size)
    res = np.sqrt(r2)
    return xi - xc, res / model.data.sigma, sq


def mouth_projections(ops: LipOperators, model: TrainedModel, captured, directions, used_only=False):
    """``(Aᵀ y (t,d), ||y||² (t,))`` of frames' mouth features ``y`` on directions ``A`` (9m, d), never forming ``y``."""
    A = frames_of(ops, captured, "captured frames", used_only)
    D = np.asarray(directions, dtype=np.float64)
    if model.cache.get("dir_fold", (None,))[0] is not D:
        ident = np.tile(np.eye(3).ravel(), len(ops.mouth_faces))[:, None]
        ext = np.hstack([D, ident])
        nv, m = len(ops.mouth_verts), len(ops.mouth_faces)
        Mx, Mc = fold_directions(ext, ops.mouth_rinv, ops.mouth_local, nv)
        model.cache["dir_fold"] = (D, (coordinate_major(Mx, nv), coordinate_major(Mc, m)),
                                   (ident.T @ D).ravel() if ops.center == "rest" else np.zeros(D.shape[1]))
    _, (Mx, Mc), d_ident = model.cache["dir_fold"]
    verts = ops.mouth_u if used_only else ops.mouth_verts
    Z, sq = mouth_terms(A, verts, ops.mouth_local, Mx, Mc, ops.mouth_P)
    c = 1.0 if ops.center == "rest" else 0.0
    return Z[:, :-1] - d_ident, sq - 2 * c * Z[:, -1] + 3 * c * len(ops.mouth_faces)


def expected_change(ops: LipOperators, model: TrainedModel, damping, corrections, extrapolation) -> np.ndarray:
    """(t,) expected change of each frame's RMS interior lip error with its predicted correction, scene units
    (positive: expected worse than the capture); see ``LipRegressor.expected_change``.

    ``corrections`` (t, nI, 3) as :func:`correct_chunk` returned them (damped when ``damping``),
    ``extrapolation`` (t,) their scores.
    """
    c = np.asarray(corrections, dtype=np.float64)
    cd2 = np.einsum("tij,tij->t", c, c)
    r2 = (np.asarray(extrapolation, dtype=np.float64) * model.data.sigma) ** 2
    em, a = model.expected_model, model.whole_weight
    S = expected_error(em, a, r2) if em else np.zeros_like(r2)
    miss = S + ((1.0 - a) ** 2 * em["floor"] if em else 0.0)  # with the correction model's floor: every frame
    if damping:  # undo the damping: |s c|² = c2³ / (c2 + S)² is increasing in c2 (bisection, log scale)
        lo, hi = np.maximum(cd2, 1e-300), np.maximum(cd2 + 2 * S + np.sqrt(cd2 * S) * 4, 1e-300)
        for _ in range(60):
            mid = np.sqrt(lo * hi)
            big = mid ** 3 / np.maximum(mid + S, 1e-300) ** 2 > cd2
            hi, lo = np.where(big, mid, hi), np.where(big, lo, mid)
        c2 = np.sqrt(lo * hi)
        s = np.divide(c2, c2 + S, out=np.ones_like(c2), where=c2 + S > 0)
    else:
        c2, s = cd2, np.ones_like(cd2)
    C = np.maximum(c2 - miss, 0.0)
    after = (1 - s) ** 2 * C + s * s * miss
    nI = max(len(ops.interior_vertices), 1)
    return np.sqrt(after / nI) - np.sqrt(C / nI)
