"""Per-frame inputs of the lip regression: frame checks and mouth deformation-gradient features.

Dinev et al. 2018, "User-Guided Lip Correction for Facial Performance
Capture", §4: the input of the regression is the vector ``y`` of deformation
gradients of the trusted mouth triangles. This module holds the helpers that
:mod:`.propagate` (the regression) and :mod:`.suggest` (training-frame
suggestion) share for it: validating a (T,V,3) sequence without copying it,
the shape-matrix columns of a block of frames, and the whole-mouth feature
rows ``vec(F_t - I)``, all computed a block of ``_BLOCK`` frames at a time so
a long float32 sequence is never converted whole. Positions are scene units;
gradients and features are unitless, float64.

Package-internal: the public API is :class:`.propagate.LipRegressor` and
:func:`.suggest.suggest_frames`.
"""

from __future__ import annotations

import numpy as np

from ..errors import FaceLabError, MeshError
from ..geometry.gradients import rest_inverse, shape_matrices

__all__: list[str] = []

_BLOCK = 64  # frames per block of the per-frame loops (working memory ~ block x region size)


def _as_frames(a, n_vertices, what, used=None):
    """Validate frames as a (T,V,3) float32 or float64 array, without copying them.

    float32 and float64 arrays are returned as they are (a (V,3) frame as a
    (1,V,3) view); other dtypes are converted to float64. Callers convert
    only the vertices they read to float64. NaNs are looked for in ``used``
    vertices only, a block of frames at a time.
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
    for s in range(0, len(A), _BLOCK):
        blk = A[s : s + _BLOCK] if used is None else A[s : s + _BLOCK, used]
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


def _shape_components(frames, verts, local):
    """Shape-matrix columns of triangles ``local`` over vertices ``verts`` for frames (T,V,3), in float64.

    Returns three (3,T,f) arrays ``e[k][i]``: column k (edge 1, edge 2,
    phantom offset), coordinate i. Component-major layout keeps every
    operation contiguous (about 3x faster than (T,f,3,3) for many frames).
    """
    Xt = np.ascontiguousarray(frames[:, verts, :].transpose(2, 0, 1), dtype=np.float64)  # (3, T, nv)
    p0 = Xt[:, :, local[:, 0]]
    e1 = Xt[:, :, local[:, 1]] - p0
    e2 = Xt[:, :, local[:, 2]] - p0
    c = np.empty_like(e1)
    np.subtract(e1[1] * e2[2], e1[2] * e2[1], out=c[0])
    np.subtract(e1[2] * e2[0], e1[0] * e2[2], out=c[1])
    np.subtract(e1[0] * e2[1], e1[1] * e2[0], out=c[2])
    s = np.sqrt(np.sqrt(c[0] * c[0] + c[1] * c[1] + c[2] * c[2]))
    c *= np.divide(1.0, s, out=np.zeros_like(s), where=s > 0)
    return e1, e2, c


def _mouth_features(frames, rest_vertices, faces, mouth_faces, chunk=_BLOCK):
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

