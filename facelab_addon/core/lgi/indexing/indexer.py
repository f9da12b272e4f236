"""Local geometric indexing: a high-resolution face from sparse 3D bundles.

Cong, Lan and Fedkiw 2019, "Local Geometric Indexing of High Resolution Data
for Facial Reconstruction from Sparse Markers". Instead of fitting a
blendshape model to the bundles, every bundle looks up the dataset shapes
whose local geometry reproduces its position, and the per-bundle geometry is
sewn together with natural-neighbour weights.

Build once (:class:`GeometricIndexer`), then reconstruct every frame. The
indexer composes the state objects of its sibling modules, built in order:

* :class:`~facelab_addon.core.lgi.indexing.dataset.IndexedDataset`: checked
  inputs, the jaw (§6, Eq. 2: with a
  :class:`~facelab_addon.core.lgi.jaw.JawRig` the dataset shapes are unskinned,
  ``b* = T(theta_n)^-1 (x0 + b_n) - x0``, bundles are unskinned per frame with
  the frame's jaw parameters and the blend is skinned back by linear blend
  skinning), natural-neighbour weights (§5) and the float32 dataset;
* :class:`~facelab_addon.core.lgi.indexing.clouds.BundleClouds` and
  :class:`~facelab_addon.core.lgi.indexing.clouds.TetGrid`: point clouds,
  pruning, merged points, tetrahedra, hulls and grids (§4, §4.1);
* :class:`~facelab_addon.core.lgi.indexing.locate.Locator`: neighbour tables
  and the per-frame choice of tetrahedra (§4, §5.1, Eq. 1);
* :class:`~facelab_addon.core.lgi.indexing.stitch.Stitcher`: the blend, exact
  interpolation and the RBF and Voronoi stitchings (§5, §7).

:meth:`GeometricIndexer.reconstruct` chains them for one frame: unskin the
bundles, locate, blend, skin, exact-interpolation correction.
:meth:`GeometricIndexer.reconstruct_stream` runs a sequence with temporal
smoothing (§7): a central moving average of every bundle's barycentric shape
weights (relative to the jaw-skinned neutral, so the jaw is not smoothed),
applied as the average of the frames' blends (the stitching is linear in the
weights: no extra blending). With exact interpolation the surface then passes
through the moving average of the bundles, so the noise of single frames is
not put back. Sequences run on two cores when one is idle: frames are indexed
in order on the calling thread while a worker blends them and finishes the
frames whose smoothing window is complete; BLAS is kept to one thread.

Units: positions in scene units; barycentric and natural-neighbour weights
are unitless; jaw angles in radians.
"""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import scipy.linalg as sla

from ...errors import BundleError, FaceLabError
from ...geometry.linsolve import idle_core, one_blas_thread
from ..inputs import check_bundle_frame, check_bundle_sequence
from .clouds import build_clouds, build_grid
from .dataset import build_dataset
from .locate import Locator, build_neighbor_tables
from .params import IndexerParams
from .stitch import Stitcher

__all__ = ["GeometricIndexer", "indexer_stats"]


