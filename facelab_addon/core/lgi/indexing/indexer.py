"""Local geometric indexing: a high-resolution face from sparse 3D bundles.

Cong, Lan and Fedkiw 2019, "Local Geometric Indexing of High Resolution Data
for Facial Reconstruction from Sparse Markers". Instead of fitting a
blendshape model to the bundles, every bundle looks up the dataset shapes
whose local geometry reproduces its position, and the per-bundle geometry is
sewn together with natural-neighbour weights.

Build once (:class:`GeometricIndexer`), then reconstruct every frame. The
constructor runs named build steps in order; each step lives with the code
that reads what it builds:

* input checks, the jaw (§6, Eq. 2: with a
  :class:`~facelab_addon.core.lgi.jaw.JawRig` the dataset shapes are unskinned,
  ``b* = T(theta_n)^-1 (x0 + b_n) - x0``, bundles are unskinned per frame with
  the frame's jaw parameters and the blend is skinned back by linear blend
  skinning), natural-neighbour weights (§5,
  :mod:`facelab_addon.core.lgi.natural_neighbor`), the float32 dataset of the
  moving vertices and ``stats``: here;
* point clouds, pruning, merged points, tetrahedra, hulls and grids (§4,
  §4.1): :mod:`facelab_addon.core.lgi.clouds`;
* neighbour tables and the per-frame choice of tetrahedra (§4, §5.1, Eq. 1):
  :mod:`facelab_addon.core.lgi.locate`;
* stitching matrices, the blend, exact interpolation, the RBF and Voronoi
  stitchings and sequences with temporal smoothing (§5, §7):
  :mod:`facelab_addon.core.lgi.stitch`.

:meth:`GeometricIndexer.reconstruct` chains them for one frame: unskin the
bundles, locate, blend, skin, exact-interpolation correction.

Units: positions in scene units; barycentric and natural-neighbour weights
are unitless; jaw angles in radians.
"""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import scipy.linalg as sla

from ..errors import BundleError, DatasetError, FaceLabError
from ..geometry.linsolve import one_blas_thread
from .clouds import IndexerClouds
from .inputs import check_bundle_frame, check_reconstruction_inputs
from .locate import IndexerLocate
from .natural_neighbor import natural_neighbor_weights
from .stitch import IndexerStitch

__all__ = ["GeometricIndexer"]


