"""Pinhole camera in pixels (OpenCV convention).

Conventions
-----------
* A world point ``X`` (scene units) goes to camera coordinates
  ``x_c = R @ X + t``; the camera looks along ``+z`` (x right, y down).
* Pixels: continuous coordinates with the image's top-left *corner* at
  ``(0, 0)`` and the bottom-right corner at ``(width, height)``; x to the
  right, y down. The centre of pixel ``(i, j)`` is ``(i + 0.5, j + 0.5)``.
  This is exactly ``(u * width, (1 - v) * height)`` for Blender's normalised
  ``world_to_camera_view`` coordinates ``(u, v)``.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg

from ..errors import CameraError

__all__ = ["Camera"]


class Camera:
    """A calibrated pinhole camera.

    Parameters
    ----------
    K : (3,3) array_like
        Intrinsics in pixels: ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]``.
    R : (3,3) array_like
        World-to-camera rotation (orthonormal, det +1).
    t : (3,) array_like
        World-to-camera translation, scene units.
    width, height : int
        Image size in pixels.
    """

    def __init__(self, K, R, t, width, height):
        K = np.asarray(K, dtype=np.float64).reshape(3, 3)
        R = np.asarray(R, dtype=np.float64).reshape(3, 3)
        t = np.asarray(t, dtype=np.float64).reshape(3)
        if not (np.all(np.isfinite(K)) and np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
            raise CameraError("Camera has non-finite calibration values; re-calibrate or re-create the camera.")
        if abs(K[2, 2]) < 1e-12 or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise CameraError(
                "Camera intrinsics are degenerate (focal length must be positive); "
                "check the lens and sensor settings."
            )
        K = K / K[2, 2]
        if np.abs(R @ R.T - np.eye(3)).max() > 1e-6 or np.linalg.det(R) < 0:
            raise CameraError(
                "Camera rotation is not a proper rotation (scaled or mirrored camera?); "
                "apply scale to the camera object so it has unit scale."
            )
        if not (np.isfinite(width) and np.isfinite(height)) or int(width) <= 0 or int(height) <= 0:
            raise CameraError("Camera resolution must be positive; set the render resolution.")
        self.K = K
        self.R = R
        self.t = t
        self.width = int(width)
        self.height = int(height)

    # ------------------------------------------------------------------ props
    @property
    def center(self) -> np.ndarray:
        """(3,) camera centre in world coordinates, scene units."""
        return -self.R.T @ self.t

    @property
    def forward(self) -> np.ndarray:
        """(3,) unit viewing direction (camera +z) in world coordinates."""
        return self.R[2].copy()

    @property
    def P(self) -> np.ndarray:
        """(3,4) projection matrix ``K [R | t]``."""
        return self.K @ np.hstack([self.R, self.t[:, None]])

    # ---------------------------------------------------------------- methods
    def to_camera(self, X) -> np.ndarray:
        """World points ``(N,3)`` to camera coordinates ``(N,3)`` (scene units)."""
        X = np.asarray(X, dtype=np.float64)
        return X @ self.R.T + self.t

    def depth(self, X) -> np.ndarray:
        """Depth ``z`` along the viewing direction, ``(N,)`` scene units."""
        return self.to_camera(X)[..., 2]

    def project(self, X) -> np.ndarray:
        """Project world points.

        Parameters
        ----------
        X : (N,3) array_like
            World points, scene units.

        Returns
        -------
        (N,2) ndarray
            Pixel coordinates (top-left origin, y down). Points at or behind
            the camera plane give non-finite values.
        """
        xc = self.to_camera(X)
        uvw = xc @ self.K.T
        with np.errstate(divide="ignore", invalid="ignore"):
            return uvw[..., :2] / uvw[..., 2:3]

    def rays(self, px):
        """Back-project pixels to world rays.

        Parameters
        ----------
        px : (N,2) array_like
            Pixel coordinates.

        Returns
        -------
        origins : (N,3) ndarray
            The camera centre, repeated (scene units).
        dirs : (N,3) ndarray
            Unit ray directions in world coordinates (pointing away from the
            camera, into the scene).
        """
        px = np.asarray(px, dtype=np.float64).reshape(-1, 2)
        h = np.hstack([px, np.ones((len(px), 1))])
        d_cam = np.linalg.solve(self.K, h.T).T
        d = d_cam @ self.R  # == (R.T @ d_cam.T).T
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        return np.repeat(self.center[None], len(px), axis=0), d

    def in_frame(self, px, margin: float = 0.0) -> np.ndarray:
        """(N,) bool: which pixels lie inside the image (``margin`` px inset)."""
        px = np.asarray(px, dtype=np.float64).reshape(-1, 2)
        return (
            np.isfinite(px).all(axis=1)
            & (px[:, 0] >= margin)
            & (px[:, 0] <= self.width - margin)
            & (px[:, 1] >= margin)
            & (px[:, 1] <= self.height - margin)
        )

    @classmethod
    def from_projection(cls, P, width, height) -> "Camera":
        """Decompose a ``(3,4)`` projection matrix (any scale) into K, R, t.

        Parameters
        ----------
        P : (3,4) array_like
            ``s * K [R | t]`` for some non-zero scale ``s``.
        width, height : int
            Image size in pixels.
        """
        P = np.asarray(P, dtype=np.float64).reshape(3, 4)
        M = P[:, :3]
        if not np.all(np.isfinite(P)) or abs(np.linalg.det(M)) < 1e-12:
            raise CameraError("Projection matrix is singular or non-finite; re-calibrate the camera.")
        if np.linalg.det(M) < 0:
            P = -P
            M = P[:, :3]
        K, R = scipy.linalg.rq(M)
        S = np.diag(np.sign(np.diag(K)))
        K = K @ S
        R = S @ R
        if np.linalg.det(R) < 0:  # cannot happen with det(M) > 0, kept for safety
            R = -R
            K = -K
        t = np.linalg.solve(K, P[:, 3])
        return cls(K / K[2, 2], R, t, width, height)

    def __repr__(self) -> str:
        f = (self.K[0, 0], self.K[1, 1])
        return f"Camera(f={f[0]:.1f}x{f[1]:.1f}px, {self.width}x{self.height}, center={self.center.round(4).tolist()})"

    @classmethod
    def look_at(cls, eye, target, up, focal_mm, sensor_width_mm, width, height) -> "Camera":
        """Build a camera at ``eye`` looking at ``target`` (test and demo helper).

        Parameters
        ----------
        eye, target, up : (3,) array_like
            Camera position, point looked at, and world up (scene units).
        focal_mm, sensor_width_mm : float
            Lens and horizontal sensor size (mm), as in Blender.
        width, height : int
            Image size in pixels; square pixels, principal point at the centre.
        """
        eye = np.asarray(eye, float)
        z = np.asarray(target, float) - eye
        z /= np.linalg.norm(z)
        x = np.cross(z, np.asarray(up, float))  # camera x = right, y = down
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        R = np.stack([x, y, z])
        f = focal_mm / sensor_width_mm * width
        K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1.0]])
        return cls(K, R, -R @ eye, width, height)
