"""Natural-neighbour (Sibson) weights (Cong et al. 2019, §5; Sibson 1980; Park et al. 2006)."""

import numpy as np
import pytest

from facelab_addon.core.errors import FaceLabError, MeshError
from facelab_addon.core.lgi.natural_neighbor import (
    gaussian_rbf_weights,
    natural_neighbor_weights,
    sibson_coordinates,
    surface_points,
)


def grid(n=13, size=1.0):
    """Planar (n x n) grid in z=0 over [0, size]^2, its triangles and per-vertex UVs (= xy / size)."""
    from facelab_addon.testing.meshes import grid_mesh

    V, F = grid_mesh(np.linspace(0, size, n), np.linspace(0, size, n))
    return V, F, V[:, :2] / size


def raster_sibson(sites, p, n=900, lo=-0.5, hi=1.5):
    """Brute-force discrete Sibson weights: pixels that p's inserted cell steals, per site."""
    g = np.linspace(lo, hi, n)
    X, Y = np.meshgrid(g, g)
    Q = np.c_[X.ravel(), Y.ravel()]
    d = ((Q[:, None] - sites[None]) ** 2).sum(2)
    lab, dm = d.argmin(1), d.min(1)
    stolen = ((Q - p) ** 2).sum(1) < dm
    w = np.bincount(lab[stolen], minlength=len(sites)).astype(float)
    return w / w.sum()


def test_sibson_symmetric_square_gives_quarters():
    sites = np.array([[0.0, 0], [1, 0], [1, 1], [0, 1]])
    W = sibson_coordinates(sites, [[0.5, 0.5]]).toarray()
    np.testing.assert_allclose(W, [[0.25, 0.25, 0.25, 0.25]], atol=1e-12)
    # on the edge between two sites, by symmetry, the two share equally
    W = sibson_coordinates(sites, [[0.5, 0.0]]).toarray()[0]
    assert W[0] == pytest.approx(W[1], abs=1e-12) and W[2] == pytest.approx(W[3], abs=1e-12)


def test_sibson_partition_of_unity_own_site_and_linear_precision():
    rng = np.random.default_rng(0)
    S = rng.random((25, 2))
    P = 0.25 + 0.5 * rng.random((400, 2))  # well inside the hull
    W = sibson_coordinates(S, P)
    np.testing.assert_allclose(np.asarray(W.sum(1)).ravel(), 1.0, atol=1e-12)
    assert W.min() >= 0
    # Sibson coordinates reproduce linear functions: sum_i w_i s_i = p
    np.testing.assert_allclose(W @ S, P, atol=1e-10)
    # 1 at its own site, 0 at the others
    np.testing.assert_allclose(sibson_coordinates(S, S).toarray(), np.eye(25), atol=1e-12)


def test_sibson_matches_a_brute_force_raster():
    rng = np.random.default_rng(1)
    S = rng.random((12, 2))
    P = 0.3 + 0.4 * rng.random((3, 2))
    W = sibson_coordinates(S, P).toarray()
    for k in range(3):
        np.testing.assert_allclose(W[k], raster_sibson(S, P[k]), atol=6e-3)


def test_sibson_rejects_coincident_sites():
    with pytest.raises(FaceLabError, match="same place"):
        sibson_coordinates([[0, 0], [1, 0], [1, 0]], [[0.5, 0.5]])


def test_uv_weights_on_a_plane_equal_planar_sibson():
    V, F, uv = grid(13)
    rng = np.random.default_rng(2)
    bf = rng.choice(len(F), 9, replace=False)
    bb = rng.dirichlet([3, 3, 3], 9)
    nn = natural_neighbor_weights(V, F, bf, bb, uvs=uv)
    sites = surface_points(V, F, bf, bb)[:, :2]
    np.testing.assert_allclose(nn.site_uv, sites, atol=1e-12)
    ref = sibson_coordinates(sites, V[:, :2]).toarray()
    np.testing.assert_allclose(nn.weights.toarray(), ref, atol=1e-12)
    assert nn.domain.all() and nn.method == "uv"
    # Voronoi cells: every vertex belongs to its nearest bundle; neighbour graph is symmetric
    d = ((V[:, None, :2] - sites[None]) ** 2).sum(2)
    np.testing.assert_array_equal(nn.cell, d.argmin(1))
    Nb = nn.neighbors.toarray()
    np.testing.assert_array_equal(Nb, Nb.T)
    assert (Nb.sum(1) > 0).all()