class GeometricIndexer(IndexerClouds, IndexerLocate, IndexerStitch):
    """Local geometric indexing of a shape dataset by surface-bound bundles.

    Build once per (mesh, dataset, bundle binding); :meth:`reconstruct` and
    :meth:`reconstruct_sequence` are then cheap per frame (timings: docs/benchmarks.md,
    ``benchmarks/geometric_indexing.py``).

    Parameters
    ----------
    neutral : (V,3) array_like
        Neutral mesh ``x0``, scene units.
    faces : (F,3) int array_like
        Triangles.
    shapes : (S,V,3) array_like
        Dataset shapes as positions (``x0 + b_n``), for example the shape
        keys. At least 4, pairwise different, none equal to the neutral.
    bundle_faces : (B,) int array_like
        Triangle of each bundle on the neutral mesh (:func:`bind_points`).
    bundle_bary : (B,3) array_like
        Barycentric coordinates of each bundle in its triangle.
    names : list of str, optional
        Shape names, used in messages and :meth:`explain`.
    uvs : (V,2) or (F,3,2) array_like, optional
        UV map; natural-neighbour weights are then built in UV space (§5,
        the paper's choice), else with geodesics on the mesh.
    nn_method : {"uv", "geodesic"}, optional
        Force the natural-neighbour method.
    jaw : JawRig, optional
        Jaw articulation (§6, Eq. 2). Requires ``shape_jaw``.
    shape_jaw : (S,4) or (S,4,4) array_like, optional
        Jaw parameters ``(angle rad, tx, ty, tz)`` or rigid jaw poses of
        every dataset shape (:meth:`JawRig.fit_pose` estimates them).
    merge_tolerance : float, optional
        Shapes that put a bundle within this distance of each other (scene
        units) share one cloud point; the neighbouring bundles pick which of
        them to use (§5.1). Default ``2e-4`` times the face size.
    prune_tolerance : float, optional
        A shape is dropped from a bundle's point cloud when it moves no vertex
        of the bundle's natural-neighbour region by more than this, weighted
        by the bundle's weight (scene units). Default ``1e-7`` times the face
        size: only shapes that leave the region still are dropped, because a
        shape that moves the skin between bundles without moving the bundle
        itself must stay reachable (it is merged into the neutral's point, so
        it costs no tetrahedra).
    neighbors : int
        Each cloud point forms tetrahedra with 3 of its ``neighbors`` nearest
        cloud points (all 4-point combinations when the cloud is no larger
        than ``neighbors + 1``); the cloud's Delaunay tetrahedra are added so
        that the tetrahedra cover its convex hull.
    min_quality : float
        Tetrahedra whose mean-ratio quality is lower are "too thin" (0..1).
    max_edge : float, optional
        Tetrahedra with an edge longer than this (scene units) are "too large".
    forbidden : iterable of iterables of int or str
        Flagged combinations: a tetrahedron holding all shapes of one set
        (indices into ``shapes`` or names) is deleted.
    min_tets_per_point : int
        Every cloud point keeps at least this many of its best tetrahedra.
    temporal_bias : float
        Animated bundles (§5.1): a candidate's neighbour cost is multiplied by
        ``1 + temporal_bias * (4 - shared) / 4``, where ``shared`` counts the
        shapes it shares with the previous frame's choice. Unitless; a
        candidate that fits the neighbours exactly still wins.
    tie_tolerance : float, optional
        Scene units. When a bundle's best candidate reproduces its neighbours
        to within this (the neighbours cannot tell candidates apart, e.g. a
        bundle that does not move while a shape moves the skin around it),
        the candidates are re-ranked by the shapes the moving bundles chose
        (each bundle votes with its distance from the neutral). Default
        ``1e-5`` times the face size; 0 disables it.
    neighbor_rings : int
        Bundles whose surface points judge a candidate (§5.1): the natural
        neighbours (1), or also their neighbours (2), ...
    grid_density : float
        Grid cells per tetrahedron of a bundle (the grid has about
        ``(n_tets * grid_density)^(1/3)`` cells along its longest side):
        more cells mean fewer candidates per query and more memory.
    exact : bool
        Add the ``B x B`` residual correction so that the surface passes
        exactly through every bundle.
    threads : int
        Threads for the final blend (2 on a 2-core machine).
    bundle_names : list of str, optional
        Bundle names for messages (default their indices).

    Attributes
    ----------
    stats : dict
        Point counts, tetrahedra kept and pruned, grid size, memory in
        bytes, build time.
    face_size : float
        Bounding-box diagonal of the vertices with natural-neighbour weights
        (the face region), scene units.
    nn : natural_neighbor.NaturalNeighbors
        The natural-neighbour weights and Voronoi cells.
    """

    def __init__(self, neutral, faces, shapes, bundle_faces, bundle_bary, *, names=None, uvs=None, nn_method=None,
                 jaw=None, shape_jaw=None, prune_tolerance=None, merge_tolerance=None, neighbors: int = 6,
                 min_quality: float = 0.05, max_edge=None, forbidden=(), min_tets_per_point: int = 4,
                 temporal_bias: float = 0.25, tie_tolerance=None, neighbor_rings: int = 1, grid_density: float = 1.0,
                 exact: bool = True,
                 threads: int = 2, bundle_names=None):
        t0 = time.perf_counter()
        X = self._set_inputs(neutral, faces, shapes, names, bundle_faces, bundle_bary, exact, threads, bundle_names)
        D = self._unskin_dataset(X, jaw, shape_jaw)
        W = self._natural_neighbors(uvs, nn_method, prune_tolerance, temporal_bias, tie_tolerance)
        mags, dup_tol = self._check_shapes_move(D, jaw)
        self._store_dataset(D, mags)
        P, move = self._point_clouds(X, dup_tol)
        keep = self._prune(W, mags, move, forbidden)
        st, counts, n_points, n_distinct = self._tetrahedra(P, keep, merge_tolerance, neighbors, min_quality, max_edge,
                                                            min_tets_per_point)
        self._convex_hulls(P)
        self._tetrahedron_maps(P, counts)
        self._build_grid(grid_density)
        self._neighbor_tables(P, neighbor_rings)
        self._stitching_matrices(W)
        self._collect_stats(t0, P, W, move, st, counts, n_points, n_distinct)
        self.last = {}
        self._pool = ThreadPoolExecutor(self.threads) if self.threads > 1 else None

    # ------------------------------------------------------------------ build steps

    def _set_inputs(self, neutral, faces, shapes, names, bundle_faces, bundle_bary, exact, threads, bundle_names):
        """Check and store the mesh, the dataset shapes (S,V,3) and names, the bundle binding and the settings."""
        x0, F, X, self.names, bf, bb = check_reconstruction_inputs(
            neutral, faces, shapes, names, bundle_faces, bundle_bary, method="Local geometric indexing")
        nv, S, B = len(x0), len(X), len(bf)
        self.neutral, self.faces = x0, F
        self.bundle_faces, self.bundle_bary = bf, bb
        self.B, self.S, self.V = B, S, nv
        self.exact = bool(exact)
        self.threads = max(1, int(threads))
        self.bundle_names = None if bundle_names is None else [str(n) for n in bundle_names]
        return X

    def _unskin_dataset(self, X, jaw, shape_jaw):
        """Store the jaw rig and return the dataset's deltas (S,V,3), unskinned with it (Eq. 2)."""
        x0, F, bf, bb, S, nv = self.neutral, self.faces, self.bundle_faces, self.bundle_bary, self.S, self.V
        self.jaw = jaw
        if jaw is not None:
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
            self.shape_jaw = sj
            self.bundle_jaw_weights = (jaw.weights[F[bf]] * bb).sum(1)
        else:
            D = X - x0
            self.shape_jaw = None
            self.bundle_jaw_weights = None
        return D

    def _natural_neighbors(self, uvs, nn_method, prune_tolerance, temporal_bias, tie_tolerance):
        """Natural-neighbour weights (V,B) of the bundles (§5), the face size and the tolerances scaled by it."""
        x0, F, bf, bb = self.neutral, self.faces, self.bundle_faces, self.bundle_bary
        self.nn = natural_neighbor_weights(x0, F, bf, bb, uvs=uvs, method=nn_method)
        W = self.nn.weights.tocsr()
        W.sort_indices()
        dom = self.nn.domain
        lo, hi = x0[dom].min(axis=0), x0[dom].max(axis=0)
        self.face_size = float(np.linalg.norm(hi - lo))
        self.prune_tolerance = 1e-7 * self.face_size if prune_tolerance is None else float(prune_tolerance)
        self.temporal_bias = float(temporal_bias)
        self.tie_tolerance = 1e-5 * self.face_size if tie_tolerance is None else float(tie_tolerance)
        return W

    def _check_shapes_move(self, D, jaw):
        """Reject shapes equal to the neutral or to each other; returns vertex motions (S,V) and the tolerance."""
        dup_tol = 1e-7 * self.face_size
        mags = np.linalg.norm(D, axis=2)  # (S,V)
        still = np.flatnonzero(mags.max(axis=1) <= dup_tol)
        if len(still):
            why = ("equals the neutral once the jaw motion is removed (the jaw rig alone reproduces it)"
                   if jaw is not None else "equals the neutral (moves nothing)")
            raise DatasetError(f"Dataset shape {self.names[still[0]]!r} {why}; remove it from the dataset.")
        self._check_duplicates(D, dup_tol)
        return mags, dup_tol

    def _check_duplicates(self, D, tol):
        """Raise a DatasetError when two shapes' deltas ``D`` (S,V,3) agree to ``tol`` scene units."""
        S = len(D)
        flat = D.reshape(S, -1)
        rng = np.random.default_rng(0)
        proj = flat @ rng.standard_normal((flat.shape[1], 4))
        scale = np.linalg.norm(flat, axis=1).max() + 1e-300
        # candidates: close in every random projection, then verified exactly
        d = np.abs(proj[:, None, :] - proj[None, :, :]).max(axis=2)
        i, j = np.nonzero(np.triu(d <= 1e-6 * scale * np.sqrt(flat.shape[1]), 1))
        for a, b in zip(i, j):
            if np.abs(flat[a] - flat[b]).max() <= tol:
                raise DatasetError(
                    f"Dataset shapes {self.names[a]!r} and {self.names[b]!r} are duplicates (identical to "
                    f"{tol:.2g} scene units); remove one of them."
                )

    def _store_dataset(self, D, mags):
        """Keep the float32 deltas of the vertices that some shape moves, shape-major, shape 0 = the neutral."""
        S = self.S
        S1 = S + 1
        self.S1 = S1
        # only vertices that some shape moves are blended; float32 is ample for deltas (1e-7 relative)
        # (shape-major layout: a vertex run of one shape is contiguous, which keeps the gathers cached)
        self._active = np.flatnonzero(mags.max(axis=0) > 0)
        Dv = np.zeros((S1, len(self._active), 3), dtype=np.float32)
        Dv[1:] = D[:, self._active]
        self._Dact = Dv.reshape(-1, 3)
        del Dv

    def _collect_stats(self, t0, P, W, move, st, counts, n_points, n_distinct):
        """Fill ``stats``: point, tetrahedron and grid counts, memory in bytes, build time."""
        B, S, nv = self.B, self.S, self.V
        mem = {
            "tetrahedra": int(self.tets.nbytes + self._tet_aff.nbytes + self._tet_lo.nbytes
                              + self._tet_hi.nbytes + self.tet_bundle.nbytes + self._tet_flat.nbytes),
            "merged_points": int(self._mem_ptr.nbytes + self._mem.nbytes),
            "grid": int(self._cell_start.nbytes + self._cell_tets.nbytes),
            "point_clouds": int(P.nbytes),
            "natural_neighbor_weights": int(2 * (W.data.nbytes + W.indices.nbytes + W.indptr.nbytes)),
            "dataset": int(self._Dact.nbytes),
        }
        kept = len(self.tets)
        self.stats = {
            "bundles": B,
            "shapes": S,
            "vertices": nv,
            "face_size": self.face_size,
            "points_per_bundle": {"min": int(n_points.min()), "mean": float(n_points.mean()),
                                  "max": int(n_points.max())},
            "distinct_points_per_bundle": {"min": int(n_distinct.min()), "mean": float(n_distinct.mean()),
                                           "max": int(n_distinct.max())},
            "tetrahedra_candidates": int(st["candidates"]),
            "tetrahedra_kept": int(kept),
            "tetrahedra_pruned_thin": int(st["thin"]),
            "tetrahedra_pruned_large": int(st["large"]),
            "tetrahedra_pruned_flagged": int(st["flagged"]),
            "tetrahedra_restored_for_coverage": int(st["restored"]),
            "flat_point_clouds": int(st["flat_clouds"]),
            "segment_point_clouds": int(st["segment_clouds"]),
            "tetrahedra_per_bundle": {"min": int(min(counts)), "mean": float(np.mean(counts)),
                                      "max": int(max(counts))},
            "grid_cells": int(len(self._cell_start) - 1),
            "grid_entries": int(len(self._cell_tets)),
            "memory_bytes": mem,
            "memory_bytes_total": int(sum(mem.values())),
            "memory_bytes_per_tetrahedron": float((mem["tetrahedra"] + mem["grid"]) / max(kept, 1)),
            "shapes_merged_into_other_points": int(n_points.sum() - n_distinct.sum()),
            "shapes_no_bundle_sees": [self.names[k] for k in np.flatnonzero(move.max(axis=1) <= self.merge_tolerance)],
            "residual_matrix_condition": self._G_cond,
            "natural_neighbor_method": self.nn.method,
            "build_seconds": time.perf_counter() - t0,
        }

    # ------------------------------------------------------------------ per-frame

    def _check_bundles(self, q, what="bundles"):
        return check_bundle_frame(q, self.B, self.bundle_names, what)

    def unskinned_bundles(self, q, jaw=None):
        """Bundle positions with the jaw motion removed (Eq. 2), scene units, (B,3)."""
        if self.jaw is None:
            return q
        if jaw is None:
            raise BundleError("This indexer has a jaw rig; pass the frame's jaw parameters (angle, tx, ty, tz).")
        return self.jaw.unskin(q, jaw, self.bundle_jaw_weights)

    def reconstruct(self, bundles, jaw=None, *, stitching: str = "natural_neighbor", exact=None, prev=None):
        """Rebuild the high-resolution face for one frame of bundles.

        Parameters
        ----------
        bundles : (B,3) array_like
            Bundle positions (in the neutral's rigid frame), scene units.
        jaw : (4,) array_like, optional
            The frame's jaw parameters ``(angle rad, tx, ty, tz)``; required
            when the indexer has a jaw rig.
        stitching : {"natural_neighbor", "rbf", "voronoi"}
            ``"natural_neighbor"``: the paper's method (§5). ``"rbf"``: the
            §7 baseline, Gaussian RBF interpolation of the per-bundle shape
            weights (no exact interpolation unless ``exact=True``).
            ``"voronoi"``: every Voronoi cell takes its bundle's geometry
            (Fig. 1, top right; discontinuous).
        exact : bool, optional
            Residual correction through the bundles (default: the indexer's
            setting for natural neighbours, ``False`` for the others).
        prev : (B,4) int array_like, optional
            Previous frame's tetrahedra, for the temporal preference.

        Returns
        -------
        (V,3) float64 ndarray
            Reconstructed vertices, scene units. ``self.last`` holds the
            chosen tetrahedra (``shape_ids``, ``bary``), the distance of each
            bundle to its volume (``distance``; > 0 means projected) and the
            largest bundle residual before the correction (``residual``).

        Raises
        ------
        BundleError
            On a wrong shape or NaN bundle positions, or a missing jaw pose.
        """
        with one_blas_thread():
            return self._reconstruct(bundles, jaw, stitching, exact, prev)

    def _reconstruct(self, bundles, jaw, stitching, exact, prev):
        q = self._check_bundles(bundles)
        qu = self.unskinned_bundles(q, jaw)
        ids, bary, dist = self.locate(qu, prev)
        if stitching == "natural_neighbor":
            Xu = self.blend(ids, bary)
            Wd, lu = self.W, self._G_lu
            ex = self.exact if exact is None else bool(exact)
        elif stitching in ("rbf", "voronoi"):
            Wd = self._rbf_matrix() if stitching == "rbf" else self._voronoi_matrix()
            Xu = self._blend_dense(Wd, ids, bary)
            ex = False if exact is None else bool(exact)
            lu = self._lu_for(stitching) if ex else None
        else:
            raise FaceLabError(f"Unknown stitching {stitching!r}; use 'natural_neighbor', 'rbf' or 'voronoi'.")
        X = self.jaw.skin(Xu, jaw) if self.jaw is not None else Xu
        r = q - self._bary_mat @ X
        res = np.linalg.norm(r, axis=1)
        if ex:
            X = X + Wd @ sla.lu_solve(lu, r)
        self.last = {"shape_ids": ids, "bary": bary, "distance": dist, "residual": float(res.max()),
                     "projected": int((dist > 0).sum())}
        return X

    def explain(self, bundle: int):
        """Human-readable description of a bundle's last chosen shapes (for UI reports)."""
        if not self.last:
            return "no frame reconstructed yet"
        ids, w = self.last["shape_ids"][bundle], self.last["bary"][bundle]
        parts = [f"{w[k]:.2f} {'neutral' if ids[k] == 0 else self.names[ids[k] - 1]}" for k in range(4) if w[k] > 1e-6]
        return ", ".join(parts)

    def close(self):
        """Stop the blend threads (also done when the indexer is garbage collected)."""
        if self._pool is not None:
            self._pool.shutdown(wait=False)
            self._pool = None

    def __del__(self):  # pragma: no cover - best effort
        try:
            self.close()
        except Exception:
            pass
