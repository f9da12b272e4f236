"""Binding bundles to the neutral surface (local geometric indexing, Cong, Lan and Fedkiw 2019, §4).

Every bundle is tied to a triangle of the neutral mesh and barycentric
coordinates in it (:func:`bind_points`); the indexer reads the bundle's
position on every dataset shape at that surface point. ``bundle_labels`` names
bundles in error messages.

Shapes: bundle positions (B,3), bound triangles (B,) int64, barycentric
coordinates (B,3). Units: positions and distances in scene units; barycentric
coordinates are unitless.
"""

from __future__ import annotations

import numpy as np

from ..errors import BundleError
from ..geometry.mesh import validate_mesh

__all__ = ["bind_points"]


def bind_points(neutral, faces, points, *, max_distance=None, bundle_names=None):
    """Bind 3D points (bundles in the rest pose) to the closest surface points.

    Parameters
    ----------
    neutral : (V,3) array_like
        Neutral positions, scene units.
    faces : (F,3) int array_like
        Triangles.
    points : (B,3) array_like
        Bundle positions on the neutral face, scene units.
    max_distance : float, optional
        Largest allowed distance from a bundle to the surface, scene units.
        Default 0.5 percent of the mesh's bounding-box diagonal (about 2 mm on
        ICT-FaceKit).
    bundle_names : list of str, optional
        Names of the bundles for messages (default their indices).

    Returns
    -------
    bundle_faces : (B,) int64 ndarray
    bundle_bary : (B,3) float64 ndarray
        Barycentric coordinates in ``bundle_faces``.
    distance : (B,) float64 ndarray
        Distance from each point to the surface, scene units.

    Raises
    ------
    BundleError
        On NaN points, or points farther than ``max_distance`` from the mesh
        (the message lists them).
    """
    import igl

    V, F = validate_mesh(neutral, faces, name="neutral mesh")
    P = np.asarray(points, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3 or len(P) == 0:
        raise BundleError(f"Bundles must be a non-empty (B,3) array, got shape {P.shape}.")
    bad = ~np.isfinite(P).all(axis=1)
    if bad.any():
        raise BundleError(
            f"{int(bad.sum())} bundles have NaN rest positions ({bundle_labels(bundle_names, np.flatnonzero(bad))}); "
            "bind bundles on a frame where all of them are tracked."
        )
    diag = float(np.linalg.norm(V.max(axis=0) - V.min(axis=0)))
    if max_distance is None:
        max_distance = 5e-3 * diag
    d2, fi, C = igl.point_mesh_squared_distance(P, V, F)
    fi = np.asarray(fi, dtype=np.int64).ravel()
    dist = np.sqrt(np.maximum(np.asarray(d2, dtype=np.float64).ravel(), 0.0))
    far = dist > max_distance
    if far.any():
        idx = np.flatnonzero(far)
        raise BundleError(
            f"{len(idx)} bundles are off the mesh: {bundle_labels(bundle_names, idx)} lie "
            f"{np.round(dist[idx[:5]], 4).tolist()} scene units from the neutral surface (allowed "
            f"{max_distance:.4g}). Align the bundles rigidly to the neutral face (same units, same rest "
            "frame) or raise max_distance."
        )
    C = np.asarray(C, dtype=np.float64)
    bary = _triangle_barycentric(C, V[F[fi, 0]], V[F[fi, 1]], V[F[fi, 2]])
    return fi, bary, dist


def bundle_labels(names, idx, n: int = 5):
    """'bundle [3, 7]' or "'B03', 'B07'" for messages (the first ``n``)."""
    idx = [int(i) for i in np.asarray(idx).ravel()[:n]]
    if names is None:
        return f"bundle {idx}"
    return ", ".join(repr(str(names[i])) for i in idx)


def _triangle_barycentric(p, a, b, c):
    """(n,3) barycentric coordinates of points ``p`` in triangles ``a b c`` (each (n,3))."""
    v0, v1, v2 = b - a, c - a, p - a
    d00, d01, d11 = (v0 * v0).sum(1), (v0 * v1).sum(1), (v1 * v1).sum(1)
    d20, d21 = (v2 * v0).sum(1), (v2 * v1).sum(1)
    den = d00 * d11 - d01 * d01
    v = (d11 * d20 - d01 * d21) / den
    w = (d00 * d21 - d01 * d20) / den
    bary = np.stack([1 - v - w, v, w], axis=1)
    bary = np.clip(bary, 0.0, None)
    return bary / bary.sum(axis=1, keepdims=True)
