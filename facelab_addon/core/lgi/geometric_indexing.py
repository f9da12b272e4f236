"""Local geometric indexing: a high-resolution face from sparse 3D bundles.

Cong, Lan and Fedkiw 2019, "Local Geometric Indexing of High Resolution Data
for Facial Reconstruction from Sparse Markers". Instead of fitting a
blendshape model to the bundles, every bundle looks up the dataset shapes
whose local geometry reproduces its position, and the per-bundle geometry is
sewn together with natural-neighbour weights.

Build once (:class:`GeometricIndexer`), then reconstruct every frame:

* **Point clouds** (§4): the position of every bundle on every dataset shape
  (plus the neutral, shape 0).
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
  clouds a segment. ``stats`` says how many are kept and their memory.
* **Uniform grid** per bundle ([18, 32]) for point-in-tetrahedron queries
  (float32 bounding boxes screen the candidates, precomputed float64 affine
  maps give the barycentric weights).
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
* **Jaw** (§6, Eq. 2): with a :class:`JawRig`, dataset shapes are unskinned
  (``b* = T(theta_n)^-1 (x0 + b_n) - x0``), bundles are unskinned per frame
  with the frame's jaw parameters (at the bundle's skinning weight), and the
  blend is skinned back by linear blend skinning.
* **Temporal smoothing** (§7): a central moving average of every bundle's
  barycentric shape weights (relative to the jaw-skinned neutral, so the jaw
  is not smoothed), applied as the average of the frames' blends (the
  stitching is linear in the weights: no extra blending). With
  ``exact=True`` the surface then passes through the moving average of the
  bundles, so the noise of single frames is not put back.
* **Corrective shapes** (§7, Fig. 7): :class:`RigCorrectives` indexes the
  dataset's residuals from the linear rig with the bundles of a rig-shape
  combination (a deviation from indexing the shapes themselves, which does
  worse than the linear combination on combinations the dataset lacks).
* **Sequences** run on two cores when one is idle: frames are indexed in
  order on the calling thread while a worker blends them and finishes the
  frames whose smoothing window is complete. BLAS is kept to one thread (its
  spinning threads cost more than they give per frame).

The paper's baselines (§7, Fig. 4) are here too: :class:`BlendshapeFit`
(dataset blendshapes fit to the bundles with soft [0,1] bounds) and
``stitching="rbf"`` (Gaussian RBF interpolation of the per-bundle shape
weights instead of natural neighbours).

Units: positions in scene units; barycentric and natural-neighbour weights
are unitless; jaw angles in radians.
"""

from __future__ import annotations

import itertools
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
from scipy.spatial import cKDTree

from ..errors import BundleError, DatasetError, FaceLabError, MeshError  # noqa: F401
from ..geometry.mesh import validate_mesh
from .natural_neighbor import gaussian_rbf_weights, natural_neighbor_weights, surface_points

__all__ = [
    "BundleError",
    "DatasetError",
    "JawRig",
    "bind_points",
    "barycentric_tetrahedron",
    "closest_point_tetrahedron",
    "tetrahedron_quality",
    "GeometricIndexer",
    "BlendshapeFit",
    "RigCorrectives",
    "fit_rig_weights",
    "moving_bundle_layout",
    "rig_correctives",
]




# --------------------------------------------------------------------------
# Jaw (§6)
# --------------------------------------------------------------------------


def _axis_angle(axis, angle):
    """(...,3,3) rotation matrices about a unit ``axis`` (3,) by ``angle`` (...,) radians."""
    a = np.asarray(axis, dtype=np.float64)
    th = np.asarray(angle, dtype=np.float64)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    s, c = np.sin(th)[..., None, None], np.cos(th)[..., None, None]
    return np.eye(3) + s * K + (1 - c) * (K @ K)


