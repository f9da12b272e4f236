"""The inputs every bundle reconstruction checks: a mesh, its dataset shapes and the bundles' binding.

Both reconstruction methods (:class:`~facelab_addon.core.lgi.indexing.indexer.GeometricIndexer`, the paper's
local indexing, and :class:`~facelab_addon.core.lgi.fit_residual.FitResidual`, the default) take the
same inputs and refuse the same bad ones with the same messages.
"""

from __future__ import annotations

import numpy as np

from ..errors import BundleError, DatasetError
from ..geometry.mesh import validate_mesh
from .binding import bundle_labels

__all__ = ["check_reconstruction_inputs", "check_bundles_move", "check_bundle_frame", "check_bundle_sequence"]


def check_reconstruction_inputs(neutral, faces, shapes, names, bundle_faces, bundle_bary, *,
                                method: str = "Reconstruct"):
    """Validate and convert the mesh, the dataset shapes and the bundles' surface binding.

    Parameters
    ----------
    neutral : (V,3) array_like
        Neutral mesh vertices, scene units.
    faces : (F,3) int array_like
        Triangles.
    shapes : (S,V,3) array_like
        Dataset shapes as positions, scene units; at least 4.
    names : sequence of str or None
        One name per shape (``"shape i"`` when None), used in messages.
    bundle_faces : (B,) int array_like
        Triangle each bundle is bound to.
    bundle_bary : (B,3) array_like
        Barycentric coordinates of each bundle in its triangle (non-negative, summing to 1).
    method : str
        The method's name, for the "needs at least 4 dataset shapes" message.

    Returns
    -------
    x0 : (V,3) float64 ndarray
    F : (F,3) int64 ndarray
    X : (S,V,3) float64 ndarray
    names : list of str
    bf : (B,) int64 ndarray
    bb : (B,3) float64 ndarray

    Raises
    ------
    MeshError, DatasetError, BundleError
        Naming the problem and the fix (re-bind the bundles, add shape keys, ...).
    """
    x0, F = validate_mesh(neutral, faces, name="neutral mesh")
    nv = len(x0)
    X = np.asarray(shapes, dtype=np.float64)
    if X.ndim != 3 or X.shape[1:] != (nv, 3):
        raise DatasetError(
            f"Dataset shapes must be an (S,V,3) array with V={nv} (the neutral's vertex count), got "
            f"{X.shape}; every shape key must come from the same mesh."
        )
    S = len(X)
    names = [str(n) for n in names] if names is not None else [f"shape {i}" for i in range(S)]
    if len(names) != S:
        raise DatasetError(f"{len(names)} names for {S} shapes; give one name per shape.")
    if S < 4:
        raise DatasetError(
            f"{method} needs at least 4 dataset shapes, got {S}; add shape keys "
            "(expressions, in-betweens or combinations)."
        )
    bad = ~np.isfinite(X).all(axis=(1, 2))
    if bad.any():
        raise DatasetError(f"Dataset shapes {[names[i] for i in np.flatnonzero(bad)[:5]]} contain NaN; fix them.")
    bf = np.asarray(bundle_faces)
    bb = np.asarray(bundle_bary, dtype=np.float64)
    B = len(bf)
    if bf.ndim != 1 or B == 0 or not np.issubdtype(bf.dtype, np.integer):
        raise BundleError(f"bundle_faces must be a non-empty (B,) integer array, got {bf.shape} {bf.dtype}.")
    bf = bf.astype(np.int64)
    if bb.shape != (B, 3) or not np.isfinite(bb).all():
        raise BundleError(f"bundle_bary must be a finite (B,3)=({B},3) array, got {bb.shape}.")
    if bf.min() < 0 or bf.max() >= len(F):
        raise BundleError(
            f"A bundle is bound to triangle {int(bf.max()) if bf.max() >= len(F) else int(bf.min())} but the "
            f"mesh has {len(F)}; re-bind the bundles (bind_points) on this mesh."
        )
    if (bb < -1e-6).any() or np.abs(bb.sum(1) - 1).max() > 1e-6:
        raise BundleError("Bundle barycentric coordinates must be non-negative and sum to 1; re-bind the bundles.")
    return x0, F, X, names, bf, bb


def check_bundles_move(moved, tol: float, bundle_names=None) -> None:
    """Raise a BundleError naming the bundles that no dataset shape moves.

    Parameters
    ----------
    moved : (B,) array_like of float
        Largest motion of each bundle over the dataset shapes, scene units.
    tol : float
        A bundle moved by no more than this (scene units) is still.
    bundle_names : list of str, optional
        Bundle names for the message (default their indices).
    """
    still = np.flatnonzero(np.asarray(moved) <= tol)
    if len(still):
        raise BundleError(
            f"{len(still)} bundles are not moved by any dataset shape ({bundle_labels(bundle_names, still)}, for "
            "example on the back of the head or a rigid part); remove them, bind them on the moving face, or "
            "add shapes that move them."
        )


def check_bundle_frame(q, count: int, bundle_names=None, what: str = "bundles"):
    """One frame of bundle positions as a finite (B,3) float64 array, or a message naming the bad bundles.

    Parameters
    ----------
    q : (B,3) array_like
        Bundle positions, scene units.
    count : int
        B, the number of bound bundles.
    bundle_names : sequence of str, optional
        Names used in the message (indices otherwise).
    what : str
        What ``q`` is, for the shape message.

    Returns
    -------
    (B,3) float64 ndarray

    Raises
    ------
    BundleError
        Wrong shape, or NaN / infinite positions (skip the frame or fill the track gaps).
    """
    q = np.asarray(q, dtype=np.float64)
    if q.shape != (count, 3):
        raise BundleError(f"Expected {what} as a ({count},3) array (one row per bound bundle), got {q.shape}.")
    bad = ~np.isfinite(q).all(axis=1)
    if bad.any():
        raise BundleError(
            f"{int(bad.sum())} bundles have NaN positions ({bundle_labels(bundle_names, np.flatnonzero(bad))}); "
            "skip the frame or fill the track gaps."
        )
    return q


def check_bundle_sequence(bundles, count: int):
    """Bundle positions of a shot as a (T,B,3) float64 array (NaN rows allowed: those frames are skipped).

    Parameters
    ----------
    bundles : (T,B,3) array_like
        Bundle positions per frame, scene units.
    count : int
        B, the number of bound bundles.

    Returns
    -------
    (T,B,3) float64 ndarray
        ``bundles`` itself when it is already a float64 array.

    Raises
    ------
    BundleError
        Not a (T,B,3) array.
    """
    Q = np.asarray(bundles, dtype=np.float64)
    if Q.ndim != 3 or Q.shape[1:] != (count, 3):
        raise BundleError(f"Expected bundles as a (T,{count},3) array, got {Q.shape}.")
    return Q
