"""Stitching per-bundle geometry into one face, frame by frame (Cong, Lan and Fedkiw 2019, §5, §7).

The blend of :class:`~facelab_addon.core.lgi.indexing.indexer.GeometricIndexer`,
:class:`Stitcher`:

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
* **Linearity**: the blend is linear in the per-bundle weights, so the
  blend of weights averaged over frames is the average of the frames' blends
  (temporal smoothing, §7, uses this).

Shapes: per-bundle shape ids and weights (B,K); natural-neighbour weights
``W`` (V,B) sparse; results (V,3) or (T,V,3). Units: positions in scene units;
weights are unitless.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp

from ...errors import MeshError
from ...geometry.linsolve import idle_core
from ..natural_neighbor import gaussian_rbf_weights, surface_points

__all__ = ["Stitcher", "shape_weight_matrix"]


def shape_weight_matrix(sid, coef, n_ids):
    """Per-bundle shape weights as a sparse (B, n_ids) matrix ``Beta`` (duplicate ids add up).

    Parameters
    ----------
    sid : (B,K) int array_like
        Shape ids per bundle (0 = neutral, ``s + 1`` = ``shapes[s]``).
    coef : (B,K) array_like
        Their weights (unitless).
    n_ids : int
        Number of shape ids, the neutral included (``S + 1``).

    Returns
    -------
    (B, n_ids) scipy.sparse.csr_matrix
        ``Beta[i, sid[i, k]] += coef[i, k]``.
    """
    sid = np.asarray(sid, dtype=np.int64)
    coef = np.asarray(coef, dtype=np.float64)
    B, K = sid.shape
    return sp.csr_matrix((coef.ravel(), (np.repeat(np.arange(B), K), sid.ravel())), shape=(B, n_ids))


class Stitcher:
    """Sews per-bundle shape weights into one face (§5, §7), for one :class:`IndexedDataset`.

    Builds once: the natural-neighbour weights of the moving vertices in row
    blocks (one per thread) and the LU factor of the ``B x B``
    exact-interpolation matrix ``Bary W``; the RBF and Voronoi matrices are
    built on first use.

    Parameters
    ----------
    ds : IndexedDataset
    threads : int
        Row blocks of the blend, run on a thread pool when a core is idle.

    Attributes
    ----------
    ds : IndexedDataset
    threads : int
    weights : (V,B) scipy.sparse.csr_matrix
        Natural-neighbour weights (``ds.weights``).
    bary_matrix : (B,V) scipy.sparse.csr_matrix
        Surface point of every bundle: ``bary_matrix @ X`` (B,3).
    condition : float
        Condition number of ``bary_matrix @ weights``.

    Raises
    ------
    MeshError
        A vertex without natural-neighbour weight (a vertex no face uses).
    """

    def __init__(self, ds, threads: int = 2):
        F, bf, bb, B, nv = ds.faces, ds.bundle_faces, ds.bundle_bary, ds.B, ds.V
        W = ds.weights
        self.ds = ds
        self.threads = max(1, int(threads))
        if (np.diff(W.indptr) == 0).any():
            raise MeshError("Some vertices got no natural-neighbour weight; check that every vertex is used by a face.")
        Wa = W[ds.active].tocsr()
        na = len(ds.active)
        cuts = np.linspace(0, na, self.threads + 1).astype(np.int64)

        def part(a, b):
            return (int(a), Wa[a:b].tocsr())

        self._w_parts = [part(a, b) for a, b in zip(cuts[:-1], cuts[1:]) if b > a]
        self._w_full = part(0, na)
        self.weights = W
        # residual correction for exact interpolation: (Bary W) c = r
        Bary = sp.csr_matrix((bb.ravel(), (np.repeat(np.arange(B), 3), F[bf].ravel())), shape=(B, nv))
        self.bary_matrix = Bary
        G = (Bary @ W).toarray()
        self._lu = {"natural_neighbor": sla.lu_factor(G)}
        self.condition = float(np.linalg.cond(G))
        self._rbf = None
        self._voronoi = None
        self._pool = ThreadPoolExecutor(self.threads) if self.threads > 1 else None

    def _blend_part(self, part, Beta):
        """One row block of the blend: per-vertex shape weights ``C = W_rows @ Beta`` (sparse), then one
        sparse product with the shape-major float32 dataset."""
        off, Wp = part
        C = Wp @ Beta
        n = Wp.shape[0]
        rows = np.repeat(np.arange(off, off + n, dtype=np.int32), np.diff(C.indptr))
        idx = C.indices.astype(np.int32) * np.int32(len(self.ds.active)) + rows
        A = sp.csr_matrix((C.data.astype(np.float32), idx, C.indptr), shape=(n, self.ds.deltas.shape[0]))
        return A @ self.ds.deltas

    def blend_active(self, sid, coef, split: bool = True):
        """(n_active,3) float32 unskinned deltas of the moving vertices for per-bundle shape weights."""
        Beta = shape_weight_matrix(sid, coef, self.ds.S1)
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
        out = self.ds.neutral.copy()
        out[self.ds.active] += self.blend_active(sid, coef, split)
        return out

    def blend_dense(self, Wd, sid, coef):
        """Unskinned blend (V,3) with a dense (V,B) weight matrix ``Wd`` (RBF / Voronoi stitching), scene units."""
        ds = self.ds
        Beta = shape_weight_matrix(sid, coef, ds.S1)
        Wa = Wd[ds.active]
        C = np.asarray((Beta.T @ np.asarray(Wa.toarray() if sp.issparse(Wa) else Wa).T).T)
        out = ds.neutral.copy()
        out[ds.active] += np.einsum("as,sax->ax", C, ds.deltas.reshape(ds.S1, -1, 3).astype(np.float64))
        return out

    def finish(self, Xu, q, jaw, exact):
        """Skin an unskinned blend ``Xu`` (V,3) with the frame's ``jaw`` and, when ``exact``, add the
        natural-neighbour correction through the bundles ``q`` (B,3); scene units."""
        ds = self.ds
        X = ds.jaw.skin(Xu, jaw) if ds.jaw is not None else Xu
        if exact:
            r = q - self.bary_matrix @ X
            X = X + self.weights @ sla.lu_solve(self._lu["natural_neighbor"], r)
        return X

    def stitching_matrix(self, stitching):
        """(V,B) stitching weights: ``"natural_neighbor"`` (sparse, §5), ``"rbf"`` (dense Gaussian RBF,
        §7) or ``"voronoi"`` (sparse, one bundle per vertex, Fig. 1)."""
        ds = self.ds
        if stitching == "natural_neighbor":
            return self.weights
        if stitching == "rbf":
            if self._rbf is None:
                sites = surface_points(ds.neutral, ds.faces, ds.bundle_faces, ds.bundle_bary)
                self._rbf = gaussian_rbf_weights(ds.neutral, sites)
            return self._rbf
        if self._voronoi is None:
            self._voronoi = sp.csr_matrix((np.ones(ds.V), (np.arange(ds.V), ds.nn.cell)), shape=(ds.V, ds.B))
        return self._voronoi

    def factor(self, stitching):
        """LU factor (``scipy.linalg.lu_factor``) of ``bary_matrix @ stitching_matrix(stitching)`` (B,B)."""
        if stitching not in self._lu:
            G = self.bary_matrix @ self.stitching_matrix(stitching)
            G = G.toarray() if sp.issparse(G) else np.asarray(G)
            self._lu[stitching] = sla.lu_factor(G)
        return self._lu[stitching]

    def close(self):
        """Stop the blend threads."""
        if self._pool is not None:
            self._pool.shutdown(wait=False)
            self._pool = None
