"""Natural-neighbour (Sibson) weights of sparse bundles on a surface mesh.

Cong, Lan and Fedkiw 2019, "Local Geometric Indexing of High Resolution Data
for Facial Reconstruction from Sparse Markers", §5 and Fig. 1: the local
geometry found for every bundle is sewn into one face with a Voronoi diagram
of the bundles on the neutral mesh and natural-neighbour interpolation
[Sibson 1980; Park et al. 2006]. The weight of bundle ``i`` at a vertex is
the area that the vertex's own Voronoi cell, once the vertex is inserted into
the diagram, steals from the cell of ``i``, divided by the cell's area. The
weights are non-negative, sum to one, are one at a bundle's own position and
give a C0 surface. The paper found the diagram built in UV space smoother
than one built on the 3D mesh; both are offered here:

``method="uv"`` (default)
    Exact Sibson coordinates in the plane of the UV map, computed in closed
    form with Watson's cavity construction: the Delaunay triangles whose
    circumcircle holds the vertex are replaced by triangles fanned from it,
    and the area stolen from bundle ``i`` is the difference of the signed
    fan areas of its old and new Voronoi cell pieces (:func:`sibson_coordinates`).
    Only the UV islands that hold a bundle are used (coincident UVs on the
    two sides of a seam are welded, as on ICT-FaceKit's face).
``method="geodesic"``
    Discrete Sibson interpolation (Park et al. 2006, the paper's ref. [30])
    on the mesh with edge-path geodesic distances: vertex ``x`` (with area
    ``a_x``, owned by the nearest bundle ``c(x)`` at distance ``D(x)``) lies
    in the inserted cell of vertex ``v`` when ``d(x, v) < D(x)``; the weight
    of bundle ``i`` at ``v`` is the area of such ``x`` owned by ``i``, divided
    by the total. The cell is clipped to a geodesic disc of radius ``radius``
    so that vertices far from every bundle stay cheap.

Vertices outside that domain (other UV islands, teeth, eyes, or mesh pieces
without a bundle) copy the weights of the nearest domain vertex on the neutral
mesh: the paper's "extrapolates from the nearest bundle" (§7).

The weights depend only on the neutral mesh and where the bundles are bound,
so they are computed once (:func:`natural_neighbor_weights`) and reused for
every frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.spatial import Delaunay, cKDTree

from ..errors import FaceLabError, MeshError
from ..geometry.mesh import edge_length_graph, vertex_adjacency

__all__ = [
    "sibson_coordinates",
    "surface_points",
    "vertex_uvs",
    "NaturalNeighbors",
    "natural_neighbor_weights",
    "gaussian_rbf_weights",
]


# --------------------------------------------------------------------------
# Sibson coordinates in the plane
# --------------------------------------------------------------------------


def _circumcenters(a, b, c):
    """(n,2) circumcentres of the triangles ``a b c`` (each (n,2))."""
    bx, by = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]
    cx, cy = c[:, 0] - a[:, 0], c[:, 1] - a[:, 1]
    d = 2.0 * (bx * cy - by * cx)
    b2, c2 = bx * bx + by * by, cx * cx + cy * cy
    with np.errstate(divide="ignore", invalid="ignore"):
        ux = (cy * b2 - by * c2) / d
        uy = (bx * c2 - cx * b2) / d
    return np.stack([ux + a[:, 0], uy + a[:, 1]], axis=1)


def _cross(u, v):
    return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]


def _tau(o, x_i, x_next, x_prev, cc):
    """Fan area pieces of site ``i``'s Voronoi cell at one triangle corner.

    ``A(o, m_next, c) + A(o, c, m_prev)``, where ``m`` are the midpoints of the
    Delaunay edges to the next and previous corner (ccw) and ``c`` is the
    triangle's circumcentre; ``o`` is the fan origin (any point).
    """
    m_n = 0.5 * (x_i + x_next) - o
    m_p = 0.5 * (x_i + x_prev) - o
    c = cc - o
    return 0.5 * (_cross(m_n, c) + _cross(c, m_p))


def sibson_coordinates(sites, points, *, n_ghosts: int = 16, ghost_radius: float = 4.0, snap: float = 1e-9,
                       chunk: int = 4096):
    """Exact Sibson (natural-neighbour) coordinates of points among 2D sites.

    Watson's construction: inserting ``p`` into the Delaunay triangulation of
    the sites removes the *cavity* (triangles whose circumcircle contains
    ``p``) and fans new triangles from ``p`` to the cavity border. The area
    that ``p``'s new Voronoi cell steals from site ``i`` is
    ``sum_cavity tau(T, i) - sum_new tau(N, i)``, with ``tau`` the fan-area
    piece of ``i``'s cell at a triangle corner (old cell minus new cell). To
    give every point a bounded cell, ``n_ghosts`` ghost sites are placed on a
    circle of ``ghost_radius`` times the data radius; their weights are
    dropped and the rest renormalised (outside the sites' convex hull this
    extrapolates from the nearest sites, continuously).

    Parameters
    ----------
    sites : (n,2) array_like
        Site positions (any planar units), pairwise distinct.
    points : (Q,2) array_like
        Query positions, same units.
    n_ghosts, ghost_radius : int, float
        Ghost sites that bound the diagram.
    snap : float
        A point closer than ``snap`` times the data radius to a site gets
        weight exactly 1 there (the stolen areas vanish quadratically and lose
        precision).
    chunk : int
        Points handled at once (memory: ``chunk`` x triangles booleans).

    Returns
    -------
    (Q,n) scipy.sparse.csr_matrix
        Non-negative weights, each row sums to 1, ``w[i, j] = 1`` when point
        ``i`` is site ``j``. Unitless.

    Raises
    ------
    FaceLabError
        If fewer than 3 sites are given or two sites coincide.
    """
    S = np.asarray(sites, dtype=np.float64).reshape(-1, 2)
    P = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    n = len(S)
    if n < 1:
        raise FaceLabError("Natural-neighbour weights need at least one site (bundle); add bundles.")
    allp = np.vstack([S, P]) if len(P) else S
    lo, hi = allp.min(axis=0), allp.max(axis=0)
    center = 0.5 * (lo + hi)
    radius = max(0.5 * float(np.linalg.norm(hi - lo)), 1e-12)
    if n > 1:
        dd, _ = cKDTree(S).query(S, k=2)
        if (dd[:, 1] <= 1e-12 * radius).any():
            i = int(np.argmin(dd[:, 1]))
            raise FaceLabError(
                f"Two bundles sit at the same place (site {i}); remove one or bind it to a different surface point."
            )
    ang = 2 * np.pi * (np.arange(n_ghosts) + 0.5) / n_ghosts
    G = center + ghost_radius * radius * np.stack([np.cos(ang), np.sin(ang)], axis=1)
    X = np.vstack([S, G])
    tri = Delaunay(X)
    T = tri.simplices.astype(np.int64).copy()
    NB = tri.neighbors.astype(np.int64).copy()
    # counter-clockwise corners (neighbors[k] is opposite corner k)
    area2 = _cross(X[T[:, 1]] - X[T[:, 0]], X[T[:, 2]] - X[T[:, 0]])
    flip = area2 < 0
    T[flip] = T[flip][:, [0, 2, 1]]
    NB[flip] = NB[flip][:, [0, 2, 1]]
    cc = _circumcenters(X[T[:, 0]], X[T[:, 1]], X[T[:, 2]])
    r2 = ((X[T[:, 0]] - cc) ** 2).sum(axis=1)
    nT = len(T)

    rows_out, cols_out, vals_out = [], [], []
    snap_d = snap * radius
    near_d, near_i = cKDTree(S).query(P) if len(P) else (np.zeros(0), np.zeros(0, np.int64))
    for s0 in range(0, len(P), chunk):
        p = P[s0 : s0 + chunk]
        q = len(p)
        inside = ((p[:, None, :] - cc[None, :, :]) ** 2).sum(axis=2) < r2[None, :]
        qi, ti = np.nonzero(inside)
        vals = np.zeros((q, len(X)))
        o = p[qi]
        # old pieces: + tau(T, corner) for every cavity triangle and corner
        for k in range(3):
            i_, n_, p_ = T[ti, k], T[ti, (k + 1) % 3], T[ti, (k + 2) % 3]
            t = _tau(o, X[i_], X[n_], X[p_], cc[ti])
            np.add.at(vals, (qi, i_), t)
        # new pieces: - tau(N, a), - tau(N, b) for N = (a, b, p) on every border edge
        for k in range(3):
            nb = NB[ti, k]
            border = nb < 0
            ok = ~border
            border[ok] = ~inside[qi[ok], nb[ok]]
            qq, tt = qi[border], ti[border]
            a = T[tt, (k + 1) % 3]
            b = T[tt, (k + 2) % 3]
            pp = p[qq]
            cn = _circumcenters(X[a], X[b], pp)
            ta = _tau(pp, X[a], X[b], pp, cn)
            tb = _tau(pp, X[b], pp, X[a], cn)
            np.add.at(vals, (qq, a), -ta)
            np.add.at(vals, (qq, b), -tb)
        vals = vals[:, :n]
        vals[vals < 0] = 0.0
        tot = vals.sum(axis=1)
        # points on a site (or whose cell only touched ghosts): the nearest site
        hit = (near_d[s0 : s0 + q] <= snap_d) | ~(tot > 0)
        vals[hit] = 0.0
        vals[hit, near_i[s0 : s0 + q][hit]] = 1.0
        vals /= vals.sum(axis=1, keepdims=True)
        vals[vals < 1e-14] = 0.0
        r, c = np.nonzero(vals)
        rows_out.append(r + s0)
        cols_out.append(c)
        vals_out.append(vals[r, c])
    if not rows_out:
        return sp.csr_matrix((0, n))
    r, c, v = (np.concatenate(a) for a in (rows_out, cols_out, vals_out))
    W = sp.csr_matrix((v, (r, c)), shape=(len(P), n))
    # renormalise after dropping the tiny entries
    s = np.asarray(W.sum(axis=1)).ravel()
    return sp.diags(1.0 / s) @ W


# --------------------------------------------------------------------------
# Surface helpers
# --------------------------------------------------------------------------


def surface_points(vertices, faces, bundle_faces, bundle_bary):
    """(B,3) positions of surface points given as (face, barycentric) pairs.

    Parameters
    ----------
    vertices : (V,3) or (..., V,3) array_like
        Positions, scene units; leading axes (shapes, frames) are kept.
    faces : (F,3) int array_like
    bundle_faces : (B,) int array_like
    bundle_bary : (B,3) array_like
        Barycentric coordinates in each face (sum to 1).

    Returns
    -------
    (..., B, 3) float64 ndarray, scene units.
    """
    X = np.asarray(vertices, dtype=np.float64)
    F = np.asarray(faces, dtype=np.int64)[np.asarray(bundle_faces, dtype=np.int64)]
    b = np.asarray(bundle_bary, dtype=np.float64)
    return np.einsum("...bkx,bk->...bx", X[..., F, :], b)


def _corner_uvs(faces, uvs, n_vertices):
    F = np.asarray(faces, dtype=np.int64)
    U = np.asarray(uvs, dtype=np.float64)
    if U.ndim == 2 and U.shape == (n_vertices, 2):
        return U[F]
    if U.ndim == 3 and U.shape == (len(F), 3, 2):
        return U
    raise MeshError(
        f"UVs must be per vertex (V,2)=({n_vertices},2) or per triangle corner (F,3,2)=({len(F)},3,2), "
        f"got shape {U.shape}; export the active UV map of the triangulated mesh."
    )


def _uv_islands(faces, corner_uv):
    """(F,) island label: triangles joined by edges whose UVs agree at both ends."""
    F = np.asarray(faces, dtype=np.int64)
    nF = len(F)
    scale = max(float(np.abs(corner_uv).max()), 1e-12)
    qv = np.round(corner_uv / scale * 1e9).astype(np.int64)  # (F,3,2) quantised
    ends = []
    for k in range(3):
        a, b = F[:, k], F[:, (k + 1) % 3]
        ua, ub = qv[:, k], qv[:, (k + 1) % 3]
        swap = a > b
        lo_v, hi_v = np.where(swap, b, a), np.where(swap, a, b)
        lo_u = np.where(swap[:, None], ub, ua)
        hi_u = np.where(swap[:, None], ua, ub)
        ends.append(np.column_stack([lo_v, hi_v, lo_u, hi_u, np.arange(nF)]))
    E = np.vstack(ends)
    order = np.lexsort(E[:, :6].T[::-1])
    E = E[order]
    same = (E[1:, :6] == E[:-1, :6]).all(axis=1)
    i, j = E[:-1, 6][same], E[1:, 6][same]
    A = sp.coo_matrix((np.ones(len(i)), (i, j)), shape=(nF, nF))
    from scipy.sparse.csgraph import connected_components

    _, lab = connected_components(A, directed=False)
    return lab


def vertex_uvs(faces, uvs, n_vertices, domain_faces):
    """Per-vertex UVs on a set of triangles.

    Parameters
    ----------
    faces : (F,3) int array_like
    uvs : (V,2) or (F,3,2) array_like
        Per-vertex or per-corner texture coordinates.
    n_vertices : int
    domain_faces : (F,) bool array_like
        Triangles whose vertices get a UV.

    Returns
    -------
    uv : (V,2) float64 ndarray
        NaN for vertices outside the domain. A vertex with several different
        UVs in the domain (a seam) keeps the first.
    n_seam : int
        Number of such seam vertices.
    """
    F = np.asarray(faces, dtype=np.int64)
    cu = _corner_uvs(F, uvs, n_vertices)
    dom = np.asarray(domain_faces, dtype=bool)
    v = F[dom].ravel()
    u = cu[dom].reshape(-1, 2)
    out = np.full((n_vertices, 2), np.nan)
    first_idx = np.full(n_vertices, len(v), dtype=np.int64)
    np.minimum.at(first_idx, v, np.arange(len(v)))
    has = first_idx < len(v)
    out[has] = u[first_idx[has]]
    diff = np.abs(u - out[v]).max(axis=1) > 1e-9 * max(1.0, float(np.abs(u).max()))
    n_seam = int(len(np.unique(v[diff])))
    return out, n_seam


def _vertex_areas(V, F):
    a = 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)
    out = np.zeros(len(V))
    for k in range(3):
        np.add.at(out, F[:, k], a / 3.0)
    return out


@dataclass
class NaturalNeighbors:
    """Natural-neighbour weights of ``B`` bundles at the ``V`` mesh vertices.

    Attributes
    ----------
    weights : (V,B) scipy.sparse.csr_matrix
        Sibson weights; rows sum to 1. Unitless.
    cell : (V,) int64
        The bundle whose Voronoi cell holds each vertex (nearest bundle in the
        chosen metric; for vertices outside the domain, that of the domain
        vertex they copy).
    neighbors : (B,B) scipy.sparse.csr_matrix
        0/1 adjacency of Voronoi cells (natural neighbours): bundles ``i``
        and ``j`` are neighbours when a mesh edge joins their cells.
    domain : (V,) bool
        Vertices whose weights were computed (the rest copy their nearest
        domain vertex, listed in ``copied_from``).
    copied_from : (V,) int64
        For vertices outside the domain, the domain vertex they copy; -1 inside.
    method : str
        ``"uv"`` or ``"geodesic"``.
    site_uv : (B,2) float64 or None
        Bundle UVs (UV method).
    vertex_uv : (V,2) float64 or None
        Vertex UVs (NaN outside the domain; UV method).
    n_seam_vertices : int
        Domain vertices with more than one UV (their first UV was used).
    """

    weights: sp.csr_matrix
    cell: np.ndarray
    neighbors: sp.csr_matrix
    domain: np.ndarray
    copied_from: np.ndarray
    method: str
    site_uv: np.ndarray | None = None
    vertex_uv: np.ndarray | None = None
    n_seam_vertices: int = 0
    info: dict = field(default_factory=dict)


def natural_neighbor_weights(vertices, faces, bundle_faces, bundle_bary, *, uvs=None, method=None,
                             radius=None) -> NaturalNeighbors:
    """Natural-neighbour (Sibson) weights of surface-bound bundles at every vertex.

    Cong et al. 2019, §5: Voronoi diagram of the bundles on the neutral mesh
    (in UV space, or with geodesics) and natural-neighbour weights.

    Parameters
    ----------
    vertices : (V,3) array_like
        Neutral positions, scene units.
    faces : (F,3) int array_like
        Triangles.
    bundle_faces : (B,) int array_like
        Triangle holding each bundle on the neutral mesh.
    bundle_bary : (B,3) array_like
        Barycentric coordinates of each bundle in its triangle.
    uvs : (V,2) or (F,3,2) array_like, optional
        Texture coordinates (per vertex or per triangle corner). Required for
        ``method="uv"``.
    method : {"uv", "geodesic"}, optional
        Default ``"uv"`` when ``uvs`` is given, else ``"geodesic"``.
    radius : float, optional
        Geodesic method only: the inserted cells are clipped to a geodesic
        disc of this radius (scene units). Default: three times the median
        distance between neighbouring bundles.

    Returns
    -------
    NaturalNeighbors

    Raises
    ------
    FaceLabError
        If two bundles share a surface point, a bundle's UVs are degenerate,
        or ``method="uv"`` is asked without UVs.
    """
    V = np.asarray(vertices, dtype=np.float64)
    F = np.asarray(faces, dtype=np.int64)
    bf = np.asarray(bundle_faces, dtype=np.int64)
    bb = np.asarray(bundle_bary, dtype=np.float64)
    nv, B = len(V), len(bf)
    if method is None:
        method = "uv" if uvs is not None else "geodesic"
    if method not in ("uv", "geodesic"):
        raise FaceLabError(f"Unknown natural-neighbour method {method!r}; use 'uv' or 'geodesic'.")
    from scipy.sparse.csgraph import connected_components

    if method == "uv":
        if uvs is None:
            raise FaceLabError(
                "Natural-neighbour weights in UV space need the mesh's UV map; unwrap the face or use "
                "method='geodesic'."
            )
        cu = _corner_uvs(F, uvs, nv)
        isl = _uv_islands(F, cu)
        dom_f = np.isin(isl, np.unique(isl[bf]))
        vuv, n_seam = vertex_uvs(F, cu, nv, dom_f)
        site_uv = np.einsum("bkx,bk->bx", cu[bf], bb)
        domain = np.isfinite(vuv[:, 0])
        dv = np.flatnonzero(domain)
        Wd = sibson_coordinates(site_uv, vuv[dv])
        cell_d = cKDTree(site_uv).query(vuv[dv])[1]
        info = {"uv_islands_used": int(len(np.unique(isl[bf])))}
    else:
        n_comp, comp = connected_components(vertex_adjacency(F, nv), directed=False)
        used = np.zeros(nv, dtype=bool)
        used[F.ravel()] = True
        domain = np.isin(comp, np.unique(comp[F[bf, 0]])) & used
        dv = np.flatnonzero(domain)
        Wd, cell_d, info = _geodesic_sibson(V, F, bf, bb, dv, radius)
        site_uv, vuv, n_seam = None, None, 0
    # vertices outside the domain copy their nearest domain vertex (neutral, 3D)
    copied = -np.ones(nv, dtype=np.int64)
    out_v = np.flatnonzero(~domain)
    rowmap = -np.ones(nv, dtype=np.int64)
    rowmap[dv] = np.arange(len(dv))
    if len(out_v):
        _, k = cKDTree(V[dv]).query(V[out_v])
        copied[out_v] = dv[k]
        rowmap[out_v] = k
    W = Wd[rowmap].tocsr()
    cell = cell_d[rowmap].astype(np.int64)
    # natural neighbours: Voronoi cells joined by a mesh edge (domain vertices only)
    E = np.vstack([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    E = E[domain[E[:, 0]] & domain[E[:, 1]]]
    a, b = cell[E[:, 0]], cell[E[:, 1]]
    k = a != b
    Nb = sp.coo_matrix((np.ones(int(k.sum()) * 2), (np.r_[a[k], b[k]], np.r_[b[k], a[k]])), shape=(B, B)).tocsr()
    Nb.data[:] = 1.0
    Nb.sum_duplicates()
    Nb.data[:] = 1.0
    return NaturalNeighbors(
        weights=W, cell=cell, neighbors=Nb, domain=domain, copied_from=copied, method=method,
        site_uv=site_uv, vertex_uv=vuv, n_seam_vertices=n_seam, info=info,
    )


def _geodesic_sibson(V, F, bf, bb, dv, radius):
    """Discrete Sibson weights (Park et al. 2006) with edge-path geodesics, on domain vertices ``dv``."""
    from scipy.sparse.csgraph import dijkstra

    nv, B = len(V), len(bf)
    G = edge_length_graph(V, F, nv)[0]
    # one virtual node per bundle, joined to its triangle's corners by the exact 3D distance
    P = surface_points(V, F, bf, bb)
    corners = F[bf]
    dist = np.linalg.norm(V[corners] - P[:, None, :], axis=2)
    rows = np.repeat(np.arange(B) + nv, 3)
    cols = corners.ravel()
    w = np.maximum(dist.ravel(), 1e-300)
    Ga = sp.bmat([[G, None], [None, sp.csr_matrix((B, B))]]).tocsr()
    Ga = (Ga + sp.coo_matrix((np.r_[w, w], (np.r_[rows, cols], np.r_[cols, rows])), shape=(nv + B, nv + B))).tocsr()
    D, pred, src = dijkstra(Ga, directed=False, indices=np.arange(nv, nv + B), min_only=True,
                            return_predecessors=True)
    D = D[:nv]
    lab = np.asarray(src[:nv], dtype=np.int64) - nv
    if radius is None:
        sp_dist = dijkstra(Ga, directed=False, indices=np.arange(nv, nv + B), limit=np.inf)[:, nv:]
        sp_dist[np.arange(B), np.arange(B)] = np.inf
        radius = 3.0 * float(np.median(sp_dist.min(axis=1)))
    radius = float(radius)
    area = _vertex_areas(V, F)
    r = np.minimum(D, radius)
    dom = np.zeros(nv, dtype=bool)
    dom[dv] = True
    xs = dv[np.argsort(r[dv])]
    chunk = 256
    acc_r, acc_c, acc_v = [], [], []
    for s0 in range(0, len(xs), chunk):
        x = xs[s0 : s0 + chunk]
        lim = float(r[x].max())
        d = dijkstra(G, directed=False, indices=x, limit=lim * (1 + 1e-12))
        xi, vi = np.nonzero(d < r[x][:, None])
        keep = dom[vi]
        xi, vi = xi[keep], vi[keep]
        acc_r.append(vi)
        acc_c.append(lab[x[xi]])
        acc_v.append(area[x[xi]])
    rr, cc, vv = (np.concatenate(a) for a in (acc_r, acc_c, acc_v))
    num = sp.csr_matrix((vv, (rr, cc)), shape=(nv, B))
    num = num[dv]
    s = np.asarray(num.sum(axis=1)).ravel()
    bad = ~(s > 0)
    if bad.any():  # isolated vertex: nearest bundle
        fix = sp.csr_matrix((np.ones(int(bad.sum())), (np.flatnonzero(bad), lab[dv[bad]])), shape=num.shape)
        num = num + fix
        s = np.asarray(num.sum(axis=1)).ravel()
    W = (sp.diags(1.0 / s) @ num).tocsr()
    W.eliminate_zeros()
    return W, lab[dv], {"geodesic_radius": radius}


def gaussian_rbf_weights(vertices, sites, sigma=None, *, ridge: float = 1e-10):
    """Gaussian RBF interpolation weights (the paper's §7 / Fig. 4 baseline).

    ``f(v) = sum_j phi(|v - s_j|) a_j`` with ``phi(r) = exp(-(r/sigma)^2)`` and
    ``Phi a = f_sites``, so ``f(v) = R[v] @ f_sites`` with
    ``R = Phi_vs Phi_ss^-1``. Applied to the per-bundle shape weights this is
    the paper's "Gaussian RBF interpolation instead of natural neighbor
    interpolation": detail from the dataset, but the surface does not pass
    through the bundles (the weights are interpolated at the bundles' surface
    points, not at the vertices of their triangles, and rows do not sum to one).

    Parameters
    ----------
    vertices : (V,d) array_like
        Evaluation points (for example neutral vertices, scene units).
    sites : (B,d) array_like
        Bundle positions on the neutral, same units.
    sigma : float, optional
        Gaussian width, same units. Default: the median distance from a
        bundle to its nearest other bundle.
    ridge : float
        Relative Tikhonov term for ``Phi_ss``.

    Returns
    -------
    (V,B) float64 ndarray
    """
    X = np.asarray(vertices, dtype=np.float64)
    S = np.asarray(sites, dtype=np.float64)
    if sigma is None:
        d, _ = cKDTree(S).query(S, k=2)
        sigma = float(np.median(d[:, 1]))
    sigma = float(sigma)

    def phi(A, Bm):
        d2 = (A * A).sum(1)[:, None] + (Bm * Bm).sum(1)[None, :] - 2.0 * A @ Bm.T
        return np.exp(-np.maximum(d2, 0.0) / sigma**2)

    K = phi(S, S)
    K[np.diag_indices_from(K)] += ridge
    return np.linalg.solve(K, phi(X, S).T).T
