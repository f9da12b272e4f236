"""The checked, jaw-unskinned dataset a geometric indexer blends (Cong, Lan and Fedkiw 2019, §5, §6).

:func:`build_dataset` checks the mesh, the dataset shapes and the bundle
binding, removes the jaw motion from the shapes when there is a jaw rig (§6,
Eq. 2: ``b* = T(theta_n)^-1 (x0 + b_n) - x0``), builds the bundles'
natural-neighbour weights (§5,
:mod:`facelab_addon.core.lgi.natural_neighbor`), rejects shapes that move
nothing or repeat another, and keeps the float32 deltas of the vertices some
shape moves. The result, :class:`IndexedDataset`, is what the clouds, the
locator and the stitcher read.

Array conventions: shape id 0 is the neutral, ``s + 1`` is ``shapes[s]``.
Units: positions in scene units; weights unitless; jaw angles in radians.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...errors import DatasetError
from ..inputs import check_reconstruction_inputs
from ..natural_neighbor import natural_neighbor_weights

__all__ = ["IndexedDataset", "STILL_TOLERANCE", "build_dataset", "find_duplicate_shapes"]

# a shape or bundle moving less than this times the face size counts as still
STILL_TOLERANCE = 1e-7


@dataclass
class IndexedDataset:
    """Mesh, bundle binding, jaw, natural-neighbour weights and the stored deltas of an indexer.

    Attributes
    ----------
    neutral : (V,3) float64
        Neutral mesh ``x0``, scene units.
    faces : (F,3) int
        Triangles.
    bundle_faces : (B,) int
        Triangle of each bundle on the neutral.
    bundle_bary : (B,3) float64
        Barycentric coordinates of each bundle in its triangle.
    names : list of str
        Dataset shape names (S).
    bundle_names : list of str or None
        Bundle names for messages.
    jaw : JawRig or None
        Jaw articulation (§6).
    shape_jaw : (S,4) or (S,4,4) float64 or None
        Jaw parameters or rigid jaw poses of the dataset shapes.
    bundle_jaw_weights : (B,) float64 or None
        Jaw skinning weight at every bundle.
    nn : natural_neighbor.NaturalNeighbors
        Natural-neighbour weights and Voronoi cells of the bundles (§5).
    weights : (V,B) scipy.sparse.csr_matrix
        ``nn.weights`` as CSR with sorted indices (each row sums to 1).
    face_size : float
        Bounding-box diagonal of the vertices with natural-neighbour weights,
        scene units.
    active : (A,) int64
        Vertices that some shape moves (the only ones blended).
    deltas : (S+1)*A x 3 float32
        Unskinned deltas of the active vertices, shape-major (the rows of
        shape id ``k`` are ``k*A .. (k+1)*A``; shape id 0, the neutral, is 0).
    """

    neutral: np.ndarray
    faces: np.ndarray
    bundle_faces: np.ndarray
    bundle_bary: np.ndarray
    names: list
    bundle_names: list | None
    jaw: object
    shape_jaw: np.ndarray | None
    bundle_jaw_weights: np.ndarray | None
    nn: object
    weights: object
    face_size: float
    active: np.ndarray
    deltas: np.ndarray

    @property
    def B(self) -> int:
        """Number of bundles."""
        return len(self.bundle_faces)

    @property
    def S(self) -> int:
        """Number of dataset shapes."""
        return len(self.names)

    @property
    def S1(self) -> int:
        """Number of shape ids, the neutral included (``S + 1``)."""
        return len(self.names) + 1

    @property
    def V(self) -> int:
        """Number of vertices."""
        return len(self.neutral)


def find_duplicate_shapes(D, tol):
    """The first pair of shapes whose deltas agree to ``tol``, or None.

    Parameters
    ----------
    D : (S,V,3) array_like
        Shape deltas, scene units.
    tol : float
        Largest coordinate difference of a duplicate, scene units.

    Returns
    -------
    (int, int) or None
        Indices ``a < b`` of the first duplicate pair found.
    """
    S = len(D)
    flat = np.asarray(D).reshape(S, -1)
    rng = np.random.default_rng(0)
    proj = flat @ rng.standard_normal((flat.shape[1], 4))
    scale = np.linalg.norm(flat, axis=1).max() + 1e-300
    # candidates: close in every random projection, then verified exactly
    d = np.abs(proj[:, None, :] - proj[None, :, :]).max(axis=2)
    i, j = np.nonzero(np.triu(d <= 1e-6 * scale * np.sqrt(flat.shape[1]), 1))
    for a, b in zip(i, j):
        if np.abs(flat[a] - flat[b]).max() <= tol:
            return int(a), int(b)
    return None


def _unskin(X, x0, F, bf, bb, jaw, shape_jaw):
    """Deltas (S,V,3) with the jaw motion removed (Eq. 2), the checked shape_jaw and the bundles' jaw weights."""
    S, nv = len(X), len(x0)
    if jaw is None:
        return X - x0, None, None
    if shape_jaw is None:
        raise DatasetError(
            "A jaw rig needs the jaw parameters of every dataset shape (shape_jaw, (S,4)); estimate them "
            "or build the indexer without the jaw."
        )
    sj = np.asarray(shape_jaw, dtype=np.float64)
    if sj.shape not in ((S, 4), (S, 4, 4)):
        raise DatasetError(f"shape_jaw must be (S,4) or (S,4,4) with S={S}, got {sj.shape}.")
    if len(jaw.weights) != nv:
        raise DatasetError(f"The jaw rig has {len(jaw.weights)} skinning weights for {nv} vertices.")
    D = np.stack([jaw.unskin_shape(X[s], x0, sj[s]) for s in range(S)])
    return D, sj, (jaw.weights[F[bf]] * bb).sum(1)