class GeometricIndexer:
    """Local geometric indexing of a shape dataset by surface-bound bundles.

    Build once per (mesh, dataset, bundle binding, params); :meth:`reconstruct`
    and :meth:`reconstruct_sequence` are then cheap per frame.

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
    bundle_names : list of str, optional
        Bundle names for messages (default their indices).
    uvs : (V,2) or (F,3,2) array_like, optional
        UV map; natural-neighbour weights are then built in UV space (§5,
        the paper's choice), else with geodesics on the mesh.
    jaw : JawRig, optional
        Jaw articulation (§6, Eq. 2). Requires ``shape_jaw``.
    shape_jaw : (S,4) or (S,4,4) array_like, optional
        Jaw parameters ``(angle rad, tx, ty, tz)`` or rigid jaw poses of
        every dataset shape (:meth:`JawRig.fit_pose` estimates them).
    params : IndexerParams, optional
        Tolerances, tetrahedra, grid, exactness and threads (default
        ``IndexerParams()``).

    Attributes
    ----------
    params : IndexerParams
    dataset : IndexedDataset
        Mesh, bundles, jaw, natural-neighbour weights (``dataset.nn``,
        ``dataset.weights``), ``dataset.face_size`` and the stored deltas.
    clouds : BundleClouds
    grid : TetGrid
    locator : Locator
        ``locator.locate(q, prev)`` chooses the tetrahedra of unskinned bundles.
    stitcher : Stitcher
        ``stitcher.blend(sid, coef)`` sews per-bundle shape weights.
    stats : dict
        Point counts, tetrahedra kept and pruned, grid size, memory in
        bytes, build time (:func:`indexer_stats`).
    last : dict
        The last :meth:`reconstruct`'s choice (see there).
    last_sequence : dict
        After a sequence: ``shape_ids`` (T,B,4), ``bary`` (T,B,4) and
        ``skipped`` (list of frame indices).
    """

    def __init__(self, neutral, faces, shapes, bundle_faces, bundle_bary, *, names=None, bundle_names=None,
                 uvs=None, jaw=None, shape_jaw=None, params: IndexerParams | None = None):
        t0 = time.perf_counter()
        p = IndexerParams() if params is None else params
        self.params = p
        ds, X, motion = build_dataset(neutral, faces, shapes, bundle_faces, bundle_bary, names=names,
                                      bundle_names=bundle_names, uvs=uvs, nn_method=p.nn_method, jaw=jaw,
                                      shape_jaw=shape_jaw)
        self.dataset = ds
        self.clouds = build_clouds(ds, X, motion, p)
        del X, motion
        self.grid = build_grid(self.clouds, p.grid_density, ds.face_size)
        tables = build_neighbor_tables(ds.nn.neighbors, self.clouds, p.neighbor_rings)
        self.locator = Locator(self.clouds, self.grid, tables, temporal_bias=p.temporal_bias,
                               tie_tolerance=p.tie_tolerance_at(ds.face_size), face_size=ds.face_size)
        self.stitcher = Stitcher(ds, p.threads)
        self.stats = indexer_stats(ds, self.clouds, self.grid, self.stitcher)
        self.stats["build_seconds"] = time.perf_counter() - t0
        self.last = {}

    # ------------------------------------------------------------------ per-frame

    def unskinned_bundles(self, q, jaw=None):
        """Bundle positions with the jaw motion removed (Eq. 2), scene units, (B,3)."""
        ds = self.dataset
        if ds.jaw is None:
            return q
        if jaw is None:
            raise BundleError("This indexer has a jaw rig; pass the frame's jaw parameters (angle, tx, ty, tz).")
        return ds.jaw.unskin(q, jaw, ds.bundle_jaw_weights)

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
        ds, st = self.dataset, self.stitcher
        q = check_bundle_frame(bundles, ds.B, ds.bundle_names, "bundles")
        qu = self.unskinned_bundles(q, jaw)
        ids, bary, dist = self.locator.locate(qu, prev)
        if stitching == "natural_neighbor":
            Xu = st.blend(ids, bary)
            Wd, lu = st.weights, st.factor(stitching)
            ex = bool(self.params.exact) if exact is None else bool(exact)
        elif stitching in ("rbf", "voronoi"):
            Wd = st.stitching_matrix(stitching)
            Xu = st.blend_dense(Wd, ids, bary)
            ex = False if exact is None else bool(exact)
            lu = st.factor(stitching) if ex else None
        else:
            raise FaceLabError(f"Unknown stitching {stitching!r}; use 'natural_neighbor', 'rbf' or 'voronoi'.")
        X = ds.jaw.skin(Xu, jaw) if ds.jaw is not None else Xu
        r = q - st.bary_matrix @ X
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
        names = self.dataset.names
        parts = [f"{w[k]:.2f} {'neutral' if ids[k] == 0 else names[ids[k] - 1]}" for k in range(4) if w[k] > 1e-6]
        return ", ".join(parts)

    def close(self):
        """Stop the blend threads (also done when the indexer is garbage collected)."""
        self.stitcher.close()

    def __del__(self):  # pragma: no cover - best effort
        try:
            self.close()
        except Exception:
            pass

    # ------------------------------------------------------------------ sequences

    def reconstruct_sequence(self, bundles, jaw=None, *, smooth: int = 1, exact=None, progress=None,
                             pipeline="auto"):
        """Rebuild every frame of an animated bundle sequence.

        Frames are indexed in order, each preferring tetrahedra that share
        shapes with the previous frame's (§5.1). With ``smooth > 1`` the
        barycentric shape weights of every bundle are averaged over a
        centred window of ``smooth`` frames (§7, "Temporal Smoothing"), relative
        to the jaw-skinned neutral (the jaw itself is not smoothed). The
        stitching is linear in the weights, so the average is taken over the
        frames' unskinned blends: smoothing costs no extra blending.

        Parameters
        ----------
        bundles : (T,B,3) array_like
            Bundle positions per frame, scene units. A frame with any NaN
            bundle is skipped.
        jaw : (T,4) or (T,4,4) array_like, optional
            Jaw parameters or rigid jaw poses per frame (required with a jaw
            rig). A frame with NaN jaw parameters is skipped.
        smooth : int
            Moving-average window in frames (1 = off; even values are
            rounded up to the next odd one). Frames skipped for NaN bundles
            leave the window (it shrinks at gaps and at the ends).
        exact : bool, optional
            Residual correction (default: the indexer's). Without smoothing
            the surface passes exactly through each frame's bundles; with
            smoothing it passes exactly through the moving average of the
            bundles over the same window (with the jaw motion removed, so the
            jaw is not smoothed): the positions that the averaged weights
            index wherever a tetrahedron holds the bundles. So the noise of
            single frames is not put back (§7: smoothing the weights has a
            "negligible impact on the ability to interpolate the bundles").
        progress : callable, optional
            Called as ``progress(done, total)`` after every frame is indexed.
        pipeline : bool or "auto"
            Blend and finish frames on a worker thread while the next frames
            are indexed (with ``threads > 1``). ``"auto"``: only when a core
            is idle (1-minute load average below ``cpu_count - 0.5``): on an
            oversubscribed machine the two threads wait on each other for the
            interpreter lock and run 2-4 times slower than one (measured).

        Returns
        -------
        frames : (T,V,3) float64 ndarray
            Reconstructions, scene units; skipped frames are NaN.
        skipped : list of int
            Frames skipped because of NaN bundle positions.
        """
        ds = self.dataset
        Q = check_bundle_sequence(bundles, ds.B)
        out = np.full((len(Q), ds.V, 3), np.nan)
        skipped = self.reconstruct_stream(Q, jaw, out.__setitem__, smooth=smooth, exact=exact, progress=progress,
                                          pipeline=pipeline)
        return out, skipped

    def reconstruct_stream(self, bundles, jaw, sink, *, smooth: int = 1, exact=None, progress=None,
                           pipeline="auto"):
        """:meth:`reconstruct_sequence` without the (T,V,3) result: each frame is handed to ``sink``.

        Only the frames of the current smoothing window are held, so memory
        does not grow with the frames times the vertices.

        Parameters
        ----------
        bundles, jaw, smooth, exact, progress, pipeline
            As in :meth:`reconstruct_sequence`.
        sink : callable(t, X)
            Called with the frame index ``t`` and its face ``X`` (V,3) float64
            (scene units, a new array) for every frame that is not skipped, in
            increasing ``t``, from one thread at a time (the pipeline's worker
            when it runs).

        Returns
        -------
        skipped : list of int
            Frames skipped (NaN bundles or jaw); never passed to ``sink``.
        """
        with one_blas_thread():  # BLAS threads would spin against the pipeline's own threads
            return self._reconstruct_sequence(bundles, jaw, smooth, exact, progress, pipeline, sink)

    def _reconstruct_sequence(self, bundles, jaw, smooth, exact, progress, pipeline, sink):
        ds, st = self.dataset, self.stitcher
        Q = check_bundle_sequence(bundles, ds.B)
        T = len(Q)
        if ds.jaw is not None:
            if jaw is None:
                raise BundleError("This indexer has a jaw rig; pass jaw parameters per frame, (T,4).")
            J = np.asarray(jaw, dtype=np.float64)
            if J.shape not in ((T, 4), (T, 4, 4)):
                raise BundleError(f"Expected jaw parameters per frame, (T,4) or (T,4,4) with T={T}, got {J.shape}.")
        else:
            J = [None] * T
        ok = np.isfinite(Q).all(axis=(1, 2))
        if ds.jaw is not None:
            ok &= np.isfinite(J.reshape(T, -1)).all(axis=1)
        skipped = [int(t) for t in np.flatnonzero(~ok)]
        ex = bool(self.params.exact) if exact is None else bool(exact)
        ids_t = np.zeros((T, ds.B, 4), dtype=np.int64)
        bary_t = np.zeros((T, ds.B, 4))
        half = max(int(smooth), 1) // 2
        valid = np.flatnonzero(ok)
        deltas, q_unskinned = {}, {}
        acc, in_sum = [None], set()

        def blend(t):
            deltas[t] = st.blend_active(ids_t[t], bary_t[t], split=False)

        def finish(t):
            # The blend is linear in the barycentric weights, so the blend of the weights averaged over the
            # window is the average of the frames' blends: each frame is blended once (no extra cost).
            win = valid[(valid >= t - half) & (valid <= t + half)]
            if len(win) == 1:
                d, target = deltas[t], Q[t]
            else:
                # running sum over the window: frames enter and leave once (frames finish in order)
                for s in set(win) - in_sum:
                    acc[0] = deltas[s].astype(np.float64) if acc[0] is None else acc[0] + deltas[s]
                    in_sum.add(s)
                for s in in_sum - set(win):
                    acc[0] -= deltas[s]
                    in_sum.discard(s)
                d = acc[0] / len(win)
                # exact: through the moving average of the (jaw-unskinned) bundles, which is what the
                # averaged weights index where a tetrahedron holds the bundles
                target = np.mean([q_unskinned[s] for s in win], axis=0)
                if ds.jaw is not None:
                    target = ds.jaw.skin(target, J[t], ds.bundle_jaw_weights)
            Xu = ds.neutral.copy()
            Xu[ds.active] += d
            sink(int(t), st.finish(Xu, target, J[t], ex))
            for s in [s for s in deltas if s <= t - half and s not in in_sum]:
                del deltas[s]
                q_unskinned.pop(s, None)

        # Two-stage pipeline: frames are indexed in order on this thread while a worker blends each indexed
        # frame and finishes every frame whose smoothing window is complete (one worker: FIFO order).
        if pipeline == "auto":
            pipeline = idle_core()
        worker = ThreadPoolExecutor(1) if (st.threads > 1 and pipeline) else None
        self.last_pipeline = worker is not None
        futs = []
        run = (lambda f, t: futs.append(worker.submit(f, t))) if worker is not None else (lambda f, t: f(t))
        prev = None
        nxt = 0
        try:
            for t in range(T):
                if ok[t]:
                    qu = self.unskinned_bundles(Q[t], J[t])
                    q_unskinned[t] = qu
                    ids_t[t], bary_t[t], _ = self.locator.locate(qu, prev)
                    prev = ids_t[t]
                    run(blend, t)
                while nxt < len(valid) and valid[nxt] + half <= t:
                    run(finish, valid[nxt])
                    nxt += 1
                if progress is not None:
                    progress(t + 1, T)
            while nxt < len(valid):
                run(finish, valid[nxt])
                nxt += 1
            for f in futs:
                f.result()
        finally:
            if worker is not None:
                worker.shutdown(wait=True)
        self.last_sequence = {"shape_ids": ids_t, "bary": bary_t, "skipped": skipped}
        return skipped


