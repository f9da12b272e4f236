"""A tiny analytic "mouth": two horizontal half tubes facing each other.

The upper lip is the lower half of a tube along x, the lower lip the upper
half of another; seen from a camera on +z their inner silhouettes are the
lines y = +gap/2 (upper) and y = -gap/2 (lower), at depth z = 0.
"""

import numpy as np

from facelab_addon.core.capture.camera import Camera
from facelab_addon.testing.meshes import grid_triangles


def tube(y_center, theta0, theta1, radius, nx=41, nt=25, half_len=2.0):
    xs = np.linspace(-half_len, half_len, nx)
    ts = np.linspace(theta0, theta1, nt)
    X, T = np.meshgrid(xs, ts, indexing="ij")
    V = np.stack([X, y_center + radius * np.sin(T), radius * np.cos(T)], -1).reshape(-1, 3)
    F = grid_triangles(nx, nt)
    # outward normals: (0, sin, cos) must agree with the winding
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    c = V[F].mean(1) - [0, y_center, 0]
    c[:, 0] = 0
    if (np.einsum("ij,ij->i", n, c) < 0).mean() > 0.5:
        F = F[:, ::-1]
    return V, F


def two_lips(gap=0.4, radius=0.5):
    """(V,3), (F,3), upper_mask (V,) for a mouth with the given gap (scene units)."""
    # Front halves of two tubes (cos > 0 faces the camera on +z), each wrapping a
    # few steps past its inner edge: the upper lip's inner edge is its bottom
    # (theta = -pi/2), the lower lip's its top (theta = +pi/2).
    step = np.pi / 24
    Vu, Fu = tube(gap / 2 + radius, -np.pi / 2 - 4 * step, np.pi / 2, radius, nt=29)
    Vl, Fl = tube(-gap / 2 - radius, -np.pi / 2, np.pi / 2 + 4 * step, radius, nt=29)
    V = np.vstack([Vu, Vl])
    F = np.vstack([Fu, Fl + len(Vu)])
    upper = np.r_[np.ones(len(Vu), bool), np.zeros(len(Vl), bool)]
    return V, F, upper


def front_camera(dist=20.0):
    return Camera.look_at([0, 0, dist], [0, 0, 0], [0, 1, 0], 50, 36, 1920, 1080)


def line_px(cam, y, x0=-1.5, x1=1.5, n=30):
    X = np.stack([np.linspace(x0, x1, n), np.full(n, y), np.zeros(n)], 1)
    return cam.project(X)
