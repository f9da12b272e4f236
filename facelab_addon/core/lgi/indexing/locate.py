"""Choosing a tetrahedron for every bundle (Cong, Lan and Fedkiw 2019, §4, §5.1, Eq. 1).

The per-frame step of
:class:`~facelab_addon.core.lgi.indexing.indexer.GeometricIndexer`:
:class:`Locator` queries the clouds and grid of
:mod:`facelab_addon.core.lgi.indexing.clouds` and the :class:`NeighborTables`
built once by :func:`build_neighbor_tables`:

* **Eq. 1**: the chosen tetrahedron's barycentric weights blend its four
  shapes. When no tetrahedron holds the bundle it is projected to the closest
  point of the tetrahedralized volume (§4): the closest facet of the cloud's
  convex hull (the union of the tetrahedra), or the closest tetrahedron where
  the hull does not apply.
* **Choosing tetrahedra** (§5.1): among the tetrahedra (and cloud points)
  that hold a bundle, the one whose geometry puts the neighbouring bundles'
  surface points closest to those bundles (root mean square over the natural
  neighbours). For animated bundles a candidate's cost is multiplied by
  ``1 + temporal_bias (4 - shared) / 4`` where ``shared`` counts the shapes it
  shares with the previous frame's choice. Where the neighbours cannot tell
  candidates apart (best cost below ``tie_tolerance``), the candidates are
  re-ranked by a vote of the moving bundles (a nonlocal criterion, §4).

Shapes: bundles ``q`` (B,3); the choice is shape ids (B,4) (0 = neutral,
``s + 1`` = ``shapes[s]``) and barycentric weights (B,4). Units: positions,
distances and costs in scene units; weights are unitless.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ..tets import closest_point_triangles, closest_point_tetrahedron

__all__ = ["Locator", "NeighborTables", "build_neighbor_tables"]


def _ragged_arange(starts, counts):
    """Concatenation of ``arange(s, s + c)`` for every pair, and the group of each entry.

    Parameters
    ----------
    starts, counts : (n,) int array_like

    Returns
    -------
    idx : (sum(counts),) int64 ndarray
    group : (sum(counts),) int64 ndarray
        The pair ``k`` every entry comes from.
    """
    counts = np.asarray(counts, dtype=np.int64)
    tot = int(counts.sum())
    grp = np.repeat(np.arange(len(counts)), counts)
    if tot == 0:
        return np.zeros(0, dtype=np.int64), grp
    off = np.cumsum(counts) - counts
    idx = np.arange(tot, dtype=np.int64) - np.repeat(off, counts) + np.repeat(np.asarray(starts, np.int64), counts)
    return idx, grp


@dataclass
class NeighborTables:
    """The bundles that judge every candidate (§5.1), and where they sit on every cloud point's shape.

    ``P`` is the number of cloud points (``BundleClouds.point_shape``).

    Attributes
    ----------
    neighbor_ptr : (B+1,) int64
        CSR: the neighbours of bundle ``i`` are
        ``neighbor_idx[neighbor_ptr[i]:neighbor_ptr[i+1]]`` (itself excluded).
    neighbor_idx : int64
    degree : (B,) int64
        Neighbours per bundle.
    pair_neighbor : int64
        For every (cloud point, neighbour of its bundle) pair: the neighbour.
    pair_pos : (n,3) float64
        Where that neighbour sits on the cloud point's shape, scene units.
    pair_offsets : (P+1,) int64
        Pairs of cloud point ``p``: ``pair_offsets[p]:pair_offsets[p+1]``.
    point_key : (P,) int64
        ``bundle * (S+1) + representative shape id`` of every cloud point.
    multi_points : int64
        Cloud points that belong to a merged point with several members.
    """

    neighbor_ptr: np.ndarray
    neighbor_idx: np.ndarray
    degree: np.ndarray
    pair_neighbor: np.ndarray
    pair_pos: np.ndarray
    pair_offsets: np.ndarray
    point_key: np.ndarray
    multi_points: np.ndarray


def build_neighbor_tables(neighbors, clouds, rings: int = 1):
    """Neighbouring bundles (§5.1), their positions on every cloud point's shape, and the merged-point keys.

    Parameters
    ----------
    neighbors : (B,B) scipy.sparse matrix
        Natural-neighbour adjacency of the bundles (``NaturalNeighbors.neighbors``).
    clouds : BundleClouds
    rings : int
        1: the natural neighbours; 2: also their neighbours; ...

    Returns
    -------
    NeighborTables
    """
    B, S1 = clouds.points.shape[1], clouds.points.shape[0]
    P = clouds.points
    Nb = neighbors.tocsr()
    R = Nb.copy()
    for _ in range(int(rings) - 1):
        R = ((R + R @ Nb) > 0).astype(np.float64)
    R = R.tolil()
    R.setdiag(0)
    Nb = sp.csr_matrix(R)
    Nb.eliminate_zeros()
    Nb.sort_indices()
    ptr, idx = Nb.indptr.astype(np.int64), Nb.indices.astype(np.int64)
    deg = np.diff(ptr)
    pb = clouds.point_bundle
    # every cloud point with every neighbour of its bundle: the neighbours' positions on that shape
    pos, g = _ragged_arange(ptr[pb], deg[pb])
    pair_nbr = idx[pos]
    # merged points: the representative key of every cloud point, and the points of multi-member keys
    rep_of = np.zeros(len(clouds.point_shape), dtype=np.int64)
    for i in range(B):
        lo_, hi_ = clouds.point_offsets[i], clouds.point_offsets[i + 1]
        rep_of[lo_:hi_] = i * S1 + clouds.shapes[i][clouds.rep_local[i]]
    multi = np.zeros(B * S1, dtype=bool)
    multi[clouds.multi_keys] = True
    return NeighborTables(neighbor_ptr=ptr, neighbor_idx=idx, degree=deg, pair_neighbor=pair_nbr,
                          pair_pos=P[clouds.point_shape[g], pair_nbr], pair_offsets=np.r_[0, np.cumsum(deg[pb])],
                          point_key=rep_of, multi_points=np.flatnonzero(multi[rep_of]))


class Locator:
    """Per-frame choice of a tetrahedron and barycentric weights for every bundle (§4, §5.1).

    Parameters
    ----------
    clouds : BundleClouds
    grid : TetGrid
    tables : NeighborTables
    temporal_bias : float
        Unitless weight of the previous frame's choice (``IndexerParams.temporal_bias``).
    tie_tolerance : float
        Scene units (resolved, ``IndexerParams.tie_tolerance_at``); 0 disables the re-ranking.
    face_size : float
        Scene units; scales the geometric tolerances.
    """

    def __init__(self, clouds, grid, tables, *, temporal_bias: float, tie_tolerance: float, face_size: float):
        self.clouds, self.grid, self.tables = clouds, grid, tables
        self.temporal_bias = float(temporal_bias)
        self.tie_tolerance = float(tie_tolerance)
        self.face_size = float(face_size)
        self.S1, self.B = clouds.points.shape[:2]

    def locate(self, q, prev=None):
        """Choose a tetrahedron and barycentric weights for every bundle (§4, §5.1).

        Parameters
        ----------
        q : (B,3) array_like
            Unskinned bundle positions, scene units.
        prev : (B,4) int array_like, optional
            The previous frame's shapes; candidates sharing more shapes with
            them are preferred (``temporal_bias``).

        Returns
        -------
        shape_ids : (B,4) int64 ndarray
            Shape index of each corner (0 = neutral, ``s + 1`` = ``shapes[s]``).
        bary : (B,4) float64 ndarray
            Barycentric weights (non-negative, sum 1).
        distance : (B,) float64 ndarray
            Distance from each bundle to its cloud's tetrahedralized volume
            (0 when a tetrahedron holds it), scene units.
        """
        cl, tb, gr = self.clouds, self.tables, self.grid
        q = np.asarray(q, dtype=np.float64)
        B, S1 = self.B, self.S1
        # --- candidates: tetrahedra holding the bundle (grid, float32 screen, exact float64 weights)
        rel = (q - gr.lo) / gr.h
        cidx = np.floor(rel).astype(np.int64)
        inbox = ((cidx >= 0) & (cidx < gr.n)).all(axis=1)
        cidx = np.clip(cidx, 0, gr.n - 1)
        cell = gr.base + (cidx[:, 2] * gr.n[:, 1] + cidx[:, 1]) * gr.n[:, 0] + cidx[:, 0]
        s0 = gr.cell_start[cell]
        cnt = np.where(inbox, gr.cell_start[cell + 1] - s0, 0)
        pos, bund = _ragged_arange(s0, cnt)
        cand = gr.cell_tets[pos]
        # box screen (float32 boxes rounded outwards), then the exact float64 affine maps of the survivors
        q32 = q.astype(np.float32)
        qb = q32[bund]
        ok = ((cl.tet_lo[cand] <= qb) & (qb <= cl.tet_hi[cand])).all(axis=1)
        cand, bund = cand[ok], bund[ok]
        tid = cl.tets[cand].astype(np.int64)
        w3 = np.einsum("nij,nj->ni", cl.tet_affine[cand], np.c_[q, np.ones(B)][bund])
        w = np.column_stack([1 - w3.sum(1), w3])
        inside = (w >= -1e-9).all(axis=1)
        bund, tid, w = bund[inside], tid[inside], np.clip(w[inside], 0.0, None)
        w /= np.maximum(w.sum(axis=1, keepdims=True), 1e-300)
        # a candidate at a single cloud point is that point's candidate below
        single = (w > 1 - 1e-9).any(axis=1)
        bund, tid, w = bund[~single], tid[~single], w[~single]
        dist = np.zeros(B)
        dp = np.linalg.norm(cl.point_pos - q[cl.point_bundle], axis=1)
        near = dp <= cl.merge_tolerance
        has = np.zeros(B, dtype=bool)
        has[bund] = True
        has[cl.point_bundle[near]] = True
        miss = np.flatnonzero(~has)
        if len(miss):
            pb, pt, pw, pd = self._project_hull(miss, q)
            dist[miss] = pd
            one = (pw > 1 - 1e-9).any(axis=1)
            # projections onto a cloud point become that point's candidate
            top = pt[np.arange(len(pt)), np.argmax(pw, axis=1)]
            key = pb[one] * S1 + top[one]
            near |= np.isin(tb.point_key, np.unique(key))
            bund, tid, w = np.r_[bund, pb[~one]], np.vstack([tid, pt[~one]]), np.vstack([w, pw[~one]])
        # --- cloud points that may be used alone or as members of merged points: their own cost (§5.1)
        need = np.zeros(B * S1, dtype=bool)
        need[(bund[:, None] * S1 + tid)[w > 0]] = True
        mp = tb.multi_points
        pts = np.union1d(mp[need[tb.point_key[mp]]], np.flatnonzero(near))
        pc = self._point_costs(q, prev, pts)
        ids, bary, cost = self._select(q, prev, None, bund, tid, w, pc, near)
        # Ties: where the neighbours cannot tell candidates apart (best cost below tie_tolerance), prefer
        # the shapes that the moving bundles chose (each bundle votes with its motion from the neutral).
        amb = cost <= self.tie_tolerance
        if amb.any() and self.tie_tolerance > 0:
            motion = np.linalg.norm(q - cl.points[0], axis=1)
            vote = np.bincount(ids.ravel(), weights=(bary * motion[:, None]).ravel(), minlength=S1)
            vote[0] = 0.0
            if vote.max() > 0:
                vote /= vote.max()
            vote[0] = 0.5  # the neutral beats shapes no moving bundle chose (the least assumption)
            pc2 = pc + self.tie_tolerance * (1.0 - vote[cl.point_shape])
            sel = amb[bund]
            ids2, bary2, _ = self._select(q, prev, vote, bund[sel], tid[sel], w[sel], pc2, near & amb[cl.point_bundle])
            ids[amb], bary[amb] = ids2[amb], bary2[amb]
        return ids, bary, dist

    def _point_costs(self, q, prev, pts):
        """(P,) cost of cloud points ``pts`` used alone: neighbour RMS distance (+ temporal term), scene
        units; ``inf`` for the other points."""
        cl, tb = self.clouds, self.tables
        c = np.full(len(cl.point_shape), np.inf)
        if len(pts) == 0:
            return c
        pos, g = _ragged_arange(tb.pair_offsets[pts], tb.pair_offsets[pts + 1] - tb.pair_offsets[pts])
        e = ((tb.pair_pos[pos] - q[tb.pair_neighbor[pos]]) ** 2).sum(axis=1)
        cp = np.sqrt(np.bincount(g, weights=e, minlength=len(pts)) / np.maximum(tb.degree[cl.point_bundle[pts]], 1))
        if prev is not None:
            pv = np.asarray(prev)[cl.point_bundle[pts]]
            cp = cp * (1.0 + self.temporal_bias * ~(pv == cl.point_shape[pts][:, None]).any(axis=1))
        c[pts] = cp
        return c

    def _select(self, q, prev, vote, bund, tid, w, pc, near):
        """Best candidate per bundle among tetrahedra (bund, tid, w) and the cloud points flagged ``near``.

        Merged points in tetrahedra are replaced by their best member (lowest
        point cost). Returns (B,4) shapes, (B,4) weights and (B,) costs.
        """
        cl, tb = self.clouds, self.tables
        B, S1 = self.B, self.S1
        sub = np.tile(np.arange(S1, dtype=np.int64), B)
        mp = tb.multi_points
        mp = mp[np.isfinite(pc[mp])]  # members without a cost keep their representative (the default)
        if len(mp):
            o = np.lexsort((pc[mp], tb.point_key[mp]))
            k = tb.point_key[mp][o]
            first = o[np.r_[True, k[1:] != k[:-1]]]
            sub[tb.point_key[mp][first]] = cl.point_shape[mp][first]
        tid = sub[bund[:, None] * S1 + tid]
        c_t = self._neighbor_cost(bund, tid, w, q, prev, vote) if len(bund) else np.zeros(0)
        npt = np.flatnonzero(near)
        ids = np.zeros((B, 4), dtype=np.int64)
        bary = np.zeros((B, 4))
        best = np.full(B, np.inf)
        # cloud points first (a tetrahedron must be strictly better to win)
        if len(npt):
            o = np.lexsort((pc[npt], cl.point_bundle[npt]))
            bb_ = cl.point_bundle[npt][o]
            first = o[np.r_[True, bb_[1:] != bb_[:-1]]]
            b_ = cl.point_bundle[npt][first]
            best[b_] = pc[npt][first]
            ids[b_] = cl.point_shape[npt][first][:, None]
            bary[b_, 0] = 1.0
        if len(bund):
            o = np.lexsort((c_t, bund))
            first = o[np.r_[True, bund[o][1:] != bund[o][:-1]]]
            b_, c_ = bund[first], c_t[first]
            better = c_ < best[b_] - 1e-15
            b_, f_ = b_[better], first[better]
            best[b_] = c_[better]
            ids[b_], bary[b_] = tid[f_], w[f_]
        return ids, bary, best

    def _neighbor_cost(self, bund, tet_ids, w, q, prev, vote=None):
        """Candidate cost, scene units: RMS distance of the neighbouring bundles to their surface points
        under the candidate's geometry (§5.1), plus the temporal and tie-break terms."""
        cl, tb = self.clouds, self.tables
        deg = tb.degree[bund]
        pos, c = _ragged_arange(tb.neighbor_ptr[bund], deg)
        j = tb.neighbor_idx[pos]
        s = np.einsum("nk,nkx->nx", w[c], cl.points[tet_ids[c], j[:, None]])
        e = ((s - q[j]) ** 2).sum(axis=1)
        cost = np.sqrt(np.bincount(c, weights=e, minlength=len(bund)) / np.maximum(deg, 1))
        if prev is not None:
            pv = np.asarray(prev)[bund]
            shared = (tet_ids[:, :, None] == pv[:, None, :]).any(axis=2).sum(axis=1)
            cost = cost * (1.0 + self.temporal_bias * (4 - shared) / 4.0)
        if vote is not None:
            cost = cost + self.tie_tolerance * (1.0 - (w * vote[tet_ids]).sum(axis=1))
        return cost

    def _project_hull(self, miss, q):
        """Closest points on the convex hulls of the missing bundles' clouds (§4).

        Bundles whose cloud is flat (no hull), or that lie inside their hull
        (in a gap left by a pruned sliver), use the tetrahedra directly
        (:meth:`_project_candidates`). Returns bundles (n,), representative
        shapes (n,4), weights (n,4) and the distances (len(miss),).
        """
        cl = self.clouds
        a, b = cl.hull_offsets[miss], cl.hull_offsets[miss + 1]
        pos, grp = _ragged_arange(a, b - a)
        bm = miss[grp]
        qq = q[bm]
        eq = cl.hull_planes[pos]
        out = np.full(len(miss), -np.inf)
        np.maximum.at(out, grp, (eq[:, :3] * qq).sum(1) + eq[:, 3])
        tri = cl.hull_tris[pos]
        X = cl.points[tri, bm[:, None]]
        d, w3 = closest_point_triangles(qq, X[:, 0], X[:, 1], X[:, 2])
        dmin = np.full(len(miss), np.inf)
        np.minimum.at(dmin, grp, d)
        use = (b > a) & (out > 1e-12 * self.face_size)
        tie = use[grp] & (d <= dmin[grp] * (1 + 1e-9) + 1e-12 * self.face_size)
        pb = bm[tie]
        pt = np.column_stack([tri[tie], tri[tie][:, 2]])
        pw = np.column_stack([w3[tie], np.zeros(int(tie.sum()))])
        dist = np.where(use, dmin, 0.0)
        rest = miss[~use]
        if len(rest):
            rb, rt, rw, rd = self._project_candidates(rest, q)
            pb, pt, pw = np.r_[pb, rb], np.vstack([pt, rt]), np.vstack([pw, rw])
            dist[~use] = rd
        return pb, pt, pw, dist

    def _project_candidates(self, miss, q):
        """Closest points of the missing bundles' tetrahedralized volumes (§4): the tied-closest candidates.

        Returns bundles (n,), representative shapes (n,4), weights (n,4) and
        the distance of every missing bundle (len(miss),), scene units.
        """
        cl = self.clouds
        a, b = cl.tet_offsets[miss], cl.tet_offsets[miss + 1]
        pos, grp = _ragged_arange(a, b - a)
        qq = q[miss][grp]
        # lower bound: distance to each tetrahedron's box; upper bound: distance to the nearest cloud point
        lb = np.linalg.norm(np.maximum(np.maximum(cl.tet_lo[pos] - qq, qq - cl.tet_hi[pos]), 0.0), axis=1)
        ub = np.full(len(miss), np.inf)
        for k, i in enumerate(miss):
            ub[k] = np.linalg.norm(cl.points[cl.reps[i], i] - q[i], axis=1).min()
        sel = lb <= ub[grp] * (1 + 1e-6) + 1e-9 * self.face_size
        pos, grp, qq, lb = pos[sel], grp[sel], qq[sel], lb[sel]
        # exact distances in rounds of increasing box distance, until no box is closer than the best
        o = np.lexsort((lb, grp))
        pos, grp, qq, lb = pos[o], grp[o], qq[o], lb[o]
        first = np.r_[0, np.flatnonzero(np.diff(grp)) + 1]
        rank = np.arange(len(grp)) - np.repeat(first, np.diff(np.r_[first, len(grp)]))
        done = np.zeros(len(grp), dtype=bool)
        dmin = np.full(len(miss), np.inf)
        d_all = np.full(len(grp), np.inf)
        w_all = np.zeros((len(grp), 4))
        tid_all = cl.tets[pos].astype(np.int64)
        lim = 16
        while True:
            todo = ~done & (rank < lim) & (lb <= dmin[grp] * (1 + 1e-9) + 1e-12 * self.face_size)
            if not todo.any():
                if not (~done & (lb <= dmin[grp] * (1 + 1e-9) + 1e-12 * self.face_size)).any():
                    break
                lim *= 4
                continue
            t = np.flatnonzero(todo)
            Xt = cl.points[tid_all[t], miss[grp[t]][:, None]]
            d_all[t], w_all[t] = closest_point_tetrahedron(qq[t], Xt)
            done[t] = True
            np.minimum.at(dmin, grp[t], d_all[t])
            lim *= 2
        tie = done & (d_all <= dmin[grp] * (1 + 1e-9) + 1e-12 * self.face_size)
        tid, w = tid_all, w_all
        return miss[grp[tie]], tid[tie], w[tie], dmin
