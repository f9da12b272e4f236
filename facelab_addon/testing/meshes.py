"""Small analytic meshes for tests: regular grids (planes, height fields, tubes).

A grid has ``n x m`` vertices, vertex ``(i, j)`` at index ``i * m + j``; every
cell is split into the triangles ``(a, b, c)`` and ``(a, c, d)`` with
``a = (i, j)``, ``b = (i + 1, j)``, ``c = (i + 1, j + 1)``, ``d = (i, j + 1)``
(counter-clockwise seen from +z when ``i`` runs along +x and ``j`` along +y).
"""

from __future__ import annotations

import numpy as np

__all__ = ["grid_triangles", "grid_mesh"]


def grid_triangles(n: int, m: int | None = None):
    """Triangles of an ``n x m`` vertex grid (module docstring).

    Parameters
    ----------
    n, m : int
        Vertices along the first and second grid direction (``m`` defaults to ``n``).

    Returns
    -------
    (2 (n-1) (m-1), 3) int64
        Cell by cell, ``i`` major: ``(a, b, c), (a, c, d)``.
    """
    m = n if m is None else m
    i, j = np.meshgrid(np.arange(n - 1), np.arange(m - 1), indexing="ij")
    a = (i * m + j).ravel()
    b, c, d = a + m, a + m + 1, a + 1
    return np.stack([np.stack([a, b, c], 1), np.stack([a, c, d], 1)], 1).reshape(-1, 3).astype(np.int64)


def grid_mesh(xs, ys, z=None):
    """A height field over the grid ``xs x ys``.

    Parameters
    ----------
    xs : (n,) float
        Coordinates along x (grid index ``i``).
    ys : (m,) float
        Coordinates along y (grid index ``j``).
    z : callable, optional
        ``z(X, Y)`` heights for the ``(n, m)`` coordinate arrays; default 0 (a plane).

    Returns
    -------
    vertices : (n m, 3) float64
        Vertex ``(i, j)`` at index ``i * m + j``.
    faces : (2 (n-1) (m-1), 3) int64
        :func:`grid_triangles`.
    """
    X, Y = np.meshgrid(np.asarray(xs, dtype=np.float64), np.asarray(ys, dtype=np.float64), indexing="ij")
    Z = np.zeros_like(X) if z is None else z(X, Y)
    return np.stack([X, Y, Z], -1).reshape(-1, 3), grid_triangles(len(xs), len(ys))
