"""Eyeball spheres and the projection of tracked eyelid curves onto them.

Bhat et al. 2013, "High Fidelity Facial Animation Capture and Retargeting
With Contours", §4.1 "Fitting 3D eyelid curves": eyelids slide on the
cornea, a relatively rigid object, so a tracked 2D eyelid curve is projected
from its camera onto the cornea to obtain a 3D curve, which is then fitted
with the 3D point constraint (Eq. 2).

The cornea/eyeball is modelled as a sphere fitted (linear least squares) to
the eyeball geometry of the rig: on ICT-FaceKit the ``M_ScleraLeft`` /
``M_ScleraRight`` parts (radius about 1.58 cm). A pixel's camera ray is
intersected with the sphere; the first hit (closest to the camera) is the 3D
eyelid point. Rays that miss the sphere (the curve's pixel lies outside the
eyeball's image) get the point of the sphere closest to the ray, and are
reported in the ``hit`` mask.

Conventions: scene units for positions and radii, pixels top-left origin and
y down, cameras as in :mod:`facelab_addon.core.capture.camera`. NumPy only.
"""

from __future__ import annotations

import numpy as np

from ..errors import FaceLabError

__all__ = ["fit_sphere", "ray_sphere", "project_to_sphere"]


def fit_sphere(points):
    """Least-squares sphere through points.

    Solves ``|p|^2 = 2 c . p + (r^2 - |c|^2)`` linearly for the centre ``c``
    and radius ``r`` (the algebraic fit; for points spread over a large part
    of a sphere it equals the geometric fit to within noise).

    Parameters
    ----------
    points : (n,3) array_like
        Points on (or near) the sphere, scene units; ``n >= 4``, not coplanar.

    Returns
    -------
    center : (3,) float64
        Scene units.
    radius : float
        Scene units.

    Raises
    ------
    FaceLabError
        With fewer than 4 points or coplanar points.
    """
    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(P) < 4 or not np.isfinite(P).all():
        raise FaceLabError(
            f"Fitting an eyeball sphere needs at least 4 finite points, got {len(P)}; "
            "pass the eyeball (sclera) vertices of the rig."
        )
    m = P.mean(axis=0)
    Q = P - m  # centred for conditioning
    A = np.empty((len(Q), 4))
    A[:, :3] = 2.0 * Q
    A[:, 3] = 1.0
    b = (Q**2).sum(axis=1)
    # normal equations (4x4): conditioned by the centring, much cheaper than an SVD for per-frame refits
    N = A.T @ A
    ev = np.linalg.eigvalsh(N)
    rank = int((ev > 1e-12 * max(ev[-1], 1e-300)).sum())
    if rank == 4:
        x = np.linalg.solve(N, A.T @ b)
    if rank < 4:
        raise FaceLabError(
            "The eyeball points are coplanar, so no sphere fits them; pass the vertices of the eyeball "
            "surface (for ICT-FaceKit the M_ScleraLeft / M_ScleraRight parts)."
        )
    c = x[:3]
    r2 = x[3] + c @ c
    if not r2 > 0:
        raise FaceLabError("The eyeball points do not describe a sphere; check the eyeball vertices.")
    return c + m, float(np.sqrt(r2))


def ray_sphere(origins, dirs, center, radius):
    """First intersection of rays with a sphere.

    Parameters
    ----------
    origins : (n,3) array_like
        Ray origins, scene units (outside the sphere).
    dirs : (n,3) array_like
        Ray directions (need not be unit length).
    center : (3,) array_like
        Sphere centre, scene units.
    radius : float or (n,) array_like
        Sphere radius, scene units (one per ray: concentric spheres).

    Returns
    -------
    points : (n,3) float64
        The intersection closest to the origin in front of it; for rays that
        miss, the point of the sphere closest to the ray.
    hit : (n,) bool
        Whether the ray really meets the sphere.
    """
    O = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    D = np.asarray(dirs, dtype=np.float64).reshape(-1, 3)
    D = D / np.linalg.norm(D, axis=1, keepdims=True)
    c = np.asarray(center, dtype=np.float64).reshape(3)
    radius = np.broadcast_to(np.asarray(radius, dtype=np.float64), (len(O),))
    oc = O - c
    b = np.einsum("ij,ij->i", oc, D)
    q = np.einsum("ij,ij->i", oc, oc) - radius * radius
    disc = b * b - q
    hit = disc >= 0
    s = -b - np.sqrt(np.maximum(disc, 0.0))
    inside = q < 0  # origin inside the sphere: take the exit point
    s = np.where(inside, -b + np.sqrt(np.maximum(disc, 0.0)), s)
    hit &= s > 0
    X = O + s[:, None] * D
    if not hit.all():
        # closest point of the sphere to the ray: foot of the centre on the ray, pushed to the surface
        t = np.maximum(-b, 0.0)
        foot = O + t[:, None] * D
        u = foot - c
        n = np.linalg.norm(u, axis=1, keepdims=True)
        u = np.where(n > 1e-300, u / np.maximum(n, 1e-300), -D)
        X = np.where(hit[:, None], X, c + radius[:, None] * u)
    return X, hit


def project_to_sphere(camera, pixels, center, radius):
    """Project pixels from a camera onto a sphere (a tracked eyelid curve onto the cornea).

    Parameters
    ----------
    camera : Camera
    pixels : (n,2) array_like
        Pixel coordinates, top-left origin, y down.
    center : (3,) array_like
        Sphere centre, scene units.
    radius : float or (n,) array_like
        Sphere radius, scene units (or one per pixel).

    Returns
    -------
    points : (n,3) float64
        3D points on the sphere, scene units (first hit from the camera).
    hit : (n,) bool
        False where the pixel's ray misses the sphere (the point is then the
        sphere point closest to the ray).
    """
    px = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    K = camera.K  # upper triangular, K[2,2] == 1: back-substitute (no LAPACK call per curve)
    y = (px[:, 1] - K[1, 2]) / K[1, 1]
    x = (px[:, 0] - K[0, 2] - K[0, 1] * y) / K[0, 0]
    d_cam = np.stack([x, y, np.ones_like(x)], axis=1)
    D = d_cam @ camera.R  # camera -> world directions
    O = np.broadcast_to(camera.center, D.shape)
    return ray_sphere(O, D, center, radius)
