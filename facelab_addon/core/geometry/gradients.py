"""Per-triangle deformation gradients with a phantom fourth vertex.

Dinev et al. 2018, "User-Guided Lip Correction for Facial Performance
Capture", §4: the mouth and inner-lip regions are represented differentially,
by the deformation gradient ``F = D_d D_r^-1`` of every triangle, where the
shape matrices ``D = [v2-v1, v3-v1, v4-v1]`` use the phantom vertex of Sumner
and Popović 2004 ("Deformation transfer for triangle meshes", §3):

    v4 = v1 + (v2-v1) x (v3-v1) / sqrt(|(v2-v1) x (v3-v1)|)

so ``F`` maps the rest triangle's edges onto the deformed edges and its
(scaled) normal onto the deformed one. Gradients are unitless and invariant
to a translation of the mesh and to scaling rest and deformed shape together
(cm or m scenes give the same ``F``).
"""

from __future__ import annotations

import numpy as np

from ..errors import MeshError
from .inv3 import inv3

__all__ = ["shape_matrices", "rest_inverse", "deformation_gradients"]


def shape_matrices(vertices, faces) -> np.ndarray:
    """Shape matrices ``D = [v2-v1, v3-v1, v4-v1]`` (edge vectors as columns).

    Parameters
    ----------
    vertices : (V,3) or (T,V,3) array_like
        Positions, scene units; a leading frame axis is allowed.
    faces : (F,3) int array_like
        Triangles.

    Returns
    -------
    (F,3,3) or (T,F,3,3) float64 ndarray
        Columns are the two edge vectors and the phantom offset (scene units;
        the phantom column has units of sqrt(length)). A zero-area triangle
        gets a zero phantom column (its ``D`` is singular).
    """
    X = np.asarray(vertices, dtype=np.float64)
    Fc = np.asarray(faces, dtype=np.int64)
    P = X[..., Fc, :]  # (..., F, 3 corners, 3 xyz)
    e1 = P[..., 1, :] - P[..., 0, :]
    e2 = P[..., 2, :] - P[..., 0, :]
    c = np.cross(e1, e2)
    s = np.sqrt(np.linalg.norm(c, axis=-1, keepdims=True))
    e3 = np.divide(c, s, out=np.zeros_like(c), where=s > 0)
    return np.stack([e1, e2, e3], axis=-1)


def rest_inverse(rest, faces, *, name: str = "rest mesh") -> np.ndarray:
    """Inverse rest shape matrices ``D_r^-1`` (precompute once per mesh).

    Parameters
    ----------
    rest : (V,3) array_like
        Rest (neutral) positions, scene units.
    faces : (F,3) int array_like
        Triangles.
    name : str
        Used in error messages.

    Returns
    -------
    (F,3,3) float64 ndarray
        Units 1/length (edge rows) and 1/sqrt(length) (phantom row).

    Raises
    ------
    MeshError
        On NaN coordinates or degenerate (zero-area) rest triangles.
    """
    R = np.asarray(rest, dtype=np.float64)
    if R.ndim != 2 or R.shape[1] != 3:
        raise MeshError(f"{name}: expected (V,3) vertices, got shape {R.shape}.")
    if not np.isfinite(R).all():
        raise MeshError(f"{name}: NaN or infinite coordinates; fix the rest mesh.")
    Dr = shape_matrices(R, faces)
    e1, e2 = Dr[:, :, 0], Dr[:, :, 1]
    area2 = np.linalg.norm(np.cross(e1, e2), axis=-1)
    scale = np.maximum(np.linalg.norm(e1, axis=-1), np.linalg.norm(e2, axis=-1))
    bad = ~(area2 > 1e-12 * np.maximum(scale, 1e-300) ** 2)
    if bad.any():
        idx = np.flatnonzero(bad)
        raise MeshError(
            f"{name}: {len(idx)} degenerate (zero-area) triangles, first faces {idx[:5].tolist()}; "
            "run Mesh > Clean Up > Degenerate Dissolve or leave them out of the regions."
        )
    return inv3(Dr)


def deformation_gradients(rest, deformed, faces, *, rest_inv=None) -> np.ndarray:
    """Per-triangle deformation gradients ``F = D_d D_r^-1``.

    Parameters
    ----------
    rest : (V,3) array_like
        Rest positions, scene units.
    deformed : (V,3) or (T,V,3) array_like
        Deformed positions (one frame or T frames), same units and vertex order.
    faces : (F,3) int array_like
        Triangles.
    rest_inv : (F,3,3) array_like, optional
        Precomputed :func:`rest_inverse` for ``rest`` and ``faces``.

    Returns
    -------
    (F,3,3) or (T,F,3,3) float64 ndarray
        Unitless. ``F @ (r2-r1) = d2-d1`` and ``F @ (r3-r1) = d3-d1`` for the
        rest edges ``r`` and deformed edges ``d`` of each triangle. A rigid
        motion ``x -> R x + t`` (or a similarity ``s R x + t``) gives ``s R``
        exactly on every triangle; a general affine map ``A`` gives ``A`` on
        the triangle's plane (the normal column follows the phantom vertex).

    Raises
    ------
    MeshError
        On a vertex count that differs from ``rest``, NaN coordinates, or
        degenerate rest triangles.
    """
    R = np.asarray(rest, dtype=np.float64)
    D = np.asarray(deformed, dtype=np.float64)
    if D.ndim not in (2, 3) or D.shape[-1] != 3 or D.shape[-2] != R.shape[0]:
        raise MeshError(
            f"The deformed mesh has shape {D.shape} but the rest mesh is {R.shape}; the topology differs. "
            "Use frames of the same mesh (same vertex count and order) as the rest pose."
        )
    if not np.isfinite(D).all():
        bad = ~np.isfinite(D).reshape(-1, D.shape[-2] * 3).all(axis=1)
        where = f" (frames {np.flatnonzero(bad)[:5].tolist()})" if D.ndim == 3 else ""
        raise MeshError(f"The deformed mesh has NaN or infinite coordinates{where}; fix or re-import the capture.")
    Ri = rest_inverse(R, faces) if rest_inv is None else np.asarray(rest_inv, dtype=np.float64)
    Dd = shape_matrices(D, faces)
    return np.matmul(Dd, Ri)
