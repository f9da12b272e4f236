"""Checks of the lip regression's settings, inputs and outputs.

Dinev et al. 2018, "User-Guided Lip Correction for Facial Performance
Capture", §4 gives the regression; this module holds what
:class:`.lip_regressor.LipRegressor` checks around it so that every bad input
or implausible result ends in a :class:`~facelab_addon.core.errors.FaceLabError`
naming the problem and the fix: the rest mesh, the settings, the ``out``
array of :meth:`~.lip_regressor.LipRegressor.predict` (float32/float64, the
frames' shape, writeable), precomputed mouth features and each predicted frame (finite, and no vertex
moved further than the mouth region is wide). Positions are scene units.
"""

from __future__ import annotations

import numpy as np

from ...errors import FaceLabError, FrameError, MeshError, PredictionError

__all__ = ["check_settings", "same_array", "checked_mesh", "checked_out", "check_features", "check_prediction"]


def check_settings(ridge, rtol, atol, patches, input_radius):
    """Refuse regression settings out of range (FaceLabError naming the setting and a usable value)."""
    if not (ridge == "loo" or (_is_number(ridge) and float(ridge) >= 0)):
        raise FaceLabError(f"ridge must be a non-negative number or 'loo', got {ridge!r}; use 0 (the paper).")
    for name, v in (("rtol", rtol), ("atol", atol)):
        if not (_is_number(v) and 0 <= float(v) < 1):
            raise FaceLabError(f"{name} must be a number in [0, 1), got {v!r}; use the default 1e-4.")
    if not (_is_number(patches) and float(patches) >= 1 and float(patches) == int(patches)):
        raise FaceLabError(f"patches must be a whole number >= 1, got {patches!r}; use 1 (one map) or 10.")
    if input_radius is not None and not (_is_number(input_radius) and float(input_radius) > 0):
        raise FaceLabError(f"input_radius must be a positive distance, got {input_radius!r}; leave it unset.")


def _is_number(v):
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool) and bool(np.isfinite(v))


def same_array(a, b):
    """True when ``a`` and ``b`` are the same elements of the same buffer (e.g. ``out`` is the input)."""
    return a is b or (
        isinstance(a, np.ndarray) and a.shape == b.shape and a.dtype == b.dtype and a.strides == b.strides
        and a.__array_interface__["data"][0] == b.__array_interface__["data"][0]
    )


def checked_mesh(rest_vertices, faces):
    """``(R, F)``: the rest positions as (V,3) float64 and the triangles as (F,3) int64, validated."""
    R = np.asarray(rest_vertices, dtype=np.float64)
    F = np.asarray(faces)
    if R.ndim != 2 or R.shape[1] != 3 or len(R) == 0:
        raise MeshError(f"rest_vertices must be a non-empty (V,3) array, got shape {R.shape}.")
    if not np.isfinite(R).all():
        raise MeshError("The rest mesh has NaN or infinite coordinates; fix the rest pose.")
    if F.ndim != 2 or F.shape[1] != 3 or not np.issubdtype(F.dtype, np.integer):
        raise MeshError(f"faces must be an (F,3) integer array of triangles, got {F.shape}; triangulate first.")
    F = F.astype(np.int64)
    if F.size and (F.min() < 0 or F.max() >= len(R)):
        raise MeshError(f"Face indices are out of range [0, {len(R)}); the faces do not belong to this mesh.")
    return R, F


def checked_out(out, A):
    """``out`` as a (T,V,3) view after checking it is a writeable float32/float64 array like ``A``."""
    if not isinstance(out, np.ndarray):
        raise FaceLabError(f"out must be a NumPy array, got {type(out).__name__}; pass an array like the frames.")
    if out.dtype not in (np.float32, np.float64):
        raise FaceLabError(
            f"out has dtype {out.dtype}, which would round or truncate the corrected positions; pass a float32 "
            "or float64 array (or no out)."
        )
    if out.shape == A.shape[1:] and len(A) == 1:
        out = out[None]
    if out.shape != A.shape:
        raise FaceLabError(f"out has shape {out.shape}, expected {A.shape}; pass an array like the frames.")
    if not out.flags.writeable:
        raise FaceLabError("out is read-only; pass a writeable array (or no out).")
    return out


def check_features(features, m):
    """``features`` as a (T, 9m) float array after checking its shape, dtype and values (``m`` mouth triangles).

    Raises FaceLabError for a wrong shape, no frames or a non-float dtype, and FrameError naming the rows with
    NaN or infinite values; each message says to compute them with ``LipRegressor.mouth_features``.
    """
    Y = np.asarray(features)
    d = 9 * m
    if Y.ndim != 2 or Y.shape[1] != d:
        raise FaceLabError(
            f"features have shape {Y.shape}, expected (T, {d}) (9 per mouth triangle); compute them with "
            "mouth_features() of this regressor."
        )
    if len(Y) == 0:
        raise FaceLabError("No features given (0 frames); pass at least one frame.")
    if not np.issubdtype(Y.dtype, np.floating):
        raise FaceLabError(f"features have dtype {Y.dtype}, expected floats; compute them with mouth_features().")
    bad = np.flatnonzero(~np.isfinite(Y).all(axis=1))
    if bad.size:
        raise FrameError("The features of {frames} contain NaN or infinite values; recompute them with "
                         "mouth_features() from frames without NaN coordinates.", bad[:20])
    return Y


def check_prediction(xi, captured_interior, first, mouth_size):
    """Refuse non-finite results and corrections larger than the mouth (PredictionError naming frame indices)."""
    d = xi - captured_interior
    size = np.sqrt(np.max(np.sum(d * d, axis=2), axis=1))  # (t,) largest vertex move per frame; NaN if any
    bad = np.flatnonzero(~np.isfinite(size))
    if bad.size:
        raise PredictionError(
            "The predicted lips of {frames} are not finite (NaN or infinite), so nothing was written; check "
            "those frames for broken mouth shapes and add a corrected frame like them.", first + bad[:20])
    bad = np.flatnonzero(size > mouth_size)
    if bad.size:
        raise PredictionError(
            "The predicted lip correction of {frames} moves the lips by up to "
            f"{size[bad].max():.3g} scene units, more than the whole mouth ({mouth_size:.3g}), so "
            "nothing was written: those mouth shapes lie far outside the training frames. Correct one of them "
            "and add it to the training frames.", first + bad[:20])