@dataclass
class JawRig:
    """A jaw joint with linear-blend-skinning weights (Cong et al. 2019, §6).

    The jaw transform for parameters ``theta = (angle, tx, ty, tz)`` rotates
    by ``angle`` radians about ``axis`` through ``pivot`` and then translates
    by ``(tx, ty, tz)`` (scene units): ``T(x) = R (x - pivot) + pivot + t``.
    ``theta`` may also be a general rigid jaw pose, a (4,4) matrix ``[R t]``
    (for example a jaw bone's motion from its rest pose, in the mesh's
    space). Vertex ``v`` follows ``(1 - w_v) x + w_v T(x)`` (linear blend
    skinning with the skull, which stays put).

    Attributes
    ----------
    pivot : (3,) float64
        A point on the hinge axis, scene units.
    axis : (3,) float64
        Unit hinge axis.
    weights : (V,) float64
        Skinning weight of the jaw at every vertex, in [0, 1].
    """

    pivot: np.ndarray
    axis: np.ndarray
    weights: np.ndarray

    def __post_init__(self):
        self.pivot = np.asarray(self.pivot, dtype=np.float64).reshape(3)
        a = np.asarray(self.axis, dtype=np.float64).reshape(3)
        self.axis = a / np.linalg.norm(a)
        self.weights = np.clip(np.asarray(self.weights, dtype=np.float64).ravel(), 0.0, 1.0)

    def transform(self, theta):
        """Rigid jaw transform.

        Parameters
        ----------
        theta : (4,) or (4,4) array_like
            ``(angle rad, tx, ty, tz)``, or a rigid matrix.

        Returns
        -------
        R : (3,3) float64
        t : (3,) float64
            ``T(x) = R x + t``, scene units.
        """
        th = np.asarray(theta, dtype=np.float64)
        if th.shape == (4, 4):
            return th[:3, :3].copy(), th[:3, 3].copy()
        th = th.reshape(4)
        R = _axis_angle(self.axis, th[0])
        return R, self.pivot - R @ self.pivot + th[1:]

    def _affine(self, theta, w):
        R, t = self.transform(theta)
        w = np.asarray(w, dtype=np.float64)
        A = (1 - w)[:, None, None] * np.eye(3) + w[:, None, None] * R
        return A, w[:, None] * t

    def skin(self, X, theta, weights=None):
        """Linear blend skinning of points.

        Parameters
        ----------
        X : (N,3) array_like
            Points, scene units (default: one per mesh vertex).
        theta : (4,) array_like
            Jaw parameters.
        weights : (N,) array_like, optional
            Skinning weights of the points (default ``self.weights``).

        Returns
        -------
        (N,3) float64 ndarray
        """
        X = np.asarray(X, dtype=np.float64)
        w = self.weights if weights is None else np.asarray(weights, dtype=np.float64)
        R, t = self.transform(theta)
        # (X R^T + t - X) without BLAS: a (V,3)x(3,3) product would wake multithreaded BLAS, whose
        # spinning threads cost more than the product on a busy machine
        D = X[:, :1] * (R[:, 0] - [1, 0, 0]) + X[:, 1:2] * (R[:, 1] - [0, 1, 0]) + X[:, 2:] * (R[:, 2] - [0, 0, 1]) + t
        return X + w[:, None] * D

    def unskin(self, X, theta, weights=None):
        """Invert :meth:`skin`: ``T_v(theta)^-1 x`` at every point.

        Parameters
        ----------
        X : (N,3) array_like
            Skinned points, scene units.
        theta : (4,) array_like
        weights : (N,) array_like, optional

        Returns
        -------
        (N,3) float64 ndarray
        """
        X = np.asarray(X, dtype=np.float64)
        w = self.weights if weights is None else np.asarray(weights, dtype=np.float64)
        A, b = self._affine(theta, w)
        inv, _ = _inv3(A)
        return np.einsum("nij,nj->ni", inv, X - b)

    def fit_pose(self, shape, neutral, *, min_weight: float = 0.99):
        """Estimate a shape's jaw pose: the rigid motion of its jaw vertices (Kabsch fit).

        Every dataset shape needs its jaw parameters (§6); the vertices that
        follow the jaw rigidly (skinning weight >= ``min_weight``: lower teeth,
        chin) give them.

        Parameters
        ----------
        shape, neutral : (V,3) array_like
            Positions, scene units.
        min_weight : float

        Returns
        -------
        (4,4) float64 ndarray
            Rigid matrix ``[R t]`` (identity when the jaw did not move).

        Raises
        ------
        DatasetError
            When fewer than 3 vertices follow the jaw rigidly.
        """
        A = np.asarray(neutral, dtype=np.float64)
        Bp = np.asarray(shape, dtype=np.float64)
        m = self.weights >= min_weight
        if m.sum() < 3:
            raise DatasetError(
                f"Only {int(m.sum())} vertices follow the jaw rigidly (weight >= {min_weight}); paint the jaw "
                "vertex group to 1 on the lower teeth and chin."
            )
        A, Bp = A[m], Bp[m]
        ca, cb = A.mean(0), Bp.mean(0)
        U, _, Vt = np.linalg.svd((A - ca).T @ (Bp - cb))
        d = np.sign(np.linalg.det(U @ Vt))
        R = (U @ np.diag([1.0, 1.0, d]) @ Vt).T
        M = np.eye(4)
        M[:3, :3] = R
        M[:3, 3] = cb - R @ ca
        return M

    def unskin_shape(self, shape, neutral, theta):
        """Unskinned delta of a dataset shape (Eq. 2): ``T(theta)^-1 (x0 + b) - x0``.

        Parameters
        ----------
        shape : (V,3) array_like
            The dataset shape ``x0 + b`` (positions), scene units.
        neutral : (V,3) array_like
        theta : (4,) array_like
            The shape's jaw parameters.

        Returns
        -------
        (V,3) float64 ndarray
            ``b*``, scene units.
        """
        return self.unskin(shape, theta) - np.asarray(neutral, dtype=np.float64)


# --------------------------------------------------------------------------
# Binding bundles to the neutral surface
# --------------------------------------------------------------------------


