"""Point clouds, tetrahedra and search grids of a geometric indexer (Cong, Lan and Fedkiw 2019, §4, §4.1).

:func:`build_clouds` runs these build steps of
:class:`~facelab_addon.core.lgi.indexing.indexer.GeometricIndexer` in order and
returns them as one :class:`BundleClouds`; :func:`build_grid` adds the search
grid (:class:`TetGrid`):

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
``points`` (S+1,B,3) holds the clouds, scene units; ``tets`` (N,4) int32
holds shape ids, grouped per bundle by ``tet_offsets`` (B+1,).
"""


from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..binding import bundle_labels
from ...errors import BundleError, DatasetError
from ..inputs import check_bundles_move
from ..natural_neighbor import surface_points
from ..tets import TET_EDGES, tet_inverse, tetrahedron_quality
from .dataset import STILL_TOLERANCE

__all__ = ["BundleClouds", "TetGrid", "build_clouds", "build_grid", "cluster_points", "forbidden_shape_ids",
           "tetrahedralize"]


@dataclass
class BundleClouds:
    """Every bundle's point cloud, merged points, tetrahedra and convex hull (§4, §4.1).

    ``P`` below is the number of cloud points of all bundles, ``N`` the
    number of tetrahedra, ``H`` the number of hull facets.

    Attributes
    ----------
    points : (S+1,B,3) float64
        Position of every bundle on the neutral (shape id 0) and on every
        dataset shape, unskinned, scene units.
    motion : (S,B) float64
        Distance every shape moves every bundle, scene units.
    merge_tolerance : float
        Scene units; shapes closer than this at a bundle share one point.
    shapes : list of (n_i,) int64
        Shape ids in each bundle's cloud (pruned, §4.1), the neutral first.
    reps : list of (d_i,) int64
        Representative shape ids of each bundle's distinct (merged) points.
    rep_local : list of (n_i,) int64
        For each shape of ``shapes[i]``, the index in ``shapes[i]`` of its
        representative.
    n_points, n_distinct : (B,) int64
        Cloud points and distinct (merged) points per bundle.
    point_shape, point_bundle : (P,) int64
        Shape id and bundle of every cloud point, grouped per bundle.
    point_offsets : (B+1,) int64
        Cloud points of bundle ``i``: ``point_offsets[i]:point_offsets[i+1]``.
    point_pos : (P,3) float64
        Position of every cloud point, scene units.
    member_ptr : (B*(S+1)+1,) int64
        CSR over ``key = bundle * (S+1) + representative shape id``.
    members : int64
        Member shape ids of every key's merged point (itself when unmerged).
    multi_keys : int64
        Keys whose merged point has more than one member.
    tets : (N,4) int32
        Representative shape ids of every tetrahedron; flat clouds store
        triangles ``(a, b, c, c)`` and two-point clouds a segment ``(a, b, b, b)``.
    tet_offsets : (B+1,) int64
        Tetrahedra of bundle ``i``: ``tet_offsets[i]:tet_offsets[i+1]``.
    tet_bundle : (N,) int32
    tet_affine : (N,3,4) float64
        Affine maps ``q -> (w1, w2, w3)`` (``w0 = 1 - sum``), 1/scene units;
        NaN rows for flat tetrahedra.
    tet_flat : (N,) bool
    tet_lo, tet_hi : (N,3) float32
        Bounding boxes rounded outwards, scene units.
    hull_offsets : (B+1,) int64
        Hull facets of bundle ``i`` (none for flat clouds).
    hull_tris : (H,3) int64
        Shape ids of every hull facet.
    hull_planes : (H,4) float64
        Outward plane equations ``n . x + d`` (unit ``n``), scene units.
    counts : dict
        Tetrahedra ``candidates`` and those pruned ``thin``, ``large``,
        ``flagged``, ``restored`` for coverage; ``flat_clouds`` and
        ``segment_clouds``.
    """

    points: np.ndarray
    motion: np.ndarray
    merge_tolerance: float
    shapes: list
    reps: list
    rep_local: list
    n_points: np.ndarray
    n_distinct: np.ndarray
    point_shape: np.ndarray
    point_bundle: np.ndarray
    point_offsets: np.ndarray
    point_pos: np.ndarray
    member_ptr: np.ndarray
    members: np.ndarray
    multi_keys: np.ndarray
    tets: np.ndarray
    tet_offsets: np.ndarray
    tet_bundle: np.ndarray
    tet_affine: np.ndarray
    tet_flat: np.ndarray
    tet_lo: np.ndarray
    tet_hi: np.ndarray
    hull_offsets: np.ndarray
    hull_tris: np.ndarray
    hull_planes: np.ndarray
    counts: dict

    @property
    def tets_per_bundle(self):
        """(B,) int64 number of tetrahedra of every bundle."""
        return np.diff(self.tet_offsets)


