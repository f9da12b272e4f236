"""geometry.mesh.edge_length_graph and geometry.axes.unit_axis against hand-computed values."""

import numpy as np
import pytest

from facelab_addon.core.errors import FaceLabError
from facelab_addon.core.geometry.axes import unit_axis
from facelab_addon.core.geometry.mesh import edge_length_graph


def test_edge_length_graph_of_two_triangles():
    # unit square split along the diagonal 0-2: edges 01, 12, 23, 03 of length 1 and 02 of length sqrt(2)
    V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    F = np.array([[0, 1, 2], [0, 2, 3]])
    G, E, w = edge_length_graph(V, F)
    assert E.tolist() == [[0, 1], [0, 2], [0, 3], [1, 2], [2, 3]]
    np.testing.assert_allclose(w, [1, np.sqrt(2), 1, 1, 1])
    D = G.toarray()
    np.testing.assert_allclose(D, D.T)
    assert D[0, 2] == pytest.approx(np.sqrt(2)) and D[1, 3] == 0.0 and G.nnz == 10
    # a larger graph for extra vertices; a clamp keeps coincident vertices connected
    V2 = V.copy()
    V2[1] = V2[0]
    G2, _, w2 = edge_length_graph(V2, F, 6, min_length=1e-9)
    assert G2.shape == (6, 6) and w2[0] == 1e-9 and G2[0, 1] == 1e-9


def test_unit_axis_normalises_and_refuses_zero():
    np.testing.assert_allclose(unit_axis((0, 3, 4)), [0, 0.6, 0.8])
    with pytest.raises(FaceLabError, match="'up' direction is zero"):
        unit_axis((0, 0, 0), "up")