def test_weight_is_one_at_a_bundle_on_a_vertex():
    V, F, uv = grid(9)
    bf = np.array([10, 40, 70, 100])
    bb = np.tile([1.0, 0.0, 0.0], (4, 1))  # exactly on the first corner
    nn = natural_neighbor_weights(V, F, bf, bb, uvs=uv)
    corner = F[bf, 0]
    np.testing.assert_allclose(nn.weights[corner].toarray(), np.eye(4), atol=1e-12)


def test_per_corner_uvs_and_islands_outside_copy_the_nearest_vertex():
    # two separate planes: bundles on the first; the second (its own UV island) copies the nearest vertex
    V1, F1, uv1 = grid(7)
    V2 = V1 + [0, 0, 0.05]
    V = np.vstack([V1, V2])
    F = np.vstack([F1, F1 + len(V1)])
    cuv = np.concatenate([uv1[F1], uv1[F1]])  # (F,3,2) per-corner UVs, the second island overlaps in UV
    bf = np.array([3, 20, 41, 60])
    bb = np.full((4, 3), 1 / 3)
    nn = natural_neighbor_weights(V, F, bf, bb, uvs=cuv)
    assert nn.domain[: len(V1)].all() and not nn.domain[len(V1):].any()
    np.testing.assert_array_equal(nn.copied_from[len(V1):], np.arange(len(V1)))
    np.testing.assert_allclose(nn.weights[len(V1):].toarray(), nn.weights[: len(V1)].toarray())
    with pytest.raises(MeshError, match="per vertex"):
        natural_neighbor_weights(V, F, bf, bb, uvs=np.zeros((5, 2)))


def test_geodesic_weights_are_a_partition_of_unity_close_to_uv_sibson():
    V, F, uv = grid(21)
    rng = np.random.default_rng(3)
    bf = rng.choice(len(F), 10, replace=False)
    bb = rng.dirichlet([3, 3, 3], 10)
    g = natural_neighbor_weights(V, F, bf, bb, method="geodesic")
    u = natural_neighbor_weights(V, F, bf, bb, uvs=uv)
    W = g.weights.toarray()
    np.testing.assert_allclose(W.sum(1), 1.0, atol=1e-12)
    assert W.min() >= 0
    # the edge-path Voronoi cells follow the exact planar ones, and a vertex mostly follows its own bundle
    assert (g.cell == u.cell).mean() > 0.85
    assert (W[np.arange(len(V)), g.cell] > 0.3).mean() > 0.9
    # a bundle exactly on a vertex has weight 1 there
    bf2 = np.array([10, 200, 420])
    g2 = natural_neighbor_weights(V, F, bf2, np.tile([1.0, 0, 0], (3, 1)), method="geodesic")
    np.testing.assert_allclose(g2.weights[F[bf2, 0]].toarray(), np.eye(3), atol=1e-12)


def test_uv_method_needs_uvs():
    V, F, _ = grid(5)
    with pytest.raises(FaceLabError, match="UV map"):
        natural_neighbor_weights(V, F, [0, 5, 9, 20], np.full((4, 3), 1 / 3), method="uv")


def test_gaussian_rbf_interpolates_at_the_sites():
    rng = np.random.default_rng(4)
    S = rng.random((8, 3))
    R = gaussian_rbf_weights(S, S, sigma=0.4)
    np.testing.assert_allclose(R, np.eye(8), atol=1e-6)
    X = rng.random((50, 3))
    assert gaussian_rbf_weights(X, S).shape == (50, 8)
