"""Small analytic meshes for tests: regular grids (planes, height fields, tubes).

A grid has ``n x m`` vertices, vertex ``(i, j)`` at index ``i * m + j``; every
cell is split into the triangles ``(a, b, c)`` and ``(a, c, d)`` with
``a = (i, j)``, ``b = (i + 1, j)``, ``c = (i + 1, j + 1)``, ``d = (i, j + 1)``
(counter-clockwise seen from +z when ``i`` runs along +x and ``j`` along +y).
"""

from __future__ import annotations

import numpy as np

__all__ = ["grid_triangles", "grid_mesh", "malformed_grid", "MALFORMATIONS"]


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


#: What :func:`malformed_grid` may do to a grid: reverse some triangles, cut holes, add an edge shared by three
#: triangles, repeat triangles, squash triangles into slivers, merge two corners of a triangle into one position.
MALFORMATIONS = ("flip", "hole", "nonmanifold", "duplicate", "sliver", "coincident")


def malformed_grid(seed: int):
    """A randomly perturbed grid with one to three :data:`MALFORMATIONS` (the meshes artists' scans and
    broken exports give), deterministic in ``seed``.

    Returns
    -------
    vertices : (V,3) float64
        Grid of 3 to 19 vertices a side, unit spacing, perturbed by Gaussian noise (sigma 0 to 3).
    faces : (F,3) int64
    kinds : list of str
        The malformations applied.
    """
    rng = np.random.default_rng(seed)
    kinds = sorted(str(k) for k in rng.choice(MALFORMATIONS, rng.integers(1, 4), replace=False))
    n, m = rng.integers(3, 20, 2)
    V, F = grid_mesh(np.arange(n, dtype=float), np.arange(m, dtype=float))
    V = V + rng.normal(0, rng.choice([0.0, 0.05, 0.3, 1.0, 3.0]), V.shape)
    if "flip" in kinds:
        idx = rng.choice(len(F), rng.integers(1, max(2, len(F) // 3)), replace=False)
        F[idx] = F[idx][:, ::-1]
    if "hole" in kinds:
        F = F[rng.random(len(F)) > rng.uniform(0.05, 0.5)]
    if "nonmanifold" in kinds and len(F):
        f = F[rng.integers(len(F))]
        V = np.vstack([V, V[f].mean(0) + rng.normal(0, 0.3, 3)])
        F = np.vstack([F, [f[0], f[1], len(V) - 1]])
    if "duplicate" in kinds and len(F):
        F = np.vstack([F, F[rng.integers(len(F), size=3)]])
    if "sliver" in kinds and len(F):
        for f in F[rng.integers(len(F), size=3)]:
            V[f[2]] = V[f[0]] + (V[f[1]] - V[f[0]]) * rng.random() + rng.normal(0, 1e-9, 3)
    if "coincident" in kinds and len(F):
        for f in F[rng.integers(len(F), size=3)]:
            V[f[1]] = V[f[0]]
    return V, F, kinds