@dataclass
class TetGrid:
    """A uniform grid per bundle over its tetrahedra's boxes ([18, 32]), as CSR cell -> tetrahedra.

    Attributes
    ----------
    density : float
        Grid cells per tetrahedron (see ``IndexerParams.grid_density``).
    cell_start : (C+1,) int64
        Entries of global cell ``c``: ``cell_tets[cell_start[c]:cell_start[c+1]]``.
    cell_tets : int32
        Tetrahedron indices (rows of ``BundleClouds.tets``).
    lo : (B,3) float64
        Grid origin of every bundle, scene units.
    h : (B,3) float64
        Cell size of every bundle, scene units.
    n : (B,3) int64
        Cells along x, y, z of every bundle.
    base : (B,) int64
        Global index of every bundle's first cell; cell ``(x, y, z)`` of
        bundle ``i`` is ``base[i] + (z * n[i,1] + y) * n[i,0] + x``.
    """

    density: float
    cell_start: np.ndarray
    cell_tets: np.ndarray
    lo: np.ndarray
    h: np.ndarray
    n: np.ndarray
    base: np.ndarray


def _point_clouds(ds, X):
    """Bundle positions (S+1,B,3) on the neutral and every shape, unskinned (§4), and their motions (S,B)."""
    x0, F, bf, bb, jaw = ds.neutral, ds.faces, ds.bundle_faces, ds.bundle_bary, ds.jaw
    P = np.zeros((ds.S1, ds.B, 3))
    P[0] = surface_points(x0, F, bf, bb)
    if jaw is not None:
        # the bundle on shape n, unskinned the way frames are (Eq. 2 at the bundle's skinning weight)
        Ps = surface_points(X, F, bf, bb)
        for s in range(ds.S):
            P[s + 1] = jaw.unskin(Ps[s], ds.shape_jaw[s], ds.bundle_jaw_weights)
    else:
        P[1:] = surface_points(X, F, bf, bb)
    move = np.linalg.norm(P[1:] - P[0], axis=2)  # (S,B)
    check_bundles_move(move.max(axis=0), STILL_TOLERANCE * ds.face_size, ds.bundle_names)
    return P, move


def _prune(ds, mags, move, tol):
    """(S,B) bool, the shapes kept in each bundle's cloud: those that move its natural-neighbour region (§4.1)."""
    Wc = ds.weights.tocsc()
    region = np.zeros((ds.S, ds.B))
    for i in range(ds.B):
        rows = Wc.indices[Wc.indptr[i] : Wc.indptr[i + 1]]
        ww = Wc.data[Wc.indptr[i] : Wc.indptr[i + 1]]
        if len(rows):
            region[:, i] = (mags[:, rows] * ww).max(axis=1)
    return (region > tol) | (move > tol)


def cluster_points(pts, tol):
    """Greedy merge of points within ``tol``: earlier points represent later ones.

    Parameters
    ----------
    pts : (m,3) array_like
        Points, scene units.
    tol : float
        Merge distance, scene units.

    Returns
    -------
    (m,) int64 ndarray
        Index of every point's representative (``rep[p] == p`` for representatives).
    """
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


def forbidden_shape_ids(forbidden, names):
    """Forbidden shape sets as sorted arrays of shape ids (0 = neutral, ``s + 1`` = ``shapes[s]``).

    Parameters
    ----------
    forbidden : iterable of iterables of int or str
        Sets of shape indices (into the dataset shapes) or names.
    names : list of str
        Dataset shape names.

    Returns
    -------
    list of int64 ndarray

    Raises
    ------
    DatasetError
        For an unknown shape name.
    """
    sets = []
    for f in forbidden or ():
        ids = []
        for s in f:
            if isinstance(s, str):
                if s not in names:
                    raise DatasetError(f"Forbidden combination names unknown shape {s!r}; use a dataset shape name.")
                ids.append(names.index(s) + 1)
            else:
                ids.append(int(s) + 1)
        sets.append(np.array(sorted(set(ids)), dtype=np.int64))
    return sets


