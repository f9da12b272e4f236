"""Choosing a tetrahedron per bundle (core.lgi.indexing.locate): hand-computed barycentric locations."""

import numpy as np
import pytest
import scipy.sparse as sp

from facelab_addon.core.lgi.indexing.clouds import build_clouds, build_grid
from facelab_addon.core.lgi.indexing.locate import Locator, build_neighbor_tables
from facelab_addon.core.lgi.indexing.params import IndexerParams

from .test_indexing_clouds import UNIT_TET, corner_dataset


def _locator(corners, tie_tolerance=0.0):
    ds, X, motion = corner_dataset(corners)
    c = build_clouds(ds, X, motion, IndexerParams())
    tables = build_neighbor_tables(sp.csr_matrix((1, 1)), c)  # one bundle: no neighbours
    return Locator(c, build_grid(c, 1.0, ds.face_size), tables, temporal_bias=0.25, tie_tolerance=tie_tolerance,
                   face_size=ds.face_size)


def _by_shape(ids, bary):
    """{shape id: total weight} of one bundle's choice."""
    out = {}
    for i, w in zip(ids.tolist(), bary.tolist()):
        if w > 0:
            out[i] = out.get(i, 0.0) + w
    return out


def test_a_bundle_inside_the_tetrahedron_gets_its_barycentric_weights():
    loc = _locator(UNIT_TET)
    ids, bary, dist = loc.locate(np.array([[0.1, 0.2, 0.3]]))
    # corners: neutral (origin), e_x, e_y, e_z -> weights (1 - 0.6, 0.1, 0.2, 0.3)
    assert ids.tolist() == [[0, 1, 2, 3]]
    np.testing.assert_allclose(bary, [[0.4, 0.1, 0.2, 0.3]], atol=1e-15)
    assert dist.tolist() == [0.0]


def test_a_bundle_outside_projects_to_the_closest_hull_facet():
    loc = _locator(UNIT_TET)
    ids, bary, dist = loc.locate(np.array([[1.0, 1.0, 1.0]]))
    # closest point of the tetrahedron: the centre (1/3, 1/3, 1/3) of the facet x + y + z = 1
    w = _by_shape(ids[0], bary[0])
    assert sorted(w) == [1, 2, 3]
    np.testing.assert_allclose([w[1], w[2], w[3]], 1 / 3, atol=1e-12)
    assert dist[0] == pytest.approx(2 / np.sqrt(3), rel=1e-12)


def test_a_bundle_on_a_cloud_point_uses_that_shape_alone():
    loc = _locator(UNIT_TET)
    ids, bary, dist = loc.locate(np.array([[0.0, 1.0, 0.0]]))
    assert _by_shape(ids[0], bary[0]) == {2: 1.0} and dist[0] == 0.0


def test_merged_shapes_share_a_point_and_the_first_represents_it():
    # shapes 0 and 3 put the bundle at the same place (within the merge tolerance 2e-4): one cloud point
    loc = _locator(UNIT_TET + [[1.0 + 1e-5, 0, 0]])
    c = loc.clouds
    assert c.n_points.tolist() == [5] and c.n_distinct.tolist() == [4]
    assert c.reps[0].tolist() == [0, 1, 2, 3] and c.multi_keys.tolist() == [1]
    assert c.members[c.member_ptr[1]:c.member_ptr[2]].tolist() == [1, 4]
    ids, bary, _ = loc.locate(np.array([[0.1, 0.2, 0.3]]))
    np.testing.assert_allclose(bary, [[0.4, 0.1, 0.2, 0.3]], atol=1e-15)
    assert ids.tolist() == [[0, 1, 2, 3]]  # no neighbour prefers the other member: the representative