def build_dataset(neutral, faces, shapes, bundle_faces, bundle_bary, *, names=None, bundle_names=None, uvs=None,
                  nn_method=None, jaw=None, shape_jaw=None):
    """Check and store the indexer's data (§5, §6).

    Parameters
    ----------
    neutral : (V,3) array_like
        Neutral mesh, scene units.
    faces : (F,3) int array_like
    shapes : (S,V,3) array_like
        Dataset shapes as positions, scene units.
    bundle_faces : (B,) int array_like
    bundle_bary : (B,3) array_like
    names, bundle_names : list of str, optional
    uvs : (V,2) or (F,3,2) array_like, optional
        UV map for the natural-neighbour weights.
    nn_method : {"uv", "geodesic"}, optional
    jaw : JawRig, optional
    shape_jaw : (S,4) or (S,4,4) array_like, optional

    Returns
    -------
    dataset : IndexedDataset
    shapes : (S,V,3) float64 ndarray
        The checked shapes (positions, scene units).
    motion : (S,V) float64 ndarray
        How far every shape moves every vertex once unskinned, scene units.

    Raises
    ------
    DatasetError
        Bad shapes, a shape equal to the neutral or to another, or a jaw
        without per-shape jaw parameters.
    """
    x0, F, X, names, bf, bb = check_reconstruction_inputs(
        neutral, faces, shapes, names, bundle_faces, bundle_bary, method="Local geometric indexing")
    D, sj, bjw = _unskin(X, x0, F, bf, bb, jaw, shape_jaw)
    nn = natural_neighbor_weights(x0, F, bf, bb, uvs=uvs, method=nn_method)
    W = nn.weights.tocsr()
    W.sort_indices()
    dom = nn.domain
    lo, hi = x0[dom].min(axis=0), x0[dom].max(axis=0)
    face_size = float(np.linalg.norm(hi - lo))
    dup_tol = STILL_TOLERANCE * face_size
    mags = np.linalg.norm(D, axis=2)  # (S,V)
    still = np.flatnonzero(mags.max(axis=1) <= dup_tol)
    if len(still):
        why = ("equals the neutral once the jaw motion is removed (the jaw rig alone reproduces it)"
               if jaw is not None else "equals the neutral (moves nothing)")
        raise DatasetError(f"Dataset shape {names[still[0]]!r} {why}; remove it from the dataset.")
    dup = find_duplicate_shapes(D, dup_tol)
    if dup is not None:
        raise DatasetError(
            f"Dataset shapes {names[dup[0]]!r} and {names[dup[1]]!r} are duplicates (identical to "
            f"{dup_tol:.2g} scene units); remove one of them."
        )
    # only vertices that some shape moves are blended; float32 is ample for deltas (1e-7 relative)
    # (shape-major layout: a vertex run of one shape is contiguous, which keeps the gathers cached)
    active = np.flatnonzero(mags.max(axis=0) > 0)
    Dv = np.zeros((len(X) + 1, len(active), 3), dtype=np.float32)
    Dv[1:] = D[:, active]
    ds = IndexedDataset(neutral=x0, faces=F, bundle_faces=bf, bundle_bary=bb, names=names,
                        bundle_names=None if bundle_names is None else [str(n) for n in bundle_names],
                        jaw=jaw, shape_jaw=sj, bundle_jaw_weights=bjw, nn=nn, weights=W, face_size=face_size,
                        active=active, deltas=Dv.reshape(-1, 3))
    return ds, X, mags