def indexer_stats(ds, clouds, grid, stitcher):
    """Point, tetrahedron and grid counts and memory of a built indexer (without ``build_seconds``).

    Parameters
    ----------
    ds : IndexedDataset
    clouds : BundleClouds
    grid : TetGrid
    stitcher : Stitcher

    Returns
    -------
    dict
        Counts, ``face_size`` (scene units), ``memory_bytes`` per part and in
        total, ``memory_bytes_per_tetrahedron``, ``residual_matrix_condition``
        and the ``shapes_no_bundle_sees`` (names).
    """
    W = ds.weights
    c = clouds
    st = c.counts
    counts = c.tets_per_bundle
    n_points, n_distinct = c.n_points, c.n_distinct
    mem = {
        "tetrahedra": int(c.tets.nbytes + c.tet_affine.nbytes + c.tet_lo.nbytes
                          + c.tet_hi.nbytes + c.tet_bundle.nbytes + c.tet_flat.nbytes),
        "merged_points": int(c.member_ptr.nbytes + c.members.nbytes),
        "grid": int(grid.cell_start.nbytes + grid.cell_tets.nbytes),
        "point_clouds": int(c.points.nbytes),
        "natural_neighbor_weights": int(2 * (W.data.nbytes + W.indices.nbytes + W.indptr.nbytes)),
        "dataset": int(ds.deltas.nbytes),
    }
    kept = len(c.tets)
    return {
        "bundles": ds.B,
        "shapes": ds.S,
        "vertices": ds.V,
        "face_size": ds.face_size,
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
        "tetrahedra_per_bundle": {"min": int(counts.min()), "mean": float(np.mean(counts)),
                                  "max": int(counts.max())},
        "grid_cells": int(len(grid.cell_start) - 1),
        "grid_entries": int(len(grid.cell_tets)),
        "memory_bytes": mem,
        "memory_bytes_total": int(sum(mem.values())),
        "memory_bytes_per_tetrahedron": float((mem["tetrahedra"] + mem["grid"]) / max(kept, 1)),
        "shapes_merged_into_other_points": int(n_points.sum() - n_distinct.sum()),
        "shapes_no_bundle_sees": [ds.names[k] for k in np.flatnonzero(c.motion.max(axis=1) <= c.merge_tolerance)],
        "residual_matrix_condition": stitcher.condition,
        "natural_neighbor_method": ds.nn.method,
    }
