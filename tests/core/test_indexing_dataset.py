"""The indexer's dataset (core.lgi.indexing.dataset): stored deltas, jaw unskinning, refused shapes."""

import numpy as np
import pytest

from facelab_addon.core.errors import DatasetError
from facelab_addon.core.lgi.indexing.dataset import build_dataset, find_duplicate_shapes
from facelab_addon.core.lgi.jaw import JawRig
from facelab_addon.testing.meshes import grid_mesh


def _square():
    """A 3 x 3 vertex plane over [0,2]^2 and 4 shapes that each move one corner region along z."""
    V, F = grid_mesh(np.linspace(0, 2, 3), np.linspace(0, 2, 3))
    X = np.repeat(V[None], 4, axis=0)
    for s, v in enumerate((0, 2, 6, 8)):
        X[s, v, 2] = 0.1 * (s + 1)
        X[s, 4, 2] = 0.05  # every shape also lifts the centre
    bf = np.array([0, 3, 4, 7])
    bb = np.full((4, 3), 1 / 3)
    return V, F, X, bf, bb


def test_deltas_hold_only_moving_vertices_shape_major_in_float32():
    V, F, X, bf, bb = _square()
    ds, shapes, motion = build_dataset(V, F, X, bf, bb, uvs=V[:, :2])
    assert (ds.B, ds.S, ds.S1, ds.V) == (4, 4, 5, 9)
    np.testing.assert_array_equal(ds.active, [0, 2, 4, 6, 8])  # the vertices some shape moves
    D = ds.deltas.reshape(ds.S1, len(ds.active), 3)
    assert ds.deltas.dtype == np.float32
    np.testing.assert_array_equal(D[0], 0.0)  # shape id 0 is the neutral
    for s in range(4):
        np.testing.assert_array_equal(D[s + 1], (X[s] - V)[ds.active].astype(np.float32))
    np.testing.assert_allclose(motion[2], [0, 0, 0, 0, 0.05, 0, 0.3, 0, 0], atol=1e-15)  # shape 2: vertex 6
    np.testing.assert_array_equal(shapes, X)
    assert ds.face_size == pytest.approx(np.sqrt(8), rel=1e-12)  # the diagonal of [0,2]^2
    np.testing.assert_allclose(np.asarray(ds.weights.sum(axis=1)).ravel(), 1.0, atol=1e-12)


def test_jaw_shapes_are_stored_unskinned():
    V, F, X, bf, bb = _square()
    rig = JawRig(pivot=[1.0, -1.0, 0.0], axis=[1, 0, 0], weights=V[:, 1] / 2)
    theta = np.array([[0.1, 0, 0, 0], [0.2, 0, 0, 0.01], [0.0, 0.02, 0, 0], [0.3, 0, 0, 0]])
    Xs = np.stack([rig.skin(X[s], theta[s]) for s in range(4)])
    ds, _, _ = build_dataset(V, F, Xs, bf, bb, uvs=V[:, :2], jaw=rig, shape_jaw=theta)
    D = ds.deltas.reshape(ds.S1, len(ds.active), 3)
    for s in range(4):
        np.testing.assert_allclose(D[s + 1], (X[s] - V)[ds.active], atol=1e-7)
    # a bundle's jaw weight is the barycentric mix of its triangle's vertex weights
    np.testing.assert_allclose(ds.bundle_jaw_weights, (rig.weights[F[bf]] * bb).sum(1), atol=1e-15)
    with pytest.raises(DatasetError, match="shape_jaw"):
        build_dataset(V, F, Xs, bf, bb, uvs=V[:, :2], jaw=rig)


def test_duplicates_and_still_shapes_are_refused():
    D = np.zeros((4, 5, 3))
    D[:, 0, 0] = [1.0, 2.0, 3.0, 2.0 + 1e-9]
    assert find_duplicate_shapes(D, 1e-6) == (1, 3)
    assert find_duplicate_shapes(D, 1e-12) is None
    V, F, X, bf, bb = _square()
    with pytest.raises(DatasetError, match="'shape 1' and 'shape 3' are duplicates"):
        build_dataset(V, F, X[[0, 1, 2, 1]], bf, bb, uvs=V[:, :2])
    X[2] = V
    with pytest.raises(DatasetError, match="'shape 2' equals the neutral"):
        build_dataset(V, F, X, bf, bb, uvs=V[:, :2])