def _merged_tetrahedra(ds, P, keep, merge_tol, params, forbidden):
    """Merge close cloud points and tetrahedralize every bundle's cloud (§4, §4.1): a dict of the fields."""
    B, S1 = ds.B, ds.S1
    tets, counts = [], []
    st = dict(candidates=0, thin=0, large=0, flagged=0, restored=0, flat_clouds=0, segment_clouds=0)
    n_points = np.zeros(B, dtype=np.int64)
    n_distinct = np.zeros(B, dtype=np.int64)
    mem_key, mem_list = [], []
    cloud_shapes, cloud_reps, rep_local = [], [], []
    for i in range(B):
        ids = np.r_[0, 1 + np.flatnonzero(keep[:, i])]
        cloud_shapes.append(ids)
        n_points[i] = len(ids)
        rep = cluster_points(P[ids, i], merge_tol)
        rep_local.append(rep)
        reps = np.flatnonzero(rep == np.arange(len(ids)))
        cloud_reps.append(ids[reps])
        n_distinct[i] = len(reps)
        for r in reps:
            mem = ids[rep == r]
            if len(mem) > 1:
                mem_key.append(i * S1 + ids[r])
                mem_list.append(mem)
        if len(reps) < 2:
            raise BundleError(
                f"{bundle_labels(ds.bundle_names, [i])} is not moved by any dataset shape by more than "
                f"{merge_tol:.3g} scene "
                "units; remove it, bind it on the moving face, or add shapes that move it."
            )
        T = tetrahedralize(P[ids[reps], i], ids[reps], int(params.neighbors), float(params.min_quality),
                           params.max_edge, int(params.min_tets_per_point), st, forbidden)
        tets.append(T)
        counts.append(len(T))
    point_shape = np.concatenate(cloud_shapes)
    point_bundle = np.repeat(np.arange(B), n_points)
    # members of merged points: CSR over key = bundle * S1 + representative shape
    ptr = np.zeros(B * S1 + 1, dtype=np.int64)
    cnt = np.ones(B * S1, dtype=np.int64)
    for k, m in zip(mem_key, mem_list):
        cnt[k] = len(m)
    ptr[1:] = np.cumsum(cnt)
    members = np.repeat(np.arange(B * S1) % S1, cnt)
    for k, m in zip(mem_key, mem_list):
        members[ptr[k] : ptr[k + 1]] = m
    return dict(shapes=cloud_shapes, reps=cloud_reps, rep_local=rep_local, n_points=n_points, n_distinct=n_distinct,
                point_shape=point_shape, point_bundle=point_bundle, point_offsets=np.r_[0, np.cumsum(n_points)],
                point_pos=P[point_shape, point_bundle], member_ptr=ptr, members=members,
                multi_keys=np.flatnonzero(cnt > 1).astype(np.int64),
                tets=np.vstack(tets).astype(np.int32),  # representative shape ids (0 = neutral)
                counts=st, tet_counts=counts)


def _convex_hulls(P, cloud_reps):
    """Convex hull facets and plane equations of every bundle's cloud, for projecting bundles outside it (§4)."""
    # convex hull of every cloud: the union of the tetrahedra (the Delaunay ones cover it), so a
    # bundle outside every tetrahedron projects to the closest hull facet (§4)
    from scipy.spatial import ConvexHull

    hf, hc, heq = [], [], []
    for i, r in enumerate(cloud_reps):
        try:
            h = ConvexHull(P[r, i])
            hf.append(r[h.simplices])
            heq.append(h.equations)
            hc.append(len(h.simplices))
        except Exception:  # flat cloud: no hull, the tetrahedra are used directly
            hc.append(0)
    return dict(hull_offsets=np.r_[0, np.cumsum(hc)].astype(np.int64),
                hull_tris=np.vstack(hf).astype(np.int64) if hf else np.zeros((0, 3), np.int64),
                hull_planes=np.vstack(heq) if heq else np.zeros((0, 4)))


def _tetrahedron_maps(P, tets, counts):
    """Per-tetrahedron bundle, float64 barycentric affine maps and float32 bounding boxes."""
    B = len(counts)
    tet_offsets = np.r_[0, np.cumsum(counts)].astype(np.int64)
    tet_bundle = np.repeat(np.arange(B), counts).astype(np.int32)
    Xt = P[tets, tet_bundle[:, None]]  # (N,4,3)
    inv = tet_inverse(Xt)
    # float64 affine maps q -> (w1, w2, w3) (w0 = 1 - sum); NaN rows for flat tetrahedra
    aff = np.concatenate([inv, -np.einsum("nij,nj->ni", inv, Xt[:, 0])[:, :, None]], axis=2)
    flat = ~np.isfinite(inv).all(axis=(1, 2))
    del inv
    # float32 boxes rounded outwards, so a box always holds its tetrahedron
    lo = np.nextafter(Xt.min(axis=1).astype(np.float32), np.float32(-np.inf))
    hi = np.nextafter(Xt.max(axis=1).astype(np.float32), np.float32(np.inf))
    return dict(tet_offsets=tet_offsets, tet_bundle=tet_bundle, tet_affine=aff, tet_flat=flat, tet_lo=lo, tet_hi=hi)


