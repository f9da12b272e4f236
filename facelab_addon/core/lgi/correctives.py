"""Actor-specific corrective shapes for combinations of rig shapes (Cong, Lan and Fedkiw 2019, §7, Fig. 7).

:class:`RigCorrectives` indexes the dataset's residuals from the linear rig
with the bundles of a rig-shape combination (a deviation from indexing the
shapes themselves, which does worse than the linear combination on
combinations the dataset lacks); :func:`rig_correctives` runs it for a list
of combinations. Its parts: :func:`fit_rig_weights` (bounded least-squares
rig weights of the dataset shapes) and :func:`moving_bundle_layout` (the
default bundles: spread over the part of the mesh that the shapes move).

Shapes: neutral (V,3), rig shapes ``{name: (V,3)}`` and dataset shapes
(S,V,3) as positions. Units: positions and correctives in scene units; rig
weights are unitless.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg as sla

from ..errors import DatasetError, FaceLabError
from ..geometry.mesh import validate_mesh
from .indexing.indexer import GeometricIndexer
from .indexing.params import IndexerParams
from .indexing.stitch import shape_weight_matrix
from .natural_neighbor import surface_points

__all__ = ["RigCorrectives", "fit_rig_weights", "moving_bundle_layout", "rig_correctives"]


def moving_bundle_layout(neutral, faces, shapes, n: int = 100, *, min_motion: float = 0.05):
    """Bundles spread over the part of the mesh that the shapes move (farthest-point sampling).

    For tools that place their own bundles (the corrective-shape tool): one
    bundle at the centroid of each chosen triangle, among the triangles whose
    three vertices all move by more than ``min_motion`` times the largest
    motion in some shape.

    Parameters
    ----------
    neutral : (V,3) array_like
    faces : (F,3) int array_like
    shapes : (S,V,3) array_like
        Positions, scene units.
    n : int
        Number of bundles (fewer if fewer triangles move).
    min_motion : float
        Fraction of the largest vertex motion, unitless.

    Returns
    -------
    bundle_faces : (n,) int64 ndarray
    bundle_bary : (n,3) float64 ndarray
    """
    x0, F = validate_mesh(neutral, faces, name="neutral mesh")
    X = np.asarray(shapes, dtype=np.float64)
    mv = np.linalg.norm(X - x0, axis=2).max(axis=0)
    ok = np.flatnonzero((mv[F] > min_motion * mv.max()).all(axis=1))
    if len(ok) == 0:
        raise DatasetError("The shapes move no triangle of the mesh; check that they are shapes of this mesh.")
    C = x0[F[ok]].mean(axis=1)
    chosen = [int(np.argmax(mv[F[ok]].min(axis=1)))]
    d = np.linalg.norm(C - C[chosen[0]], axis=1)
    for _ in range(min(int(n), len(ok)) - 1):
        k = int(np.argmax(d))
        chosen.append(k)
        d = np.minimum(d, np.linalg.norm(C - C[k], axis=1))
    return ok[np.array(chosen)].astype(np.int64), np.full((len(chosen), 3), 1.0 / 3.0)


def fit_rig_weights(neutral, rig_deltas, shapes, *, bounds=(0.0, 1.0)):
    """Bounded least-squares rig weights of shapes: ``min |sum_k w_k d_k - (x - x0)|^2``, ``lo <= w <= hi``.

    Parameters
    ----------
    neutral : (V,3) array_like
    rig_deltas : (K,V,3) array_like
        Rig shape deltas, scene units.
    shapes : (S,V,3) array_like
        Positions, scene units.
    bounds : (float, float)

    Returns
    -------
    (S,K) float64 ndarray
        Unitless weights.
    """
    from scipy.optimize import lsq_linear

    A = np.asarray(rig_deltas, dtype=np.float64).reshape(len(rig_deltas), -1)
    Y = (np.asarray(shapes, dtype=np.float64) - np.asarray(neutral, dtype=np.float64)).reshape(len(shapes), -1)
    G = A @ A.T
    G += 1e-12 * np.trace(G) / len(G) * np.eye(len(G))
    L = np.linalg.cholesky(G)  # |A^T w - y|^2 = |L^T w - L^-1 A y|^2 + const
    rhs = sla.solve_triangular(L, A @ Y.T, lower=True)  # (K,S)
    return np.stack([lsq_linear(L.T, rhs[:, s], bounds=bounds, method="bvls").x for s in range(len(Y))])


class RigCorrectives:
    """Actor-specific corrective shapes for combinations of rig shapes (§7, Fig. 7).

    The paper rebuilds a combination of template rig shapes from the bundles
    of their linear combination, with local geometric indexing on the
    actor's dataset. Indexing the actor's *shapes* with those bundles puts
    the result through the linear combination's bundles and leaves it in the
    convex hull of the dataset, so a combination that the dataset does not
    hold comes out worse than the plain linear combination (docs/benchmarks.md,
    ``benchmarks/geometric_indexing.py``). So the same machinery indexes the
    dataset's *nonlinear residuals* instead:

    1. every dataset shape ``x_s`` gets rig weights ``w_s`` (bounded least
       squares, :func:`fit_rig_weights`, or given), its linear rig
       counterpart ``l_s = x0 + sum_k w_sk d_k`` and its residual
       ``r_s = x_s - l_s`` (what the linear rig misses: combination bulges,
       jaw arcs, in-between bunching);
    2. a :class:`GeometricIndexer` is built on the ``l_s``: point clouds of
       bundle positions on the linear counterparts, tetrahedra, grid, natural
       neighbours (§4, §5);
    3. a combination's linear shape ``l_c`` gives bundle positions, which are
       located in those clouds exactly as a frame of bundles is (§4, §5.1),
       and the chosen tetrahedra's barycentric weights blend the *residuals*,
       stitched with the natural-neighbour weights (§5).

    The corrective is that blend; ``l_c`` + corrective is the actor-specific
    combination. A combination the dataset holds is rebuilt exactly; a
    single rig shape gets the residual of the dataset shape it indexes.

    Parameters
    ----------
    neutral : (V,3) array_like
    faces : (F,3) int array_like
    rig_shapes : dict str -> (V,3) array_like
        Template rig shapes on the actor's neutral, positions, scene units.
    dataset_shapes : (S,V,3) array_like
        The actor's shapes, positions, scene units.
    dataset_names : list of str, optional
    dataset_weights : (S,K) array_like, optional
        Rig weights of the dataset shapes (columns in ``rig_shapes`` order);
        fitted when not given.
    bundle_faces, bundle_bary : optional
        Bundles; default :func:`moving_bundle_layout` with ``n_bundles``.
    n_bundles : int
    uvs : optional
        UV map for the natural-neighbour weights (§5).
    params : IndexerParams, optional
        Settings of the :class:`GeometricIndexer` (default
        ``IndexerParams(threads=1, exact=False)``: the residual blend needs
        no exact interpolation).

    Attributes
    ----------
    rig_names : list of str
    weights : (S,K) float64
        Rig weights of the dataset shapes used.
    residuals : (S,V,3) float64
        ``x_s - l_s``, scene units.
    dropped : list of str
        Dataset shapes left out: no rig content (``l_s`` is the neutral) or
        the same rig weights as an earlier shape.
    indexer : GeometricIndexer
    """

    def __init__(self, neutral, faces, rig_shapes: dict, dataset_shapes, *, dataset_names=None, dataset_weights=None,
                 bundle_faces=None, bundle_bary=None, n_bundles: int = 100, uvs=None,
                 params: IndexerParams | None = None):
        x0, F = validate_mesh(neutral, faces, name="neutral mesh")
        self.neutral, self.faces = x0, F
        if not rig_shapes:
            raise DatasetError("No rig shapes; give the template rig's shapes (shape keys of the rig object).")
        self.rig_names = list(rig_shapes)
        Dr = np.stack([np.asarray(rig_shapes[n], dtype=np.float64) - x0 for n in self.rig_names])
        if Dr.shape[1:] != x0.shape:
            raise DatasetError(f"Rig shapes must be (V,3) with V={len(x0)}; the rig must share the face's topology.")
        self.rig_deltas = Dr
        X = np.asarray(dataset_shapes, dtype=np.float64)
        if X.ndim != 3 or X.shape[1:] != x0.shape:
            raise DatasetError(f"Dataset shapes must be (S,V,3) with V={len(x0)}, got {X.shape}.")
        names = list(dataset_names) if dataset_names is not None else [f"shape {i}" for i in range(len(X))]
        if dataset_weights is None:
            Wt = fit_rig_weights(x0, Dr, X)
        else:
            Wt = np.asarray(dataset_weights, dtype=np.float64).reshape(len(X), len(self.rig_names))
        L = x0 + np.einsum("sk,kvd->svd", Wt, Dr)
        size = float(np.linalg.norm(x0.max(0) - x0.min(0)))
        moves = np.linalg.norm(L - x0, axis=2).max(axis=1) > 1e-7 * size
        keep = moves.copy()
        # shapes with the same rig weights index the same point: keep the first
        _, first = np.unique(np.round(Wt / 1e-9), axis=0, return_index=True)
        uniq = np.zeros(len(X), dtype=bool)
        uniq[first] = True
        keep &= uniq
        self.dropped = [names[i] for i in np.flatnonzero(~keep)]
        if keep.sum() < 4:
            raise DatasetError(
                f"Only {int(keep.sum())} dataset shapes have distinct rig content; the corrective tool needs at "
                "least 4 (add the actor's expressions, in-betweens and combinations as shape keys)."
            )
        self.dataset_names = [names[i] for i in np.flatnonzero(keep)]
        self.weights = Wt[keep]
        self.residuals = X[keep] - L[keep]
        if bundle_faces is None:
            bundle_faces, bundle_bary = moving_bundle_layout(x0, F, L[keep], n_bundles)
        if params is None:
            params = IndexerParams(threads=1, exact=False)
        self.indexer = GeometricIndexer(x0, F, L[keep], bundle_faces, bundle_bary, names=self.dataset_names, uvs=uvs,
                                        params=params)
        R = np.zeros((len(self.residuals) + 1,) + x0.shape)
        R[1:] = self.residuals
        self._R = R

    def linear(self, weights):
        """(V,3) linear rig shape ``x0 + sum_k w_k d_k`` for ``{rig name: weight}``, scene units."""
        w = self._weight_vector(weights)
        return self.neutral + np.tensordot(w, self.rig_deltas, axes=1)

    def _weight_vector(self, weights):
        if isinstance(weights, str):
            weights = (weights,)
        if not isinstance(weights, dict):
            weights = {n: 1.0 for n in weights}
        missing = [n for n in weights if n not in self.rig_names]
        if missing:
            raise FaceLabError(f"Unknown rig shapes {missing}; available: {self.rig_names[:10]}...")
        return np.array([float(weights.get(n, 0.0)) for n in self.rig_names])

    def corrective(self, weights):
        """Corrective delta for a combination, to add on top of its linear rig shape.

        Parameters
        ----------
        weights : dict str -> float, or iterable of str
            The combination (names at weight 1, or explicit weights).

        Returns
        -------
        corrective : (V,3) float64 ndarray
            Scene units.
        info : dict
            ``projected``: bundles outside the dataset's clouds (the
            combination goes beyond the dataset there); ``shapes``: the
            dataset shapes used, by total weight.
        """
        ds = self.indexer.dataset
        lin = self.linear(weights)
        q = surface_points(lin, self.faces, ds.bundle_faces, ds.bundle_bary)
        ids, bary, dist = self.indexer.locator.locate(q)
        C = (ds.weights @ shape_weight_matrix(ids, bary, ds.S1)).tocsc()
        out = np.zeros_like(self.neutral)
        for s in np.flatnonzero(np.diff(C.indptr)[1:]) + 1:
            rows = C.indices[C.indptr[s] : C.indptr[s + 1]]
            out[rows] += C.data[C.indptr[s] : C.indptr[s + 1], None] * self._R[s, rows]
        used = np.bincount(ids.ravel(), weights=bary.ravel(), minlength=ds.S1)[1:]
        order = np.argsort(-used)
        info = {"projected": int((dist > 0).sum()),
                "shapes": [(self.dataset_names[k], float(used[k] / ds.B)) for k in order[:5] if used[k] > 0]}
        return out, info

    def close(self):
        self.indexer.close()


def rig_correctives(neutral, faces, rig_shapes: dict, dataset_shapes, combinations, **options):
    """Actor-specific corrective shapes for combinations of rig shapes (§7, Fig. 7; :class:`RigCorrectives`).

    Parameters
    ----------
    neutral : (V,3) array_like
    faces : (F,3) int array_like
    rig_shapes : dict str -> (V,3) array_like
        Template rig shapes (positions, scene units).
    dataset_shapes : (S,V,3) array_like
        The actor's dataset (positions, scene units).
    combinations : iterable of tuple of str
        E.g. ``[("noseSneer_L", "mouthUpperUp_L")]``.
    **options
        Passed to :class:`RigCorrectives`.

    Returns
    -------
    dict str -> dict
        Keyed by ``"+".join(combination)``: ``"linear"`` (V,3) the linear
        combination, ``"corrective"`` (V,3) the delta to add on top of it,
        ``"reconstruction"`` (V,3) their sum, scene units; ``"info"``.

    Raises
    ------
    FaceLabError
        For an unknown rig shape name; DatasetError / BundleError for an
        unusable dataset.
    """
    rc = RigCorrectives(neutral, faces, rig_shapes, dataset_shapes, **options)
    out = {}
    try:
        for combo in combinations:
            combo = (combo,) if isinstance(combo, str) else tuple(combo)
            lin = rc.linear(combo)
            c, info = rc.corrective(combo)
            out["+".join(combo)] = {"linear": lin, "corrective": c, "reconstruction": lin + c, "info": info}
    finally:
        rc.close()
    return out
