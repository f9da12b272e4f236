import numpy as np

from facelab_addon.core.geometry.laplacian import cotangent_laplacian, uniform_laplacian


def grid(n=7, jitter=0.0, seed=0):
    xs, ys = np.meshgrid(np.arange(n, dtype=float), np.arange(n, dtype=float))
    V = np.c_[xs.ravel(), ys.ravel(), np.zeros(n * n)]
    rng = np.random.default_rng(seed)
    V[:, :2] += jitter * rng.uniform(-1, 1, (n * n, 2))
    F = []
    for i in range(n - 1):
        for j in range(n - 1):
            a = i * n + j
            F += [[a, a + 1, a + n], [a + 1, a + n + 1, a + n]]
    interior = ((xs > 0) & (xs < n - 1) & (ys > 0) & (ys < n - 1)).ravel()
    return V, np.array(F), interior


def test_flat_mesh_cotangent_laplacian_vanishes_inside():
    V, F, inner = grid(jitter=0.3)
    L = cotangent_laplacian(V, F)
    np.testing.assert_allclose((L @ V)[inner], 0.0, atol=1e-12)  # linear precision
    np.testing.assert_allclose(L @ np.ones(len(V)), 0.0, atol=1e-12)
    np.testing.assert_allclose((L - L.T).toarray(), 0.0, atol=1e-14)


def test_uniform_laplacian_regular_grid_and_hand_value():
    V, F, inner = grid()
    L = uniform_laplacian(F, len(V))
    np.testing.assert_allclose((L @ V)[inner], 0.0, atol=1e-12)
    # corner vertex 0 has neighbours 1 and n (=7): delta = v0 - mean = (-0.5, -0.5, 0)
    np.testing.assert_allclose((L @ V)[0], [-0.5, -0.5, 0.0])


def test_laplacian_coordinates_rotate_with_rigid_motion():
    rng = np.random.default_rng(3)
    V, F, _ = grid(jitter=0.2)
    V[:, 2] = np.sin(V[:, 0]) * 0.5 + rng.normal(0, 0.05, len(V))
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    R = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
    W = V @ R.T + [1.0, -2.0, 3.0]
    for L0, L1 in (
        (uniform_laplacian(F, len(V)), uniform_laplacian(F, len(V))),
        (cotangent_laplacian(V, F), cotangent_laplacian(W, F)),
    ):
        np.testing.assert_allclose(L1 @ W, (L0 @ V) @ R.T, atol=1e-10)