def build_clouds(ds, shapes, motion, params):
    """Point clouds, merged points, tetrahedra, hulls and barycentric maps of every bundle (§4, §4.1).

    Parameters
    ----------
    ds : IndexedDataset
    shapes : (S,V,3) array_like
        The dataset shapes as positions (not unskinned), scene units.
    motion : (S,V) array_like
        How far every unskinned shape moves every vertex, scene units.
    params : IndexerParams

    Returns
    -------
    BundleClouds

    Raises
    ------
    BundleError
        A bundle no shape moves.
    DatasetError
        A forbidden set naming an unknown shape.
    """
    P, move = _point_clouds(ds, shapes)
    keep = _prune(ds, motion, move, params.prune_tolerance_at(ds.face_size))
    forbidden = forbidden_shape_ids(params.forbidden, ds.names)
    # Shapes that put the bundle at the same place (within merge_tolerance) share one cloud point;
    # which of them is used is decided per frame by the neighbouring bundles (§5.1).
    merge_tol = params.merge_tolerance_at(ds.face_size)
    t = _merged_tetrahedra(ds, P, keep, merge_tol, params, forbidden)
    tet_counts = t.pop("tet_counts")
    hulls = _convex_hulls(P, t["reps"])
    maps = _tetrahedron_maps(P, t["tets"], tet_counts)
    return BundleClouds(points=P, motion=move, merge_tolerance=merge_tol, **t, **hulls, **maps)


def tetrahedralize(pts, ids, K, qmin, max_edge, min_per_point, st, forbidden=(), delaunay=True):
    """Overlapping tetrahedra of one point cloud (§4, §4.1), as shape ids.

    Parameters
    ----------
    pts : (m,3) array_like
        The cloud's distinct points, scene units.
    ids : (m,) int array_like
        Their shape ids.
    K : int
        Each point forms tetrahedra with 3 of its ``K`` nearest points.
    qmin : float
        Least mean-ratio quality kept (unitless, 0..1).
    max_edge : float or None
        Longest edge kept, scene units.
    min_per_point : int
        Tetrahedra every point keeps at least.
    st : dict
        Counters (``candidates``, ``thin``, ``large``, ``flagged``,
        ``restored``, ``flat_clouds``, ``segment_clouds``), incremented.
    forbidden : list of int arrays
        Shape-id sets a tetrahedron must not hold all of (:func:`forbidden_shape_ids`).
    delaunay : bool
        Add the cloud's Delaunay tetrahedra (they cover its convex hull).

    Returns
    -------
    (n,4) int ndarray
        Shape ids; flat clouds give triangles ``(a, b, c, c)``, collinear or
        two-point clouds segments ``(a, b, b, b)``.
    """
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
    if forbidden:
        g = ids[cand]
        flag = np.zeros(len(cand), dtype=bool)
        for fs in forbidden:
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


def build_grid(clouds, density, face_size):
    """Uniform grid per bundle over its tetrahedra's boxes ([18, 32]), for point-in-tetrahedron queries.

    Parameters
    ----------
    clouds : BundleClouds
    density : float
        Grid cells per tetrahedron (about ``(n_tets * density)^(1/3)`` cells
        along a bundle grid's longest side, at most 48).
    face_size : float
        Scene units; floors the grid extent of a flat cloud.

    Returns
    -------
    TetGrid
    """
    density = float(density)
    B = len(clouds.tet_offsets) - 1
    starts, entries, lo_all, h_all, n_all, base = [], [], [], [], [], []
    total = 0
    n_entries = 0
    for i in range(B):
        a, b = clouds.tet_offsets[i], clouds.tet_offsets[i + 1]
        lo_t, hi_t = clouds.tet_lo[a:b].astype(np.float64), clouds.tet_hi[a:b].astype(np.float64)
        lo, hi = lo_t.min(axis=0), hi_t.max(axis=0)
        ext = np.maximum(hi - lo, 1e-12 * max(face_size, 1e-12))
        nt = b - a
        nc = int(np.clip(np.round(np.cbrt(nt * density)), 1, 48))
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
    return TetGrid(density=density, cell_start=np.r_[np.concatenate(starts), len(cell_tets)].astype(np.int64),
                   cell_tets=cell_tets, lo=np.array(lo_all), h=np.array(h_all), n=np.array(n_all),
                   base=np.array(base, dtype=np.int64))
