"""Point clouds, tetrahedra and search grids of a geometric indexer (Cong, Lan and Fedkiw 2019, §4, §4.1).

Build steps of :class:`~facelab_addon.core.lgi.indexer.GeometricIndexer`
(the mixin :class:`IndexerClouds`), in the order the indexer runs them:

* **Point clouds** (§4): the position of every bundle on every dataset shape
  (plus the neutral, shape 0), in unskinned space when there is a jaw rig.
* **Pruning** (§4.1, "removing points corresponding to expressions that do
  not involve them"): a shape is dropped from a bundle's cloud when it leaves
  the bundle's natural-neighbour region still; shapes that put the bundle at
  the same place (within ``merge_tolerance``, e.g. every mouth shape for a
  forehead bundle) are merged into one cloud point and create no extra
  tetrahedra. Which member of a merged point is used is decided per frame by
  the neighbouring bundles, so a dataset shape that moves the skin between
  bundles but not the bundle itself is still reproduced.
* **Tetrahedra** (§4, §4.1): overlapping, non-manifold tetrahedra from
  combinations of 4 points: each point with 3 of its ``neighbors`` nearest
  cloud points (all combinations for small clouds; a "too much spatial
  extent" pruning adaptive to the local density), plus the cloud's Delaunay
  tetrahedra so that their union covers the convex hull. Tetrahedra that are
  too thin (mean-ratio quality below ``min_quality``; Delaunay ones only when
  flat), too large (an edge longer than ``max_edge``) or flagged bad
  (``forbidden`` shape sets) are deleted; every point keeps at least
  ``min_tets_per_point`` tetrahedra. Flat clouds use triangles, two-point
  clouds a segment.
* **Convex hulls** of the clouds, for bundles outside every tetrahedron (§4).
* **Uniform grid** per bundle ([18, 32]) for point-in-tetrahedron queries
  (float32 bounding boxes screen the candidates, precomputed float64 affine
  maps give the barycentric weights).

Array conventions: shape id 0 is the neutral, ``s + 1`` is ``shapes[s]``;
``points_all`` (S+1,B,3) holds the clouds, scene units; ``tets`` (N,4) int32
holds shape ids, grouped per bundle by ``tet_offsets`` (B+1,).
"""

from __future__ import annotations

import itertools

import numpy as np
from scipy.spatial import cKDTree

from ..errors import BundleError, DatasetError
from .binding import bundle_labels
from .inputs import check_bundles_move
from .natural_neighbor import surface_points
from .tets import TET_EDGES, tet_inverse, tetrahedron_quality

__all__ = ["IndexerClouds"]


