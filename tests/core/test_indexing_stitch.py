"""Stitching per-bundle shape weights (core.lgi.indexing.stitch) on a hand-made two-cell square."""

from types import SimpleNamespace

import numpy as np
import pytest
import scipy.sparse as sp

from facelab_addon.core.errors import MeshError
from facelab_addon.core.lgi.indexing.dataset import IndexedDataset
from facelab_addon.core.lgi.indexing.stitch import Stitcher, shape_weight_matrix

# a unit square (two triangles) with bundle 0 on vertex 0 and bundle 1 on vertex 2; every row of W sums to 1
X0 = np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
FACES = np.array([[0, 1, 2], [0, 2, 3]])
W = np.array([[1.0, 0.0], [0.5, 0.5], [0.0, 1.0], [0.25, 0.75]])
CELL = np.array([0, 0, 1, 1])  # the Voronoi cell of every vertex
# two dataset shapes: shape 1 lifts every vertex by 1 along z, shape 2 moves vertex 3 by 2 along x
D = np.zeros((2, 4, 3))
D[0, :, 2] = 1.0
D[1, 3, 0] = 2.0


def square(weights=W):
    active = np.array([0, 1, 2, 3])
    deltas = np.zeros((3, 4, 3), np.float32)
    deltas[1:] = D
    return IndexedDataset(neutral=X0, faces=FACES, bundle_faces=np.array([0, 0]),
                          bundle_bary=np.array([[1.0, 0, 0], [0, 0, 1.0]]), names=["up", "slide"], bundle_names=None,
                          jaw=None, shape_jaw=None, bundle_jaw_weights=None, nn=SimpleNamespace(cell=CELL),
                          weights=sp.csr_matrix(weights), face_size=np.sqrt(2), active=active,
                          deltas=deltas.reshape(-1, 3))


def test_shape_weight_matrix_adds_repeated_ids():
    Beta = shape_weight_matrix([[1, 1, 0, 2]], [[0.25, 0.25, 0.3, 0.2]], 3)
    np.testing.assert_allclose(Beta.toarray(), [[0.3, 0.5, 0.2]], atol=1e-15)


def test_same_shape_everywhere_is_that_shape_because_the_weights_sum_to_one():
    st = Stitcher(square(), threads=1)
    for s in (1, 2):
        np.testing.assert_allclose(st.blend([[s], [s]], [[1.0], [1.0]]), X0 + D[s - 1], atol=1e-7)
    st.close()


def test_two_cells_blend_by_the_natural_neighbour_weights():
    # bundle 0: shape 1 fully; bundle 1: half neutral, half shape 2
    sid, coef = [[1, 0], [0, 2]], [[1.0, 0.0], [0.5, 0.5]]
    expect = X0.copy()
    expect[:, 2] += W[:, 0] * 1.0  # z lift weighted by bundle 0's weight: 1, 0.5, 0, 0.25
    expect[3, 0] += W[3, 1] * 0.5 * 2.0  # vertex 3 slides 0.75 * 0.5 * 2 = 0.75
    for threads in (1, 2):  # row blocks on threads give the same numbers
        st = Stitcher(square(), threads=threads)
        np.testing.assert_allclose(st.blend(sid, coef), expect, atol=1e-7)
        st.close()
    st = Stitcher(square(), threads=1)
    # the Voronoi stitching gives every vertex its cell's bundle: vertices 0, 1 lift by 1, vertex 3 slides 1
    vor = st.blend_dense(st.stitching_matrix("voronoi"), np.array(sid), np.array(coef))
    expect_v = X0.copy()
    expect_v[[0, 1], 2] += 1.0
    expect_v[3, 0] += 1.0
    np.testing.assert_allclose(vor, expect_v, atol=1e-7)
    st.close()


def test_exact_correction_puts_the_surface_through_the_bundles():
    st = Stitcher(square(), threads=1)
    q = np.array([[0.1, 0.0, 0.2], [1.0, 1.3, -0.1]])  # targets of bundles 0 (vertex 0) and 1 (vertex 2)
    X = st.finish(X0.copy(), q, None, True)
    np.testing.assert_allclose(X[[0, 2]], q, atol=1e-14)
    # the residual spreads with W: vertex 1 moves by the mean of the two residuals
    np.testing.assert_allclose(X[1] - X0[1], 0.5 * (q[0] - X0[0]) + 0.5 * (q[1] - X0[2]), atol=1e-14)
    assert st.condition == pytest.approx(1.0)  # Bary W = identity here
    np.testing.assert_array_equal(st.finish(X0.copy(), q, None, False), X0)
    st.close()


def test_a_vertex_without_weight_is_refused():
    Wz = W.copy()
    Wz[1] = 0.0
    with pytest.raises(MeshError, match="no natural-neighbour weight"):
        Stitcher(square(Wz), threads=1)
