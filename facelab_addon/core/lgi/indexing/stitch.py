"""Stitching per-bundle geometry into one face, frame by frame (Cong, Lan and Fedkiw 2019, §5, §7).

The blend of :class:`~facelab_addon.core.lgi.indexer.GeometricIndexer` (the
mixin :class:`IndexerStitch`):

* **Stitching** (§5): natural-neighbour (Sibson) weights of the bundles on the
  neutral mesh, in UV space or with geodesics
  (:mod:`facelab_addon.core.lgi.natural_neighbor`). The blend is one sparse
  product: vertex ``v`` gets ``sum_i W[v,i] sum_k beta_ik b_{t_ik}(v)``
  (per-vertex shape weights ``W @ Beta``, then a product with the float32,
  shape-major dataset of the vertices that move).
* **Exact interpolation**: the paper's surface passes through bundles that sit
  on vertices. Our bundles sit anywhere in a triangle, and a bundle may have
  been projected, so a last step adds ``W @ c`` with ``(Bary W) c =
  residual``: a ``B x B`` solve, factored once, that makes the surface pass
  exactly through every bundle (like the paper's §7 correction of the RBF
  variant with [6]). ``exact=False`` skips it.
* **Baseline stitchings** (§7, Fig. 4; Fig. 1): Gaussian RBF interpolation of
  the per-bundle shape weights (``"rbf"``) and Voronoi cells (``"voronoi"``).
* **Temporal smoothing** (§7): a central moving average of every bundle's
  barycentric shape weights (relative to the jaw-skinned neutral, so the jaw
  is not smoothed), applied as the average of the frames' blends (the
  stitching is linear in the weights: no extra blending). With
  ``exact=True`` the surface then passes through the moving average of the
  bundles, so the noise of single frames is not put back.
* **Sequences** run on two cores when one is idle: frames are indexed in
  order on the calling thread while a worker blends them and finishes the
  frames whose smoothing window is complete. BLAS is kept to one thread (its
  spinning threads cost more than they give per frame).

Shapes: per-bundle shape ids and weights (B,K); natural-neighbour weights
``W`` (V,B) sparse; results (V,3) or (T,V,3). Units: positions in scene units;
weights are unitless.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp

from ..errors import BundleError, MeshError
from ..geometry.linsolve import idle_core, one_blas_thread
from .inputs import check_bundle_sequence
from .natural_neighbor import gaussian_rbf_weights, surface_points

__all__ = ["IndexerStitch"]


class IndexerStitch:
    """Stitching and sequences of :class:`~facelab_addon.core.lgi.indexer.GeometricIndexer` (§5, §7).

    A mixin: :meth:`_stitching_matrices` builds the blend's row blocks and the
    exact-interpolation factor once; :meth:`blend` and
    :meth:`reconstruct_sequence` use them with the choices of
    :meth:`~facelab_addon.core.lgi.locate.IndexerLocate.locate`.
    """

    def _stitching_matrices(self, W):
        """Natural-neighbour weights of the moving vertices in row blocks, and the exact-interpolation factor."""
        F, bf, bb, B, nv = self.faces, self.bundle_faces, self.bundle_bary, self.B, self.V
        if (np.diff(W.indptr) == 0).any():
            raise MeshError("Some vertices got no natural-neighbour weight; check that every vertex is used by a face.")
        Wa = W[self._active].tocsr()
        na = len(self._active)
        cuts = np.linspace(0, na, self.threads + 1).astype(np.int64)
        def part(a, b):
            return (int(a), Wa[a:b].tocsr())

        self._w_parts = [part(a, b) for a, b in zip(cuts[:-1], cuts[1:]) if b > a]
        self._w_full = part(0, na)
        self.W = W
        # residual correction for exact interpolation: (Bary W) c = r
        Bary = sp.csr_matrix((bb.ravel(), (np.repeat(np.arange(B), 3), F[bf].ravel())), shape=(B, nv))
        self._bary_mat = Bary
        G = (Bary @ W).toarray()
        self._G_lu = sla.lu_factor(G)
        self._G_cond = float(np.linalg.cond(G))
        self._rbf = None
        self._voronoi = None

    def _blend_part(self, part, Beta):
        """One row block of the blend: per-vertex shape weights ``C = W_rows @ Beta`` (sparse), then one
        sparse product with the shape-major float32 dataset."""
        off, Wp = part
        C = Wp @ Beta
        n = Wp.shape[0]
        rows = np.repeat(np.arange(off, off + n, dtype=np.int32), np.diff(C.indptr))
        idx = C.indices.astype(np.int32) * np.int32(len(self._active)) + rows
        A = sp.csr_matrix((C.data.astype(np.float32), idx, C.indptr), shape=(n, self._Dact.shape[0]))
        return A @ self._Dact

    def _blend_active(self, sid, coef, split: bool = True):
        """(n_active,3) float32 unskinned deltas of the moving vertices for per-bundle shape weights."""
        sid = np.asarray(sid, dtype=np.int64)
        coef = np.asarray(coef, dtype=np.float64)
        K = sid.shape[1]
        Beta = sp.csr_matrix((coef.ravel(), (np.repeat(np.arange(self.B), K), sid.ravel())), shape=(self.B, self.S1))
        if not split:
            return self._blend_part(self._w_full, Beta)
        if self._pool is not None and len(self._w_parts) > 1 and idle_core():
            futs = [self._pool.submit(self._blend_part, part, Beta) for part in self._w_parts]
            parts = [f.result() for f in futs]
        else:
            parts = [self._blend_part(part, Beta) for part in self._w_parts]
        return parts[0] if len(parts) == 1 else np.vstack(parts)

    def blend(self, sid, coef, *, split: bool = True):
        """Unskinned natural-neighbour blend of per-bundle shape weights (Eq. 1 sewn with §5).

        ``x0 + sum_i W[:, i] sum_k coef_ik b*_{sid_ik}``, evaluated as one
        sparse product per row block (one block per thread) over the moving
        vertices. The blend is linear in ``coef``: the blend of averaged
        weights is the average of the blends (temporal smoothing uses this).

        Parameters
        ----------
        sid : (B,K) int array_like
            Shape ids per bundle (0 = neutral).
        coef : (B,K) array_like
            Their weights (each row sums to 1).
        split : bool
            Spread the row blocks over the indexer's threads when a core is
            idle (``False`` when the caller already runs frames in parallel).

        Returns
        -------
        (V,3) float64 ndarray
            Scene units.
        """
        out = self.neutral.copy()
        out[self._active] += self._blend_active(sid, coef, split)
        return out

    def _blend_dense(self, Wd, sid, coef):
        """Blend with a dense (V,B) weight matrix (RBF / Voronoi stitching)."""
        K = sid.shape[1]
        Beta = sp.csr_matrix((coef.ravel(), (np.repeat(np.arange(self.B), K), sid.ravel())), shape=(self.B, self.S1))
        Wa = Wd[self._active]
        C = np.asarray((Beta.T @ np.asarray(Wa.toarray() if sp.issparse(Wa) else Wa).T).T)
        out = self.neutral.copy()
        out[self._active] += np.einsum("as,sax->ax", C, self._Dact.reshape(self.S1, -1, 3).astype(np.float64))
        return out

    def _finish(self, Xu, q, jaw, exact):
        X = self.jaw.skin(Xu, jaw) if self.jaw is not None else Xu
        if exact:
            r = q - self._bary_mat @ X
            X = X + self.W @ sla.lu_solve(self._G_lu, r)
        return X

    def _lu_for(self, stitching):
        key = "_lu_" + stitching
        if getattr(self, key, None) is None:
            Wd = self._rbf_matrix() if stitching == "rbf" else self._voronoi_matrix()
            G = self._bary_mat @ Wd
            G = G.toarray() if sp.issparse(G) else np.asarray(G)
            setattr(self, key, sla.lu_factor(G))
        return getattr(self, key)

    def _rbf_matrix(self):
        if self._rbf is None:
            sites = surface_points(self.neutral, self.faces, self.bundle_faces, self.bundle_bary)
            self._rbf = gaussian_rbf_weights(self.neutral, sites)
        return self._rbf

    def _voronoi_matrix(self):
        if self._voronoi is None:
            self._voronoi = sp.csr_matrix((np.ones(self.V), (np.arange(self.V), self.nn.cell)), shape=(self.V, self.B))
        return self._voronoi

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
        Q = check_bundle_sequence(bundles, self.B)
        out = np.full((len(Q), self.V, 3), np.nan)
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
        Q = check_bundle_sequence(bundles, self.B)
        T = len(Q)
        if self.jaw is not None:
            if jaw is None:
                raise BundleError("This indexer has a jaw rig; pass jaw parameters per frame, (T,4).")
            J = np.asarray(jaw, dtype=np.float64)
            if J.shape not in ((T, 4), (T, 4, 4)):
                raise BundleError(f"Expected jaw parameters per frame, (T,4) or (T,4,4) with T={T}, got {J.shape}.")
        else:
            J = [None] * T
        ok = np.isfinite(Q).all(axis=(1, 2))
        if self.jaw is not None:
            ok &= np.isfinite(J.reshape(T, -1)).all(axis=1)
        skipped = [int(t) for t in np.flatnonzero(~ok)]
        ex = self.exact if exact is None else bool(exact)
        ids_t = np.zeros((T, self.B, 4), dtype=np.int64)
        bary_t = np.zeros((T, self.B, 4))
        half = max(int(smooth), 1) // 2
        valid = np.flatnonzero(ok)
        deltas, q_unskinned = {}, {}
        acc, in_sum = [None], set()

        def blend(t):
            deltas[t] = self._blend_active(ids_t[t], bary_t[t], split=False)

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
                if self.jaw is not None:
                    target = self.jaw.skin(target, J[t], self.bundle_jaw_weights)
            Xu = self.neutral.copy()
            Xu[self._active] += d
            sink(int(t), self._finish(Xu, target, J[t], ex))
            for s in [s for s in deltas if s <= t - half and s not in in_sum]:
                del deltas[s]
                q_unskinned.pop(s, None)

        # Two-stage pipeline: frames are indexed in order on this thread while a worker blends each indexed
        # frame and finishes every frame whose smoothing window is complete (one worker: FIFO order).
        if pipeline == "auto":
            pipeline = idle_core()
        worker = ThreadPoolExecutor(1) if (self.threads > 1 and pipeline) else None
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
                    ids_t[t], bary_t[t], _ = self.locate(qu, prev)
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
