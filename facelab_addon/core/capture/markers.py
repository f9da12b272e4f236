"""Markers and bundles bound to the mesh surface (Bhat et al. 2013, §4.1).

"A point x on the mesh surface is represented using barycentric coordinates:
x = AV" -- every painted dot is tied once, on a reference frame, to a point
inside a triangle of the neutral (or reference) mesh, and from then on
follows the skin: ``x = b0 v_i + b1 v_j + b2 v_k`` for any deformation of the
mesh. This module finds those bindings:

* :func:`bind_surface_points` casts the camera ray through each tracked
  pixel and keeps the first (closest to the camera) triangle it hits -- the
  2D markers of a movie-clip track;
* :func:`nearest_surface_points` takes the closest surface point to each 3D
  point -- the 3D bundles of a tracking reconstruction or empties.

Both are vectorised NumPy: the ray cast culls triangles by their image-space
bounding box (exact for rays that all start at the camera centre) and runs
the Moller-Trumbore test only on the candidates, so a few hundred rays
against the 52k ICT triangles take a few tens of milliseconds.

Conventions: vertices (V,3) float64 scene units, triangles (F,3) int64,
pixels top-left origin with y down (``camera.Camera``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import FaceLabError, UsageError
from ..geometry.mesh import validate_mesh
from .camera import Camera

__all__ = ["SurfacePoints", "bind_surface_points", "nearest_surface_points", "ray_triangle_hits"]


@dataclass
class SurfacePoints:
    """Points bound to the mesh surface by barycentric coordinates.

    Attributes
    ----------
    vertices : (m,3) int64
        Triangle vertex ids of each point; ``-1`` rows are unbound (a ray that
        missed the mesh).
    bary : (m,3) float64
        Barycentric weights (sum 1) of each point in its triangle.
    """

    vertices: np.ndarray
    bary: np.ndarray

    def __post_init__(self):
        v, b = np.asarray(self.vertices), np.asarray(self.bary)
        if v.size % 3 or b.size % 3 or (v.size and not np.issubdtype(v.dtype, np.integer)):
            raise UsageError(f"SurfacePoints: vertices must be (m,3) integer vertex ids and bary (m,3) weights, got "
                             f"{v.dtype} {v.shape} and {b.shape}; give three vertices and weights per point")
        self.vertices = v.astype(np.int64).reshape(-1, 3)
        self.bary = b.astype(np.float64).reshape(-1, 3)
        if self.bary.shape != self.vertices.shape:
            raise UsageError("SurfacePoints: bary must have the shape of vertices (m,3); give three weights per point")

    def __len__(self) -> int:
        return len(self.vertices)

    @property
    def bound(self) -> np.ndarray:
        """(m,) bool: points tied to a triangle (``vertices >= 0``)."""
        return (self.vertices >= 0).all(axis=1)

    def subset(self, idx) -> "SurfacePoints":
        """The points ``idx`` (mask or indices) as a new ``SurfacePoints``."""
        return SurfacePoints(self.vertices[idx], self.bary[idx])

    def evaluate(self, V) -> np.ndarray:
        """Positions of the points on a mesh or a sequence of meshes.

        Parameters
        ----------
        V : (V,3) or (T,V,3) float
            Vertices, scene units.

        Returns
        -------
        (m,3) or (T,m,3) float64
            Surface points; NaN for unbound rows.
        """
        V = np.asarray(V, dtype=np.float64)
        vid = np.maximum(self.vertices, 0)
        if V.ndim == 2:
            out = np.einsum("mk,mkd->md", self.bary, V[vid])
        elif V.ndim == 3:
            out = np.einsum("mk,tmkd->tmd", self.bary, V[:, vid])
        else:
            raise FaceLabError(f"Expected vertices of shape (V,3) or (T,V,3), got {V.shape}.")
        out[..., ~self.bound, :] = np.nan
        return out

    def matrix(self, n_vertices: int):
        """(m, V) sparse matrix ``A`` with ``x = A @ V`` (unbound rows are zero)."""
        import scipy.sparse as sp

        ok = self.bound
        rows = np.repeat(np.flatnonzero(ok), 3)
        return sp.csr_matrix(
            (self.bary[ok].ravel(), (rows, self.vertices[ok].ravel())), shape=(len(self), int(n_vertices))
        )


def ray_triangle_hits(origins, dirs, tri_a, tri_b, tri_c, eps: float = 1e-12):
    """Moller-Trumbore ray/triangle test for matched pairs (vectorised).

    Parameters
    ----------
    origins, dirs : (n,3) float
        Ray origins and directions (any length; ``t`` is in units of ``|dir|``).
    tri_a, tri_b, tri_c : (n,3) float
        Triangle corners of each pair.
    eps : float
        Determinant threshold for rays parallel to the triangle plane.

    Returns
    -------
    t : (n,) float64
        Ray parameter of the hit (``origin + t dir``); ``inf`` where there is
        no hit with ``t > 0``.
    bary : (n,3) float64
        Barycentric weights ``(1-u-v, u, v)`` of the hit point.
    """
    e1 = tri_b - tri_a
    e2 = tri_c - tri_a
    p = np.cross(dirs, e2)
    det = np.einsum("ij,ij->i", e1, p)
    ok = np.abs(det) > eps * np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1) * np.linalg.norm(dirs, axis=1)
    inv = np.divide(1.0, det, out=np.zeros_like(det), where=ok)
    s = origins - tri_a
    u = np.einsum("ij,ij->i", s, p) * inv
    q = np.cross(s, e1)
    v = np.einsum("ij,ij->i", dirs, q) * inv
    t = np.einsum("ij,ij->i", e2, q) * inv
    tol = 1e-9
    hit = ok & (u >= -tol) & (v >= -tol) & (u + v <= 1.0 + tol) & (t > 0)
    t = np.where(hit, t, np.inf)
    bary = np.stack([1.0 - u - v, u, v], axis=1)
    return t, bary


def bind_surface_points(vertices, faces, camera: Camera, pixels, *, face_mask=None, chunk: int = 64):
    """Tie tracked pixels to the mesh: the first surface hit of each camera ray.

    Parameters
    ----------
    vertices : (V,3) float
        The mesh on the reference frame, scene units.
    faces : (F,3) int
        Triangles.
    camera : Camera
        The calibrated camera the pixels were tracked in.
    pixels : (m,2) float
        Marker positions in that camera on the reference frame (top-left
        origin, y down). NaN rows (not tracked on this frame) miss.
    face_mask : (F,) bool, optional
        Only these triangles can be hit (for example: skin only, no eyes or
        teeth). Occlusion is tested against these triangles only.
    chunk : int
        Rays tested at once (memory: ``chunk * F`` booleans).

    Returns
    -------
    points : SurfacePoints
        ``m`` bound points; rows that missed have ``vertices = -1`` and zero
        barycentrics.
    hit : (m,) bool
        Which rays hit the mesh.
    """
    V, F = validate_mesh(vertices, faces)
    px = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    m = len(px)
    tri_ids = np.arange(len(F)) if face_mask is None else np.flatnonzero(np.asarray(face_mask, bool))
    Ft = F[tri_ids]
    # image-space bounding boxes; triangles touching the camera plane are always candidates
    depth = camera.depth(V)
    P = camera.project(V)
    behind = (depth[Ft] <= 1e-12 * max(1.0, float(np.abs(depth).max()))).any(axis=1)
    Pt = P[Ft]  # (F,3,2)
    lo = np.where(behind[:, None], -np.inf, Pt.min(axis=1))
    hi = np.where(behind[:, None], np.inf, Pt.max(axis=1))
    visible = ~(depth[Ft] <= 0).all(axis=1)  # entirely behind the camera: never hit
    lo, hi, Ft_ids = lo[visible], hi[visible], tri_ids[visible]
    origins, dirs = camera.rays(np.nan_to_num(px))
    good = np.isfinite(px).all(axis=1)
    out_v = -np.ones((m, 3), np.int64)
    out_b = np.zeros((m, 3))
    hit = np.zeros(m, bool)
    slack = 1e-6 * max(camera.width, camera.height)
    for s in range(0, m, max(1, int(chunk))):
        sl = np.arange(s, min(m, s + chunk))
        sl = sl[good[sl]]
        if len(sl) == 0:
            continue
        q = px[sl]
        inside = (
            (q[:, None, 0] >= lo[None, :, 0] - slack)
            & (q[:, None, 0] <= hi[None, :, 0] + slack)
            & (q[:, None, 1] >= lo[None, :, 1] - slack)
            & (q[:, None, 1] <= hi[None, :, 1] + slack)
        )
        ri, ci = np.nonzero(inside)
        if len(ri) == 0:
            continue
        tri = F[Ft_ids[ci]]
        t, bary = ray_triangle_hits(origins[sl[ri]], dirs[sl[ri]], V[tri[:, 0]], V[tri[:, 1]], V[tri[:, 2]])
        finite = np.isfinite(t)
        ri, ci, t, bary, tri = ri[finite], ci[finite], t[finite], bary[finite], tri[finite]
        if len(ri) == 0:
            continue
        order = np.lexsort((t, ri))  # closest hit first per ray
        ri, t, bary, tri = ri[order], t[order], bary[order], tri[order]
        first = np.r_[True, ri[1:] != ri[:-1]]
        rows = sl[ri[first]]
        out_v[rows] = tri[first]
        b = np.clip(bary[first], 0.0, None)
        out_b[rows] = b / b.sum(axis=1, keepdims=True)
        hit[rows] = True
    return SurfacePoints(out_v, out_b), hit


def _closest_bary(P, A, B, C):
    """Barycentric weights (n,3) of the closest point on triangles ABC to points P (Ericson 5.1.5)."""
    ab, ac, ap = B - A, C - A, P - A
    d1 = np.einsum("ij,ij->i", ab, ap)
    d2 = np.einsum("ij,ij->i", ac, ap)
    bp = P - B
    d3 = np.einsum("ij,ij->i", ab, bp)
    d4 = np.einsum("ij,ij->i", ac, bp)
    cp = P - C
    d5 = np.einsum("ij,ij->i", ab, cp)
    d6 = np.einsum("ij,ij->i", ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    n = len(P)
    out = np.zeros((n, 3))
    done = np.zeros(n, bool)

    def put(mask, b):
        nonlocal done
        mask = mask & ~done
        out[mask] = b[mask] if np.ndim(b) == 2 else b
        done |= mask

    with np.errstate(divide="ignore", invalid="ignore"):
        put((d1 <= 0) & (d2 <= 0), np.array([1.0, 0, 0]))
        put((d3 >= 0) & (d4 <= d3), np.array([0, 1.0, 0]))
        v = d1 / (d1 - d3)
        put((vc <= 0) & (d1 >= 0) & (d3 <= 0), np.stack([1 - v, v, 0 * v], 1))
        put((d6 >= 0) & (d5 <= d6), np.array([0, 0, 1.0]))
        w = d2 / (d2 - d6)
        put((vb <= 0) & (d2 >= 0) & (d6 <= 0), np.stack([1 - w, 0 * w, w], 1))
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        put((va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0), np.stack([0 * w, 1 - w, w], 1))
        den = va + vb + vc
        v = vb / den
        w = vc / den
        put(np.ones(n, bool), np.stack([1 - v - w, v, w], 1))
    return np.nan_to_num(out)


def nearest_surface_points(vertices, faces, points, *, face_mask=None) -> SurfacePoints:
    """Tie 3D points (bundles) to the closest point of the mesh surface.

    Parameters
    ----------
    vertices : (V,3) float
        The mesh on the reference frame, scene units.
    faces : (F,3) int
    points : (m,3) float
        Bundle positions on that frame, scene units; NaN rows stay unbound
        (``vertices = -1``).
    face_mask : (F,) bool, optional
        Only these triangles are candidates.

    Returns
    -------
    SurfacePoints
    """
    import igl

    V, F = validate_mesh(vertices, faces)
    X = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    tri_ids = np.arange(len(F)) if face_mask is None else np.flatnonzero(np.asarray(face_mask, bool))
    if len(tri_ids) == 0:
        raise FaceLabError("No triangles to bind the bundles to; the face mask is empty.")
    Ft = np.ascontiguousarray(F[tri_ids])
    good = np.isfinite(X).all(axis=1)
    out_v = -np.ones((len(X), 3), np.int64)
    out_b = np.zeros((len(X), 3))
    if good.any():
        _, fi, _ = igl.point_mesh_squared_distance(np.ascontiguousarray(X[good]), V, Ft)
        tri = Ft[np.asarray(fi, dtype=np.int64).ravel()]
        b = _closest_bary(X[good], V[tri[:, 0]], V[tri[:, 1]], V[tri[:, 2]])
        b = np.clip(b, 0.0, None)
        out_v[good] = tri
        out_b[good] = b / b.sum(axis=1, keepdims=True)
    return SurfacePoints(out_v, out_b)