def bind_points(neutral, faces, points, *, max_distance=None, bundle_names=None):
    """Bind 3D points (bundles in the rest pose) to the closest surface points.

    Parameters
    ----------
    neutral : (V,3) array_like
        Neutral positions, scene units.
    faces : (F,3) int array_like
        Triangles.
    points : (B,3) array_like
        Bundle positions on the neutral face, scene units.
    max_distance : float, optional
        Largest allowed distance from a bundle to the surface, scene units.
        Default 0.5 percent of the mesh's bounding-box diagonal (about 2 mm on
        ICT-FaceKit).
    bundle_names : list of str, optional
        Names of the bundles for messages (default their indices).

    Returns
    -------
    bundle_faces : (B,) int64 ndarray
    bundle_bary : (B,3) float64 ndarray
        Barycentric coordinates in ``bundle_faces``.
    distance : (B,) float64 ndarray
        Distance from each point to the surface, scene units.

    Raises
    ------
    BundleError
        On NaN points, or points farther than ``max_distance`` from the mesh
        (the message lists them).
    """
    import igl

    V, F = validate_mesh(neutral, faces, name="neutral mesh")
    P = np.asarray(points, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3 or len(P) == 0:
        raise BundleError(f"Bundles must be a non-empty (B,3) array, got shape {P.shape}.")
    bad = ~np.isfinite(P).all(axis=1)
    if bad.any():
        raise BundleError(
            f"{int(bad.sum())} bundles have NaN rest positions ({_labels(bundle_names, np.flatnonzero(bad))}); "
            "bind bundles on a frame where all of them are tracked."
        )
    diag = float(np.linalg.norm(V.max(axis=0) - V.min(axis=0)))
    if max_distance is None:
        max_distance = 5e-3 * diag
    d2, fi, C = igl.point_mesh_squared_distance(P, V, F)
    fi = np.asarray(fi, dtype=np.int64).ravel()
    dist = np.sqrt(np.maximum(np.asarray(d2, dtype=np.float64).ravel(), 0.0))
    far = dist > max_distance
    if far.any():
        idx = np.flatnonzero(far)
        raise BundleError(
            f"{len(idx)} bundles are off the mesh: {_labels(bundle_names, idx)} lie "
            f"{np.round(dist[idx[:5]], 4).tolist()} scene units from the neutral surface (allowed "
            f"{max_distance:.4g}). Align the bundles rigidly to the neutral face (same units, same rest "
            "frame) or raise max_distance."
        )
    C = np.asarray(C, dtype=np.float64)
    bary = _triangle_barycentric(C, V[F[fi, 0]], V[F[fi, 1]], V[F[fi, 2]])
    return fi, bary, dist


def _labels(names, idx, n: int = 5):
    """'bundle [3, 7]' or "'B03', 'B07'" for messages (the first ``n``)."""
    idx = [int(i) for i in np.asarray(idx).ravel()[:n]]
    if names is None:
        return f"bundle {idx}"
    return ", ".join(repr(str(names[i])) for i in idx)


def _triangle_barycentric(p, a, b, c):
    """(n,3) barycentric coordinates of points ``p`` in triangles ``a b c`` (each (n,3))."""
    v0, v1, v2 = b - a, c - a, p - a
    d00, d01, d11 = (v0 * v0).sum(1), (v0 * v1).sum(1), (v1 * v1).sum(1)
    d20, d21 = (v2 * v0).sum(1), (v2 * v1).sum(1)
    den = d00 * d11 - d01 * d01
    v = (d11 * d20 - d01 * d21) / den
    w = (d00 * d21 - d01 * d20) / den
    bary = np.stack([1 - v - w, v, w], axis=1)
    bary = np.clip(bary, 0.0, None)
    return bary / bary.sum(axis=1, keepdims=True)


# --------------------------------------------------------------------------
# Tetrahedra: barycentric coordinates, closest points, quality
# --------------------------------------------------------------------------


def tetrahedron_quality(X):
    """Mean-ratio quality ``12 (3 vol)^(2/3) / sum(edge^2)`` of tetrahedra.

    Parameters
    ----------
    X : (n,4,3) array_like
        Corner positions, any length unit.

    Returns
    -------
    (n,) float64 ndarray
        1 for a regular tetrahedron, 0 for a flat one; unitless.
    """
    X = np.asarray(X, dtype=np.float64)
    e = X[:, 1:] - X[:, :1]
    vol = np.abs(_inv3(e)[1]) / 6.0
    l2 = sum(((X[:, i] - X[:, j]) ** 2).sum(1) for i, j in itertools.combinations(range(4), 2))
    with np.errstate(divide="ignore", invalid="ignore"):
        q = 12.0 * np.cbrt(3.0 * vol) ** 2 / l2
    return np.nan_to_num(q, nan=0.0)


def _inv3(E):
    """Closed-form inverses and determinants of (n,3,3) matrices (no per-matrix LAPACK calls)."""
    a, b, c = E[:, 0, 0], E[:, 0, 1], E[:, 0, 2]
    d, e, f = E[:, 1, 0], E[:, 1, 1], E[:, 1, 2]
    g, h, i = E[:, 2, 0], E[:, 2, 1], E[:, 2, 2]
    A, Bc, C = e * i - f * h, f * g - d * i, d * h - e * g
    det = a * A + b * Bc + c * C
    adj = np.stack([
        np.stack([A, c * h - b * i, b * f - c * e], axis=1),
        np.stack([Bc, a * i - c * g, c * d - a * f], axis=1),
        np.stack([C, b * g - a * h, a * e - b * d], axis=1),
    ], axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        return adj / det[:, None, None], det


def _tet_inverse(X, rel_eps=1e-10):
    """(n,3,3) inverse edge matrices ``[x1-x0, x2-x0, x3-x0]^-1``; NaN for flat tetrahedra."""
    E = np.transpose(X[:, 1:] - X[:, :1], (0, 2, 1))  # columns = edges
    inv, det = _inv3(E)
    L = np.linalg.norm(X[:, 1:] - X[:, :1], axis=2).max(axis=1)
    ok = np.abs(det) > rel_eps * np.maximum(L, 1e-300) ** 3
    inv[~ok] = np.nan
    return inv


def barycentric_tetrahedron(p, X):
    """Barycentric coordinates of points in tetrahedra.

    Parameters
    ----------
    p : (n,3) array_like
        Points, scene units.
    X : (n,4,3) array_like
        Tetrahedron corners, scene units.

    Returns
    -------
    (n,4) float64 ndarray
        ``w`` with ``sum(w) = 1`` and ``sum_k w_k X_k = p``; unitless. NaN for
        flat tetrahedra.
    """
    p = np.asarray(p, dtype=np.float64).reshape(-1, 3)
    X = np.asarray(X, dtype=np.float64).reshape(-1, 4, 3)
    inv = _tet_inverse(X)
    w = np.einsum("nij,nj->ni", inv, p - X[:, 0])
    return np.column_stack([1 - w.sum(1), w])


_EDGES = list(itertools.combinations(range(4), 2))
_FACES = list(itertools.combinations(range(4), 3))


def closest_point_tetrahedron(p, X, inv=None):
    """Closest point of (possibly flat) tetrahedra to query points.

    Robust to degenerate corners (repeated points, flat tetrahedra,
    triangles stored as ``(a, b, c, c)``): the candidates are the interior
    (when the tetrahedron is not flat), the 4 face interiors and the 6 edges.

    Parameters
    ----------
    p : (n,3) array_like
        Query points, scene units.
    X : (n,4,3) array_like
        Tetrahedron corners, scene units.
    inv : (n,3,3) array_like, optional
        Precomputed inverse edge matrices (:func:`_tet_inverse`).

    Returns
    -------
    distance : (n,) float64 ndarray
        Scene units.
    bary : (n,4) float64 ndarray
        Barycentric coordinates of the closest point (non-negative, sum 1).
    """
    p = np.asarray(p, dtype=np.float64).reshape(-1, 3)
    X = np.asarray(X, dtype=np.float64).reshape(-1, 4, 3)
    n = len(p)
    if inv is None:
        inv = _tet_inverse(X)
    cands_d, cands_w = [], []
    # interior
    w = np.einsum("nij,nj->ni", inv, p - X[:, 0])
    w = np.column_stack([1 - w.sum(1), w])
    ok = np.isfinite(w).all(1) & (w >= -1e-12).all(1)
    d = np.where(ok, 0.0, np.inf)
    cands_d.append(d)
    cands_w.append(np.where(ok[:, None], np.clip(np.nan_to_num(w), 0, None), 0.0))
    # edges
    for i, j in _EDGES:
        a, e = X[:, i], X[:, j] - X[:, i]
        ee = (e * e).sum(1)
        t = np.where(ee > 0, ((p - a) * e).sum(1) / np.where(ee > 0, ee, 1.0), 0.0)
        t = np.clip(t, 0.0, 1.0)
        q = a + t[:, None] * e
        cands_d.append(np.linalg.norm(p - q, axis=1))
        ww = np.zeros((n, 4))
        ww[:, i] = 1 - t
        ww[:, j] += t
        cands_w.append(ww)
    # faces
    for i, j, k in _FACES:
        a, e1, e2 = X[:, i], X[:, j] - X[:, i], X[:, k] - X[:, i]
        r = p - a
        a11, a12, a22 = (e1 * e1).sum(1), (e1 * e2).sum(1), (e2 * e2).sum(1)
        b1, b2 = (r * e1).sum(1), (r * e2).sum(1)
        det = a11 * a22 - a12 * a12
        good = det > 1e-12 * np.maximum(a11 * a22, 1e-300)
        dd = np.where(good, det, 1.0)
        s = (a22 * b1 - a12 * b2) / dd
        t = (a11 * b2 - a12 * b1) / dd
        good &= (s >= 0) & (t >= 0) & (s + t <= 1)
        q = a + s[:, None] * e1 + t[:, None] * e2
        cands_d.append(np.where(good, np.linalg.norm(p - q, axis=1), np.inf))
        ww = np.zeros((n, 4))
        ww[:, i] = 1 - s - t
        ww[:, j] += s
        ww[:, k] += t
        cands_w.append(np.where(good[:, None], ww, 0.0))
    Dm = np.stack(cands_d, axis=1)
    best = np.argmin(Dm, axis=1)
    Wm = np.stack(cands_w, axis=1)
    return Dm[np.arange(n), best], Wm[np.arange(n), best]


def _closest_point_triangles(p, a, b, c):
    """Closest points on triangles (Ericson, "Real-Time Collision Detection", 5.1.5), vectorized.

    Parameters
    ----------
    p, a, b, c : (n,3) array_like
        Query points and triangle corners, scene units.

    Returns
    -------
    distance : (n,) float64 ndarray
    bary : (n,3) float64 ndarray
        Weights of ``a, b, c`` at the closest point.
    """
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = (ab * ap).sum(1), (ac * ap).sum(1)
    bp = p - b
    d3, d4 = (ab * bp).sum(1), (ac * bp).sum(1)
    cp = p - c
    d5, d6 = (ab * cp).sum(1), (ac * cp).sum(1)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    n = len(p)
    w = np.zeros((n, 3))
    done = np.zeros(n, dtype=bool)

    def put(mask, wa, wb, wc):
        m = mask & ~done
        w[m, 0], w[m, 1], w[m, 2] = wa[m] if np.ndim(wa) else wa, wb[m] if np.ndim(wb) else wb, wc[m] if np.ndim(wc) else wc
        done[m] = True

    with np.errstate(divide="ignore", invalid="ignore"):
        put((d1 <= 0) & (d2 <= 0), 1.0, 0.0, 0.0)
        put((d3 >= 0) & (d4 <= d3), 0.0, 1.0, 0.0)
        t = np.nan_to_num(d1 / (d1 - d3))
        put((vc <= 0) & (d1 >= 0) & (d3 <= 0), 1 - t, t, 0.0)
        put((d6 >= 0) & (d5 <= d6), 0.0, 0.0, 1.0)
        t = np.nan_to_num(d2 / (d2 - d6))
        put((vb <= 0) & (d2 >= 0) & (d6 <= 0), 1 - t, 0.0, t)
        t = np.nan_to_num((d4 - d3) / ((d4 - d3) + (d5 - d6)))
        put((va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0), 0.0, 1 - t, t)
        den = va + vb + vc
        v = np.nan_to_num(vb / den)
        ww = np.nan_to_num(vc / den)
        put(np.ones(n, dtype=bool), 1 - v - ww, v, ww)
    w = np.clip(w, 0.0, 1.0)
    w /= np.maximum(w.sum(1, keepdims=True), 1e-300)
    x = w[:, :1] * a + w[:, 1:2] * b + w[:, 2:] * c
    return np.linalg.norm(p - x, axis=1), w


_BLAS = []


def _one_blas_thread():
    """Context limiting BLAS to one thread: per frame, multithreaded BLAS only spins (measured: frames 2x
    slower on a busy machine). A cached threadpoolctl controller (0.01 ms a call); no-op without it."""
    if not _BLAS:
        try:
            from threadpoolctl import ThreadpoolController

            _BLAS.append(ThreadpoolController())
        except Exception:  # optional dependency
            _BLAS.append(None)
    if _BLAS[0] is None:
        import contextlib

        return contextlib.nullcontext()
    return _BLAS[0].limit(limits=1, user_api="blas")


def _idle_core() -> bool:
    """True when the machine has an idle core (1-minute load average below ``cpu_count - 0.5``)."""
    import os

    try:
        return os.getloadavg()[0] < (os.cpu_count() or 1) - 0.5
    except (OSError, AttributeError):  # no load average (Windows): assume idle cores
        return True


def _ragged_arange(starts, counts):
    """Concatenation of ``arange(s, s + c)`` for every pair; and the group of each entry."""
    counts = np.asarray(counts, dtype=np.int64)
    tot = int(counts.sum())
    grp = np.repeat(np.arange(len(counts)), counts)
    if tot == 0:
        return np.zeros(0, dtype=np.int64), grp
    off = np.cumsum(counts) - counts
    idx = np.arange(tot, dtype=np.int64) - np.repeat(off, counts) + np.repeat(np.asarray(starts, np.int64), counts)
    return idx, grp


# --------------------------------------------------------------------------
# The indexer
# --------------------------------------------------------------------------


class GeometricIndexer:
    """Local geometric indexing of a shape dataset by surface-bound bundles.

    Build once per (mesh, dataset, bundle binding; about 3 s for 110 shapes
    and 100 bundles on the 26,719-vertex ICT face); :meth:`reconstruct` and
    :meth:`reconstruct_sequence` are then cheap (about 20 ms a frame on one
    core, 13.5-15 ms in a sequence on two; see ``benchmarks/geometric_indexing.py``).

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
        x0, F = validate_mesh(neutral, faces, name="neutral mesh")
        nv = len(x0)
        X = np.asarray(shapes, dtype=np.float64)
        if X.ndim != 3 or X.shape[1:] != (nv, 3):
            raise DatasetError(
                f"Dataset shapes must be an (S,V,3) array with V={nv} (the neutral's vertex count), got "
                f"{X.shape}; every shape key must come from the same mesh."
            )
        S = len(X)
        self.names = [str(n) for n in names] if names is not None else [f"shape {i}" for i in range(S)]
        if len(self.names) != S:
            raise DatasetError(f"{len(self.names)} names for {S} shapes; give one name per shape.")
        if S < 4:
            raise DatasetError(
                f"Local geometric indexing needs at least 4 dataset shapes, got {S}; add shape keys "
                "(expressions, in-betweens or combinations)."
            )
        bad = ~np.isfinite(X).all(axis=(1, 2))
        if bad.any():
            raise DatasetError(f"Dataset shapes {[self.names[i] for i in np.flatnonzero(bad)[:5]]} contain NaN; fix them.")
        bf = np.asarray(bundle_faces)
        bb = np.asarray(bundle_bary, dtype=np.float64)
        B = len(bf)
        if bf.ndim != 1 or B == 0 or not np.issubdtype(bf.dtype, np.integer):
            raise BundleError(f"bundle_faces must be a non-empty (B,) integer array, got {bf.shape} {bf.dtype}.")
        bf = bf.astype(np.int64)
        if bb.shape != (B, 3) or not np.isfinite(bb).all():
            raise BundleError(f"bundle_bary must be a finite (B,3)=({B},3) array, got {bb.shape}.")
        if bf.min() < 0 or bf.max() >= len(F):
            raise BundleError(
                f"A bundle is bound to triangle {int(bf.max()) if bf.max() >= len(F) else int(bf.min())} but the "
                f"mesh has {len(F)}; re-bind the bundles (bind_points) on this mesh."
            )
        if (bb < -1e-6).any() or np.abs(bb.sum(1) - 1) .max() > 1e-6:
            raise BundleError("Bundle barycentric coordinates must be non-negative and sum to 1; re-bind the bundles.")
        self.neutral, self.faces = x0, F
        self.bundle_faces, self.bundle_bary = bf, bb
        self.B, self.S, self.V = B, S, nv
        self.exact = bool(exact)
        self.threads = max(1, int(threads))
        self.bundle_names = None if bundle_names is None else [str(n) for n in bundle_names]

        # ---- jaw (Eq. 2): unskinned deltas b*
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

        # ---- natural-neighbour weights (§5)
        self.nn = natural_neighbor_weights(x0, F, bf, bb, uvs=uvs, method=nn_method)
        W = self.nn.weights.tocsr()
        W.sort_indices()
        dom = self.nn.domain
        lo, hi = x0[dom].min(axis=0), x0[dom].max(axis=0)
        self.face_size = float(np.linalg.norm(hi - lo))
        self.prune_tolerance = 1e-7 * self.face_size if prune_tolerance is None else float(prune_tolerance)
        self.temporal_bias = float(temporal_bias)
        self.tie_tolerance = 1e-5 * self.face_size if tie_tolerance is None else float(tie_tolerance)

        # ---- duplicates (shape vs shape, shape vs neutral)
        dup_tol = 1e-7 * self.face_size
        mags = np.linalg.norm(D, axis=2)  # (S,V)
        still = np.flatnonzero(mags.max(axis=1) <= dup_tol)
        if len(still):
            why = ("equals the neutral once the jaw motion is removed (the jaw rig alone reproduces it)"
                   if jaw is not None else "equals the neutral (moves nothing)")
            raise DatasetError(f"Dataset shape {self.names[still[0]]!r} {why}; remove it from the dataset.")
        self._check_duplicates(D, dup_tol)

        # dataset in a vertex-major layout, shape 0 = the neutral (zero delta)
        S1 = S + 1
        self.S1 = S1
        # only vertices that some shape moves are blended; float32 is ample for deltas (1e-7 relative)
        # (shape-major layout: a vertex run of one shape is contiguous, which keeps the gathers cached)
        self._active = np.flatnonzero(mags.max(axis=0) > 0)
        Dv = np.zeros((S1, len(self._active), 3), dtype=np.float32)
        Dv[1:] = D[:, self._active]
        self._Dact = Dv.reshape(-1, 3)
        del Dv

        # ---- point clouds (§4) in unskinned space: P_all (S1, B, 3)
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
        moved = move.max(axis=0)
        still_b = np.flatnonzero(moved <= dup_tol)
        if len(still_b):
            raise BundleError(
                f"{len(still_b)} bundles are not moved by any dataset shape ({_labels(self.bundle_names, still_b)}, for "
                "example on the back of the head or a rigid part); remove them, bind them on the moving face, or "
                "add shapes that move them."
            )
        # prune (§4.1): shapes that do not move the bundle's natural-neighbour region
        Wc = W.tocsc()
        region = np.zeros((S, B))
        for i in range(B):
            rows = Wc.indices[Wc.indptr[i] : Wc.indptr[i + 1]]
            ww = Wc.data[Wc.indptr[i] : Wc.indptr[i + 1]]
            if len(rows):
                region[:, i] = (mags[:, rows] * ww).max(axis=1)
        keep = (region > self.prune_tolerance) | (move > self.prune_tolerance)
        self._forbidden = self._parse_forbidden(forbidden)

        # ---- tetrahedra (§4, §4.1) per bundle, on merged points
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
                    f"{_labels(self.bundle_names, [i])} is not moved by any dataset shape by more than "
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
        self.tet_offsets = np.r_[0, np.cumsum(counts)].astype(np.int64)
        self.tet_bundle = np.repeat(np.arange(B), counts).astype(np.int32)
        Xt = P[self.tets, self.tet_bundle[:, None]]  # (N,4,3)
        inv = _tet_inverse(Xt)
        # float64 affine maps q -> (w1, w2, w3) (w0 = 1 - sum); NaN rows for flat tetrahedra
        self._tet_aff = np.concatenate([inv, -np.einsum("nij,nj->ni", inv, Xt[:, 0])[:, :, None]], axis=2)
        self._tet_flat = ~np.isfinite(inv).all(axis=(1, 2))
        del inv
        # float32 boxes rounded outwards, so a box always holds its tetrahedron
        self._tet_lo = np.nextafter(Xt.min(axis=1).astype(np.float32), np.float32(-np.inf))
        self._tet_hi = np.nextafter(Xt.max(axis=1).astype(np.float32), np.float32(np.inf))
        del Xt

        # ---- uniform grid per bundle ([18, 32])
        self.grid_density = float(grid_density)
        self._build_grid()

        # ---- neighbours (natural neighbours, §5.1)
        Nb = self.nn.neighbors.tocsr()
        R = Nb.copy()
        for _ in range(int(neighbor_rings) - 1):
            R = ((R + R @ Nb) > 0).astype(np.float64)
        R = R.tolil()
        R.setdiag(0)
        Nb = sp.csr_matrix(R)
        Nb.eliminate_zeros()
        Nb.sort_indices()
        self._nbr_ptr, self._nbr_idx = Nb.indptr.astype(np.int64), Nb.indices.astype(np.int64)
        self._deg = np.diff(self._nbr_ptr)
        # every cloud point with every neighbour of its bundle: the neighbours' positions on that shape
        pos, g = _ragged_arange(self._nbr_ptr[self._cloud_bundle], self._deg[self._cloud_bundle])
        self._pp_point, self._pp_nbr = g, self._nbr_idx[pos]
        self._pp_pos = P[self._cloud_shape[g], self._pp_nbr]
        self._pp_off = np.r_[0, np.cumsum(self._deg[self._cloud_bundle])]
        # merged points: the representative key of every cloud point, and the points of multi-member keys
        rep_of = np.zeros(len(self._cloud_shape), dtype=np.int64)
        for i in range(B):
            lo_, hi_ = self._cloud_off[i], self._cloud_off[i + 1]
            rep_of[lo_:hi_] = i * S1 + self.cloud_shapes[i][self._cloud_rep_local[i]]
        self._pt_key = rep_of
        multi = np.zeros(B * S1, dtype=bool)
        multi[self._multi_keys] = True
        self._multi_pts = np.flatnonzero(multi[rep_of])

        # ---- the blend: W restricted to the moving vertices, in row blocks (one per thread)
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
        self.last = {}
        self._pool = ThreadPoolExecutor(self.threads) if self.threads > 1 else None

    # ------------------------------------------------------------------ build helpers

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

    def _check_duplicates(self, D, tol):
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

    def _parse_forbidden(self, forbidden):
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
            L = np.max([np.linalg.norm(Xc[:, a] - Xc[:, b], axis=1) for a, b in _EDGES], axis=0)
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

    def _build_grid(self):
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

    # ------------------------------------------------------------------ per-frame steps

    def _check_bundles(self, q, what="bundles"):
        q = np.asarray(q, dtype=np.float64)
        if q.shape != (self.B, 3):
            raise BundleError(f"Expected {what} as a ({self.B},3) array (one row per bound bundle), got {q.shape}.")
        bad = ~np.isfinite(q).all(axis=1)
        if bad.any():
            raise BundleError(
                f"{int(bad.sum())} bundles have NaN positions ({_labels(self.bundle_names, np.flatnonzero(bad))}); "
                "skip the frame or fill the track gaps."
            )
        return q

    def unskinned_bundles(self, q, jaw=None):
        """Bundle positions with the jaw motion removed (Eq. 2), scene units, (B,3)."""
        if self.jaw is None:
            return q
        if jaw is None:
            raise BundleError("This indexer has a jaw rig; pass the frame's jaw parameters (angle, tx, ty, tz).")
        return self.jaw.unskin(q, jaw, self.bundle_jaw_weights)

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
        q = np.asarray(q, dtype=np.float64)
        B, S1 = self.B, self.S1
        # --- candidates: tetrahedra holding the bundle (grid, float32 screen, exact float64 weights)
        rel = (q - self._grid_lo) / self._grid_h
        cidx = np.floor(rel).astype(np.int64)
        inbox = ((cidx >= 0) & (cidx < self._grid_n)).all(axis=1)
        cidx = np.clip(cidx, 0, self._grid_n - 1)
        cell = self._grid_base + (cidx[:, 2] * self._grid_n[:, 1] + cidx[:, 1]) * self._grid_n[:, 0] + cidx[:, 0]
        s0 = self._cell_start[cell]
        cnt = np.where(inbox, self._cell_start[cell + 1] - s0, 0)
        pos, bund = _ragged_arange(s0, cnt)
        cand = self._cell_tets[pos]
        # box screen (float32 boxes rounded outwards), then the exact float64 affine maps of the survivors
        q32 = q.astype(np.float32)
        qb = q32[bund]
        ok = ((self._tet_lo[cand] <= qb) & (qb <= self._tet_hi[cand])).all(axis=1)
        cand, bund = cand[ok], bund[ok]
        tid = self.tets[cand].astype(np.int64)
        w3 = np.einsum("nij,nj->ni", self._tet_aff[cand], np.c_[q, np.ones(B)][bund])
        w = np.column_stack([1 - w3.sum(1), w3])
        inside = (w >= -1e-9).all(axis=1)
        bund, tid, w = bund[inside], tid[inside], np.clip(w[inside], 0.0, None)
        w /= np.maximum(w.sum(axis=1, keepdims=True), 1e-300)
        # a candidate at a single cloud point is that point's candidate below
        single = (w > 1 - 1e-9).any(axis=1)
        bund, tid, w = bund[~single], tid[~single], w[~single]
        dist = np.zeros(B)
        dp = np.linalg.norm(self._cloud_pos - q[self._cloud_bundle], axis=1)
        near = dp <= self.merge_tolerance
        has = np.zeros(B, dtype=bool)
        has[bund] = True
        has[self._cloud_bundle[near]] = True
        miss = np.flatnonzero(~has)
        if len(miss):
            pb, pt, pw, pd = self._project_hull(miss, q)
            dist[miss] = pd
            one = (pw > 1 - 1e-9).any(axis=1)
            # projections onto a cloud point become that point's candidate
            top = pt[np.arange(len(pt)), np.argmax(pw, axis=1)]
            key = pb[one] * S1 + top[one]
            near |= np.isin(self._pt_key, np.unique(key))
            bund, tid, w = np.r_[bund, pb[~one]], np.vstack([tid, pt[~one]]), np.vstack([w, pw[~one]])
        # --- cloud points that may be used alone or as members of merged points: their own cost (§5.1)
        need = np.zeros(B * S1, dtype=bool)
        need[(bund[:, None] * S1 + tid)[w > 0]] = True
        mp = self._multi_pts
        pts = np.union1d(mp[need[self._pt_key[mp]]], np.flatnonzero(near))
        pc = self._point_costs(q, prev, pts)
        ids, bary, cost = self._select(q, prev, None, bund, tid, w, pc, near)
        # Ties: where the neighbours cannot tell candidates apart (best cost below tie_tolerance), prefer
        # the shapes that the moving bundles chose (each bundle votes with its motion from the neutral).
        amb = cost <= self.tie_tolerance
        if amb.any() and self.tie_tolerance > 0:
            motion = np.linalg.norm(q - self.points_all[0], axis=1)
            vote = np.bincount(ids.ravel(), weights=(bary * motion[:, None]).ravel(), minlength=S1)
            vote[0] = 0.0
            if vote.max() > 0:
                vote /= vote.max()
            vote[0] = 0.5  # the neutral beats shapes no moving bundle chose (the least assumption)
            pc2 = pc + self.tie_tolerance * (1.0 - vote[self._cloud_shape])
            sel = amb[bund]
            ids2, bary2, _ = self._select(q, prev, vote, bund[sel], tid[sel], w[sel], pc2, near & amb[self._cloud_bundle])
            ids[amb], bary[amb] = ids2[amb], bary2[amb]
        return ids, bary, dist

    def _point_costs(self, q, prev, pts):
        """(P,) cost of cloud points ``pts`` used alone: neighbour RMS distance (+ temporal term), scene
        units; ``inf`` for the other points."""
        c = np.full(len(self._cloud_shape), np.inf)
        if len(pts) == 0:
            return c
        pos, g = _ragged_arange(self._pp_off[pts], self._pp_off[pts + 1] - self._pp_off[pts])
        e = ((self._pp_pos[pos] - q[self._pp_nbr[pos]]) ** 2).sum(axis=1)
        cp = np.sqrt(np.bincount(g, weights=e, minlength=len(pts)) / np.maximum(self._deg[self._cloud_bundle[pts]], 1))
        if prev is not None:
            pv = np.asarray(prev)[self._cloud_bundle[pts]]
            cp = cp * (1.0 + self.temporal_bias * ~(pv == self._cloud_shape[pts][:, None]).any(axis=1))
        c[pts] = cp
        return c

    def _select(self, q, prev, vote, bund, tid, w, pc, near):
        """Best candidate per bundle among tetrahedra (bund, tid, w) and the cloud points flagged ``near``.

        Merged points in tetrahedra are replaced by their best member (lowest
        point cost). Returns (B,4) shapes, (B,4) weights and (B,) costs.
        """
        B, S1 = self.B, self.S1
        sub = np.tile(np.arange(S1, dtype=np.int64), B)
        mp = self._multi_pts
        mp = mp[np.isfinite(pc[mp])]  # members without a cost keep their representative (the default)
        if len(mp):
            o = np.lexsort((pc[mp], self._pt_key[mp]))
            k = self._pt_key[mp][o]
            first = o[np.r_[True, k[1:] != k[:-1]]]
            sub[self._pt_key[mp][first]] = self._cloud_shape[mp][first]
        tid = sub[bund[:, None] * S1 + tid]
        c_t = self._neighbor_cost(bund, tid, w, q, prev, vote) if len(bund) else np.zeros(0)
        npt = np.flatnonzero(near)
        ids = np.zeros((B, 4), dtype=np.int64)
        bary = np.zeros((B, 4))
        best = np.full(B, np.inf)
        # cloud points first (a tetrahedron must be strictly better to win)
        if len(npt):
            o = np.lexsort((pc[npt], self._cloud_bundle[npt]))
            bb_ = self._cloud_bundle[npt][o]
            first = o[np.r_[True, bb_[1:] != bb_[:-1]]]
            b_ = self._cloud_bundle[npt][first]
            best[b_] = pc[npt][first]
            ids[b_] = self._cloud_shape[npt][first][:, None]
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
        deg = self._deg[bund]
        pos, c = _ragged_arange(self._nbr_ptr[bund], deg)
        j = self._nbr_idx[pos]
        s = np.einsum("nk,nkx->nx", w[c], self.points_all[tet_ids[c], j[:, None]])
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
        a, b = self._hull_off[miss], self._hull_off[miss + 1]
        pos, grp = _ragged_arange(a, b - a)
        bm = miss[grp]
        qq = q[bm]
        eq = self._hull_eq[pos]
        out = np.full(len(miss), -np.inf)
        np.maximum.at(out, grp, (eq[:, :3] * qq).sum(1) + eq[:, 3])
        tri = self._hull_tri[pos]
        X = self.points_all[tri, bm[:, None]]
        d, w3 = _closest_point_triangles(qq, X[:, 0], X[:, 1], X[:, 2])
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
        a, b = self.tet_offsets[miss], self.tet_offsets[miss + 1]
        pos, grp = _ragged_arange(a, b - a)
        qq = q[miss][grp]
        # lower bound: distance to each tetrahedron's box; upper bound: distance to the nearest cloud point
        lb = np.linalg.norm(np.maximum(np.maximum(self._tet_lo[pos] - qq, qq - self._tet_hi[pos]), 0.0), axis=1)
        ub = np.full(len(miss), np.inf)
        for k, i in enumerate(miss):
            ub[k] = np.linalg.norm(self.points_all[self.cloud_reps[i], i] - q[i], axis=1).min()
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
        tid_all = self.tets[pos].astype(np.int64)
        lim = 16
        while True:
            todo = ~done & (rank < lim) & (lb <= dmin[grp] * (1 + 1e-9) + 1e-12 * self.face_size)
            if not todo.any():
                if not (~done & (lb <= dmin[grp] * (1 + 1e-9) + 1e-12 * self.face_size)).any():
                    break
                lim *= 4
                continue
            t = np.flatnonzero(todo)
            Xt = self.points_all[tid_all[t], miss[grp[t]][:, None]]
            d_all[t], w_all[t] = closest_point_tetrahedron(qq[t], Xt)
            done[t] = True
            np.minimum.at(dmin, grp[t], d_all[t])
            lim *= 2
        tie = done & (d_all <= dmin[grp] * (1 + 1e-9) + 1e-12 * self.face_size)
        tid, w = tid_all, w_all
        return miss[grp[tie]], tid[tie], w[tie], dmin

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
        if self._pool is not None and len(self._w_parts) > 1 and _idle_core():
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

    # ------------------------------------------------------------------ public reconstruction

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
        with _one_blas_thread():
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
        with _one_blas_thread():  # BLAS threads would spin against the pipeline's own threads
            return self._reconstruct_sequence(bundles, jaw, smooth, exact, progress, pipeline)

    def _reconstruct_sequence(self, bundles, jaw, smooth, exact, progress, pipeline):
        Q = np.asarray(bundles, dtype=np.float64)
        if Q.ndim != 3 or Q.shape[1:] != (self.B, 3):
            raise BundleError(f"Expected bundles as a (T,{self.B},3) array, got {Q.shape}.")
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
        out = np.full((T, self.V, 3), np.nan)
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
            out[t] = self._finish(Xu, target, J[t], ex)
            for s in [s for s in deltas if s <= t - half and s not in in_sum]:
                del deltas[s]
                q_unskinned.pop(s, None)

        # Two-stage pipeline: frames are indexed in order on this thread while a worker blends each indexed
        # frame and finishes every frame whose smoothing window is complete (one worker: FIFO order).
        if pipeline == "auto":
            pipeline = _idle_core()
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
        return out, skipped

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


# --------------------------------------------------------------------------
# Baseline: blendshape fit with soft [0, 1] bounds (§7, Fig. 4 middle)
# --------------------------------------------------------------------------


class BlendshapeFit:
    """Dataset shapes as a linear blendshape rig fit to the bundles (§7 baseline).

    Minimises ``|A w - r|^2 + mu sum_s (min(w_s, 0)^2 + max(w_s - 1, 0)^2)
    + ridge |w|^2``, with ``A`` the bundles' motion on every shape (scene
    units) and ``r = bundles - neutral bundles``: the paper's "Euclidean
    distances from the bundles to their surface points subject to a soft
    constraint that penalizes the weights to lie between 0 and 1". Solved by
    a semismooth Newton iteration over the active bounds (exact for this
    piecewise quadratic, usually 3-6 steps).

    Parameters
    ----------
    neutral : (V,3) array_like
    faces : (F,3) int array_like
    shapes : (S,V,3) array_like
        Positions of the dataset shapes, scene units.
    bundle_faces : (B,) int array_like
    bundle_bary : (B,3) array_like
    bound_weight : float
        ``mu`` relative to the mean diagonal of ``A^T A``.
    ridge : float
        Tikhonov weight relative to the mean diagonal of ``A^T A`` (keeps
        shapes that no bundle sees at 0).
    """

    def __init__(self, neutral, faces, shapes, bundle_faces, bundle_bary, *, bound_weight: float = 1.0,
                 ridge: float = 1e-6):
        x0 = np.asarray(neutral, dtype=np.float64)
        X = np.asarray(shapes, dtype=np.float64)
        self.neutral = x0
        self.deltas = X - x0
        p0 = surface_points(x0, faces, bundle_faces, bundle_bary)
        P = surface_points(X, faces, bundle_faces, bundle_bary)  # (S,B,3)
        self.p0 = p0
        self.A = (P - p0).reshape(len(X), -1).T  # (3B, S)
        self.AtA = self.A.T @ self.A
        s = float(np.mean(np.diag(self.AtA)))
        self.mu = bound_weight * s
        self.ridge = ridge * s

    def weights(self, bundles, iterations: int = 30):
        """(S,) blendshape weights for one frame of bundles (B,3), unitless."""
        r = (np.asarray(bundles, dtype=np.float64) - self.p0).ravel()
        Atr = self.A.T @ r
        S = self.AtA.shape[0]
        H0 = self.AtA + self.ridge * np.eye(S)
        w = np.linalg.solve(H0, Atr)
        for _ in range(iterations):
            low, high = w < 0, w > 1
            act = (low | high).astype(np.float64)
            H = H0 + self.mu * np.diag(act)
            w_new = np.linalg.solve(H, Atr + self.mu * high)
            if np.array_equal(w_new < 0, low) and np.array_equal(w_new > 1, high):
                return w_new
            w = w_new
        return w

    def reconstruct(self, bundles):
        """(V,3) vertices ``x0 + sum_s w_s b_s`` for one frame of bundles, scene units."""
        w = self.weights(bundles)
        return self.neutral + np.tensordot(w, self.deltas, axes=1)


# --------------------------------------------------------------------------
# Actor-specific shapes and correctives (§7, Fig. 7)
# --------------------------------------------------------------------------


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
    hold comes out worse than the plain linear combination (measured in
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
    **indexer_options
        Passed to :class:`GeometricIndexer`.

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
                 bundle_faces=None, bundle_bary=None, n_bundles: int = 100, uvs=None, **indexer_options):
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
        self.indexer = GeometricIndexer(x0, F, L[keep], bundle_faces, bundle_bary, names=self.dataset_names, uvs=uvs,
                                        **{"threads": 1, "exact": False, **indexer_options})
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
        gi = self.indexer
        lin = self.linear(weights)
        q = surface_points(lin, self.faces, gi.bundle_faces, gi.bundle_bary)
        ids, bary, dist = gi.locate(q)
        Beta = sp.csr_matrix((bary.ravel(), (np.repeat(np.arange(gi.B), 4), ids.ravel())), shape=(gi.B, gi.S1))
        C = (gi.W @ Beta).tocsc()
        out = np.zeros_like(self.neutral)
        for s in np.flatnonzero(np.diff(C.indptr)[1:]) + 1:
            rows = C.indices[C.indptr[s] : C.indptr[s + 1]]
            out[rows] += C.data[C.indptr[s] : C.indptr[s + 1], None] * self._R[s, rows]
        used = np.bincount(ids.ravel(), weights=bary.ravel(), minlength=gi.S1)[1:]
        order = np.argsort(-used)
        info = {"projected": int((dist > 0).sum()),
                "shapes": [(self.dataset_names[k], float(used[k] / gi.B)) for k in order[:5] if used[k] > 0]}
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
