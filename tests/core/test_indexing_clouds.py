"""Point clouds, tetrahedra and grids of the indexer (core.lgi.indexing.clouds), on hand-made clouds."""

import itertools

import numpy as np
import pytest
import scipy.sparse as sp

from facelab_addon.core.errors import DatasetError
from facelab_addon.core.lgi.indexing.clouds import (
    build_clouds,
    build_grid,
    cluster_points,
    forbidden_shape_ids,
    tetrahedralize,
)
from facelab_addon.core.lgi.indexing.dataset import IndexedDataset
from facelab_addon.core.lgi.indexing.params import IndexerParams


def corner_dataset(corners):
    """One triangle; one bundle on vertex 0; shape ``s`` moves vertex 0 to ``corners[s]`` (S,3).

    The bundle's cloud is then the origin (the neutral, shape id 0) and the corners."""
    x0 = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    corners = np.asarray(corners, dtype=np.float64)
    S = len(corners)
    X = np.repeat(x0[None], S, axis=0)
    X[:, 0] = corners
    D = X - x0
    active = np.array([0])
    deltas = np.zeros((S + 1, 1, 3), np.float32)
    deltas[1:] = D[:, active]
    ds = IndexedDataset(neutral=x0, faces=np.array([[0, 1, 2]]), bundle_faces=np.array([0]),
                        bundle_bary=np.array([[1.0, 0, 0]]), names=[f"s{k}" for k in range(S)], bundle_names=None,
                        jaw=None, shape_jaw=None, bundle_jaw_weights=None, nn=None,
                        weights=sp.csr_matrix(np.ones((3, 1))), face_size=1.0, active=active,
                        deltas=deltas.reshape(-1, 3))
    return ds, X, np.linalg.norm(D, axis=2)


UNIT_TET = [[1.0, 0, 0], [0, 1, 0], [0, 0, 1]]


def test_cluster_points_merges_greedily_in_order():
    pts = np.array([[0.0, 0, 0], [0.05, 0, 0], [1, 0, 0], [1.02, 0, 0], [0.09, 0, 0]])
    # point 4 is 0.09 from point 0 (> 0.06): it is not merged into 0 even though it is close to point 1
    np.testing.assert_array_equal(cluster_points(pts, 0.06), [0, 0, 2, 2, 4])


def test_forbidden_sets_become_sorted_shape_ids():
    sets = forbidden_shape_ids([(2, "a"), ("c",)], ["a", "b", "c"])
    assert [s.tolist() for s in sets] == [[1, 3], [3]]  # shape id = index + 1 (0 is the neutral)
    with pytest.raises(DatasetError, match="unknown shape 'z'"):
        forbidden_shape_ids([("z",)], ["a", "b", "c"])


def _counts():
    return dict(candidates=0, thin=0, large=0, flagged=0, restored=0, flat_clouds=0, segment_clouds=0)


def test_tetrahedralize_small_flat_and_segment_clouds():
    st = _counts()
    T = tetrahedralize(np.array([[0.0, 0, 0], [1, 0, 0]]), np.array([0, 7]), 6, 0.05, None, 4, st)
    assert T.tolist() == [[0, 7, 7, 7]] and st["segment_clouds"] == 1
    # a unit square: flat, so its 4 triangles (right isosceles, quality sqrt(3)/2) stored as (a, b, c, c)
    st = _counts()
    sq = np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
    T = tetrahedralize(sq, np.array([0, 1, 2, 3]), 6, 0.05, None, 4, st)
    assert st["flat_clouds"] == 1
    assert sorted(map(tuple, T.tolist())) == [(a, b, c, c) for a, b, c in itertools.combinations(range(4), 3)]


def test_tetrahedralize_prunes_large_and_forbidden_tetrahedra():
    # the unit tetrahedron's corners and its centroid: all 5 four-point combinations are candidates
    pts = np.r_[[[0.0, 0, 0]], UNIT_TET, [[0.25, 0.25, 0.25]]]
    ids = np.array([0, 1, 2, 3, 4])
    st = _counts()
    T = tetrahedralize(pts, ids, 6, 0.05, None, 0, st)
    assert st["candidates"] == 5
    assert sorted(map(tuple, T.tolist())) == list(itertools.combinations(range(5), 4))
    # every 4 of these 5 points hold two unit corners, sqrt(2) apart: max_edge 1.2 deletes all, 1.5 none
    st = _counts()
    assert len(tetrahedralize(pts, ids, 6, 0.05, 1.2, 0, st)) == 0 and st["large"] == 5
    st = _counts()
    assert len(tetrahedralize(pts, ids, 6, 0.05, 1.5, 0, st)) == 5 and st["large"] == 0
    # ... unless every point must keep a tetrahedron: the best ones are restored
    st = _counts()
    T = tetrahedralize(pts, ids, 6, 0.05, 1.2, 1, st)
    assert st["restored"] == len(T) and set(T.ravel().tolist()) == set(range(5))
    # forbidding shapes {1, 2} together deletes the 3 tetrahedra that hold both
    st = _counts()
    T = tetrahedralize(pts, ids, 6, 0.05, None, 0, st, forbidden=[np.array([1, 2])])
    assert st["flagged"] == 3 and len(T) == 2 and not any({1, 2} <= set(t) for t in T.tolist())


def test_build_clouds_and_grid_on_one_bundle():
    ds, X, motion = corner_dataset(UNIT_TET)
    c = build_clouds(ds, X, motion, IndexerParams())
    np.testing.assert_array_equal(c.points[:, 0], np.r_[[[0.0, 0, 0]], UNIT_TET])
    np.testing.assert_allclose(c.motion[:, 0], 1.0)
    assert c.merge_tolerance == pytest.approx(2e-4)  # 2e-4 times the face size 1
    assert c.tets.tolist() == [[0, 1, 2, 3]] and c.tet_offsets.tolist() == [0, 1]
    # the affine map gives (w1, w2, w3) = q for the corner tetrahedron at the origin
    q = np.array([0.1, 0.2, 0.3])
    np.testing.assert_allclose(c.tet_affine[0] @ np.r_[q, 1.0], q, atol=1e-15)
    assert (c.tet_lo[0] <= 0).all() and (c.tet_hi[0] >= 1).all()
    assert c.hull_offsets.tolist() == [0, 4] and len(c.hull_tris) == 4  # the tetrahedron's 4 faces
    g = build_grid(c, 1.0, ds.face_size)
    assert g.n.tolist() == [[1, 1, 1]] and g.cell_tets.tolist() == [0]  # one tetrahedron: one cell
    g = build_grid(c, 27.0, ds.face_size)
    assert g.n.tolist() == [[3, 3, 3]] and len(g.cell_start) == 28
    assert (np.diff(g.cell_start) == 1).all()  # its box covers every cell