class IndexerClouds:
    """Build steps of :class:`~facelab_addon.core.lgi.indexer.GeometricIndexer`: point clouds, tetrahedra, grid.

    A mixin: the steps read the inputs the indexer stored (``neutral``,
    ``faces``, ``bundle_faces``, ``bundle_bary``, ``jaw``, ``B``, ``S``,
    ``S1``, ``names``, ``bundle_names``, ``face_size``, ``prune_tolerance``)
    and set the cloud, tetrahedron, hull and grid attributes that
    :class:`~facelab_addon.core.lgi.locate.IndexerLocate` queries per frame.
    """

    def _point_clouds(self, X, dup_tol):
        """Bundle positions (S1,B,3) on the neutral and every shape, unskinned (§4), and their motions (S,B)."""
        x0, F, bf, bb = self.neutral, self.faces, self.bundle_faces, self.bundle_bary
        jaw, S, S1, B = self.jaw, self.S, self.S1, self.B
        P = np.zeros((S1, B, 3))
        P[0] = surface_points(x0, F, bf, bb)
        if jaw is not None:
            # the bundle on shape n, unskinned the way frames are (Eq. 2 at the bundle's skinning weight)
            Ps = surface_points(X, F, bf, bb)
            for s in range(S):
                P[s + 1] = jaw.unskin(Ps[s], self.shape_jaw[s], self.bundle_jaw_weights)
        else:
            P[1:] = surface_points(X, F, bf, bb)
        self.points_all = P
        move = np.linalg.norm(P[1:] - P[0], axis=2)  # (S,B)
        check_bundles_move(move.max(axis=0), dup_tol, self.bundle_names)
        return P, move

    def _prune(self, W, mags, move, forbidden):
        """(S,B) bool, the shapes kept in each bundle's cloud: those that move its natural-neighbour region (§4.1)."""
        S, B = self.S, self.B
        Wc = W.tocsc()
        region = np.zeros((S, B))
        for i in range(B):
            rows = Wc.indices[Wc.indptr[i] : Wc.indptr[i + 1]]
            ww = Wc.data[Wc.indptr[i] : Wc.indptr[i + 1]]
            if len(rows):
                region[:, i] = (mags[:, rows] * ww).max(axis=1)
        keep = (region > self.prune_tolerance) | (move > self.prune_tolerance)
        self._forbidden = self._parse_forbidden(forbidden)
        return keep

    def _tetrahedra(self, P, keep, merge_tolerance, neighbors, min_quality, max_edge, min_tets_per_point):
        """Merge close cloud points and tetrahedralize every bundle's cloud (§4, §4.1); returns the pruning counts."""
        B, S1 = self.B, self.S1
        # Shapes that put the bundle at the same place (within merge_tolerance) share one cloud point;
        # which of them is used is decided per frame by the neighbouring bundles (§5.1).
        self.merge_tolerance = (2e-4 * self.face_size if merge_tolerance is None else float(merge_tolerance))
        tets, counts = [], []
        st = dict(candidates=0, thin=0, large=0, flagged=0, restored=0, flat_clouds=0, segment_clouds=0)
        n_points = np.zeros(B, dtype=np.int64)
        n_distinct = np.zeros(B, dtype=np.int64)
        mem_key, mem_list = [], []
        self.cloud_shapes, self.cloud_reps, self._cloud_rep_local = [], [], []
        for i in range(B):
            ids = np.r_[0, 1 + np.flatnonzero(keep[:, i])]
            self.cloud_shapes.append(ids)
            n_points[i] = len(ids)
            rep = self._cluster(P[ids, i], self.merge_tolerance)
            self._cloud_rep_local.append(rep)
            reps = np.flatnonzero(rep == np.arange(len(ids)))
            self.cloud_reps.append(ids[reps])
            n_distinct[i] = len(reps)
            for r in reps:
                mem = ids[rep == r]
                if len(mem) > 1:
                    mem_key.append(i * S1 + ids[r])
                    mem_list.append(mem)
            if len(reps) < 2:
                raise BundleError(
                    f"{bundle_labels(self.bundle_names, [i])} is not moved by any dataset shape by more than "
                    f"{self.merge_tolerance:.3g} scene "
                    "units; remove it, bind it on the moving face, or add shapes that move it."
                )
            T = self._tetrahedralize(P[ids[reps], i], ids[reps], int(neighbors), float(min_quality), max_edge,
                                     int(min_tets_per_point), st)
            tets.append(T)
            counts.append(len(T))
        self.n_points = n_points
        self.n_distinct_points = n_distinct
        self._cloud_shape = np.concatenate(self.cloud_shapes)
        self._cloud_bundle = np.repeat(np.arange(B), n_points)
        self._cloud_off = np.r_[0, np.cumsum(n_points)]
        self._cloud_pos = P[self._cloud_shape, self._cloud_bundle]
        # members of merged points: CSR over key = bundle * S1 + representative shape
        ptr = np.zeros(B * S1 + 1, dtype=np.int64)
        cnt = np.ones(B * S1, dtype=np.int64)
        for k, m in zip(mem_key, mem_list):
            cnt[k] = len(m)
        ptr[1:] = np.cumsum(cnt)
        members = np.repeat(np.arange(B * S1) % S1, cnt)
        for k, m in zip(mem_key, mem_list):
            members[ptr[k] : ptr[k + 1]] = m
        self._mem_ptr, self._mem = ptr, members
        self._multi_keys = np.flatnonzero(cnt > 1).astype(np.int64)
        self.tets = np.vstack(tets).astype(np.int32)  # representative shape ids (0 = neutral)
        return st, counts, n_points, n_distinct

    def _convex_hulls(self, P):
        """Convex hull facets and plane equations of every bundle's cloud, for projecting bundles outside it (§4)."""
        B = self.B
        # convex hull of every cloud: the union of the tetrahedra (the Delaunay ones cover it), so a
        # bundle outside every tetrahedron projects to the closest hull facet (§4)
        from scipy.spatial import ConvexHull

        hf, hc, heq = [], [], []
        for i in range(B):
            r = self.cloud_reps[i]
            try:
                h = ConvexHull(P[r, i])
                hf.append(r[h.simplices])
                heq.append(h.equations)
                hc.append(len(h.simplices))
            except Exception:  # flat cloud: no hull, the tetrahedra are used directly
                hc.append(0)
        self._hull_off = np.r_[0, np.cumsum(hc)].astype(np.int64)
        self._hull_tri = np.vstack(hf).astype(np.int64) if hf else np.zeros((0, 3), np.int64)
        self._hull_eq = np.vstack(heq) if heq else np.zeros((0, 4))

    def _tetrahedron_maps(self, P, counts):
        """Per-tetrahedron bundle, float64 barycentric affine maps and float32 bounding boxes."""
        B = self.B
        self.tet_offsets = np.r_[0, np.cumsum(counts)].astype(np.int64)
        self.tet_bundle = np.repeat(np.arange(B), counts).astype(np.int32)
        Xt = P[self.tets, self.tet_bundle[:, None]]  # (N,4,3)
        inv = tet_inverse(Xt)
        # float64 affine maps q -> (w1, w2, w3) (w0 = 1 - sum); NaN rows for flat tetrahedra
        self._tet_aff = np.concatenate([inv, -np.einsum("nij,nj->ni", inv, Xt[:, 0])[:, :, None]], axis=2)
        self._tet_flat = ~np.isfinite(inv).all(axis=(1, 2))
        del inv
        # float32 boxes rounded outwards, so a box always holds its tetrahedron
        self._tet_lo = np.nextafter(Xt.min(axis=1).astype(np.float32), np.float32(-np.inf))
        self._tet_hi = np.nextafter(Xt.max(axis=1).astype(np.float32), np.float32(np.inf))
        del Xt

    @staticmethod
    def _cluster(pts, tol):
        """(m,) representative of every point: greedy merge within ``tol`` (earlier points represent)."""
        m = len(pts)
        rep = -np.ones(m, dtype=np.int64)
        balls = cKDTree(pts).query_ball_point(pts, r=tol)
        for p in range(m):
            if rep[p] < 0:
                rep[p] = p
                for nb in balls[p]:
                    if rep[nb] < 0:
                        rep[nb] = p
        return rep

    def _parse_forbidden(self, forbidden):
        """Forbidden shape sets (names or indices into the shapes) as sorted arrays of shape ids (0 = neutral)."""
        sets = []
        for f in forbidden or ():
            ids = []
            for s in f:
                if isinstance(s, str):
                    if s not in self.names:
                        raise DatasetError(f"Forbidden combination names unknown shape {s!r}; use a dataset shape name.")
                    ids.append(self.names.index(s) + 1)
                else:
                    ids.append(int(s) + 1)
            sets.append(np.array(sorted(set(ids)), dtype=np.int64))
        return sets

    def _tetrahedralize(self, pts, ids, K, qmin, max_edge, min_per_point, st, delaunay=True):
        """Tetrahedra (as global shape ids) of one point cloud ``pts`` (m,3) with shape ids ``ids``."""
        m = len(pts)
        if m < 2:
            raise BundleError("A bundle's point cloud has a single point; no dataset shape moves it.")
        if m == 2:
            st["segment_clouds"] += 1
            return ids[[[0, 1, 1, 1]]]
        if m <= 4 or m - 1 <= K:
            cand = np.array(list(itertools.combinations(range(m), 4)), dtype=np.int64).reshape(-1, 4)
        else:
            _, nn = cKDTree(pts).query(pts, k=K + 1)
            nn = nn[:, 1:]
            c3 = np.array(list(itertools.combinations(range(K), 3)), dtype=np.int64)
            cand = np.concatenate([np.repeat(np.arange(m), len(c3))[:, None],
                                   nn[:, c3].reshape(-1, 3)], axis=1)
            cand.sort(axis=1)
            cand = np.unique(cand, axis=0)
            cand = cand[(np.diff(cand, axis=1) > 0).all(axis=1)]
        q = tetrahedron_quality(pts[cand]) if len(cand) else np.zeros(0)
        if len(cand) == 0 or q.max() <= 1e-6:
            # flat cloud: triangles stored as (a, b, c, c)
            st["flat_clouds"] += 1
            tri = np.array(list(itertools.combinations(range(m), 3)), dtype=np.int64)
            if len(tri) > 20000:
                _, nn = cKDTree(pts).query(pts, k=min(K, m - 1) + 1)
                c2 = np.array(list(itertools.combinations(range(nn.shape[1] - 1), 2)), dtype=np.int64)
                tri = np.concatenate([np.repeat(np.arange(m), len(c2))[:, None], nn[:, 1:][:, c2].reshape(-1, 2)], 1)
                tri.sort(axis=1)
                tri = np.unique(tri, axis=0)
            Tp = pts[tri]
            area = 0.5 * np.linalg.norm(np.cross(Tp[:, 1] - Tp[:, 0], Tp[:, 2] - Tp[:, 0]), axis=1)
            l2 = ((Tp[:, [1, 2, 0]] - Tp) ** 2).sum(axis=(1, 2))
            tq = 4 * np.sqrt(3) * area / np.maximum(l2, 1e-300)
            keep = tq >= qmin
            if not keep.any():
                # collinear: segments from the neutral
                st["segment_clouds"] += 1
                seg = np.column_stack([np.zeros(m - 1, np.int64), np.arange(1, m)])
                return ids[np.column_stack([seg, seg[:, 1], seg[:, 1]])]
            tri = tri[keep]
            return ids[np.column_stack([tri, tri[:, 2]])]
        # the Delaunay tetrahedralization of the cloud covers its convex hull; its tetrahedra join the
        # overlapping set (they are exempt from the thinness test, only flat ones are dropped)
        deln = np.zeros(len(cand), dtype=bool)
        if delaunay and m >= 5:
            try:
                from scipy.spatial import Delaunay

                dt = np.sort(Delaunay(pts).simplices.astype(np.int64), axis=1)
                allc = np.vstack([cand, dt])
                allc, inv = np.unique(allc, axis=0, return_inverse=True)
                inv = inv.ravel()
                deln = np.zeros(len(allc), dtype=bool)
                deln[inv[len(cand):]] = True
                cand = allc
                q = tetrahedron_quality(pts[cand])
            except Exception:  # flat or degenerate cloud: no Delaunay
                pass
        st["candidates"] += len(cand)
        keep = (q >= qmin) | (deln & (q > 1e-4))
        st["thin"] += int((~keep).sum())
        if max_edge is not None:
            Xc = pts[cand]
            L = np.max([np.linalg.norm(Xc[:, a] - Xc[:, b], axis=1) for a, b in TET_EDGES], axis=0)
            large = keep & (L > float(max_edge))
            st["large"] += int(large.sum())
            keep &= ~large
        if self._forbidden:
            g = ids[cand]
            flag = np.zeros(len(cand), dtype=bool)
            for fs in self._forbidden:
                flag |= np.isin(g, fs).sum(axis=1) >= len(fs)
            flagged = keep & flag
            st["flagged"] += int(flagged.sum())
            keep &= ~flag
        else:
            flag = np.zeros(len(cand), dtype=bool)
        # coverage: every point keeps at least `min_per_point` of its best tetrahedra
        covered = np.bincount(cand[keep].ravel(), minlength=m)
        need = np.maximum(0, min_per_point - covered)
        if need.any():
            inc_t = np.repeat(np.arange(len(cand)), 4)
            inc_p = cand.ravel()
            el = ~keep[inc_t] & ~flag[inc_t] & (need[inc_p] > 0)
            inc_t, inc_p = inc_t[el], inc_p[el]
            order = np.lexsort((-q[inc_t], inc_p))
            inc_t, inc_p = inc_t[order], inc_p[order]
            first = np.r_[0, np.flatnonzero(np.diff(inc_p)) + 1]
            rank = np.arange(len(inc_p)) - np.repeat(first, np.diff(np.r_[first, len(inc_p)]))
            restore = np.unique(inc_t[rank < need[inc_p]])
            keep[restore] = True
            st["restored"] += len(restore)
        return ids[cand[keep]]

    def _build_grid(self, grid_density):
        """Uniform grid per bundle over its tetrahedra' boxes ([18, 32]), as CSR cell -> tetrahedra."""
        self.grid_density = float(grid_density)
        B = self.B
        starts, entries, lo_all, h_all, n_all, base = [], [], [], [], [], []
        total = 0
        n_entries = 0
        for i in range(B):
            a, b = self.tet_offsets[i], self.tet_offsets[i + 1]
            lo_t, hi_t = self._tet_lo[a:b].astype(np.float64), self._tet_hi[a:b].astype(np.float64)
            lo, hi = lo_t.min(axis=0), hi_t.max(axis=0)
            ext = np.maximum(hi - lo, 1e-12 * max(self.face_size, 1e-12))
            nt = b - a
            nc = int(np.clip(np.round(np.cbrt(nt * self.grid_density)), 1, 48))
            n = np.maximum(1, np.round(nc * ext / ext.max())).astype(np.int64)
            h = ext / n
            i0 = np.clip(np.floor((lo_t - lo) / h).astype(np.int64), 0, n - 1)
            i1 = np.clip(np.floor((hi_t - lo) / h).astype(np.int64), 0, n - 1)
            span = i1 - i0 + 1
            cnt = span.prod(axis=1)
            tet_rep = np.repeat(np.arange(nt), cnt)
            k = np.arange(int(cnt.sum())) - np.repeat(np.cumsum(cnt) - cnt, cnt)
            sx, sy = span[tet_rep, 0], span[tet_rep, 1]
            cx = i0[tet_rep, 0] + k % sx
            cy = i0[tet_rep, 1] + (k // sx) % sy
            cz = i0[tet_rep, 2] + k // (sx * sy)
            cell = (cz * n[1] + cy) * n[0] + cx
            ncell = int(n.prod())
            order = np.argsort(cell, kind="stable")
            cs = np.searchsorted(cell[order], np.arange(ncell + 1))
            starts.append(cs[:-1] + n_entries)
            entries.append((tet_rep[order] + a).astype(np.int32))
            n_entries += len(order)
            lo_all.append(lo)
            h_all.append(h)
            n_all.append(n)
            base.append(total)
            total += ncell
        cell_tets = np.concatenate(entries)
        self._cell_start = np.r_[np.concatenate(starts), len(cell_tets)].astype(np.int64)
        self._cell_tets = cell_tets
        self._grid_lo = np.array(lo_all)
        self._grid_h = np.array(h_all)
        self._grid_n = np.array(n_all)
        self._grid_base = np.array(base, dtype=np.int64)
