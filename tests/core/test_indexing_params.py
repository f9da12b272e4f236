"""IndexerParams (core.lgi.indexing.params): defaults, face-size tolerances, and what the indexer resolves."""

import dataclasses

import numpy as np
import pytest

from facelab_addon.core.lgi.indexing.indexer import GeometricIndexer
from facelab_addon.core.lgi.indexing.params import IndexerParams

from .test_geometric_indexing import dataset, plane


def test_tolerances_scale_with_the_face_size_unless_given():
    p = IndexerParams()
    assert p.prune_tolerance_at(10.0) == pytest.approx(1e-6, rel=1e-15)
    assert p.merge_tolerance_at(10.0) == pytest.approx(2e-3, rel=1e-15)
    assert p.tie_tolerance_at(10.0) == pytest.approx(1e-4, rel=1e-15)
    q = IndexerParams(prune_tolerance=0.5, merge_tolerance=0.25, tie_tolerance=0.0)
    assert (q.prune_tolerance_at(10.0), q.merge_tolerance_at(10.0), q.tie_tolerance_at(10.0)) == (0.5, 0.25, 0.0)


def test_params_are_frozen_and_replace_makes_a_variant():
    p = IndexerParams()
    with pytest.raises(dataclasses.FrozenInstanceError):
        p.neighbors = 8
    q = dataclasses.replace(p, neighbors=8, threads=1)
    assert (q.neighbors, q.threads, p.neighbors, p.threads) == (8, 1, 6, 2)


def test_the_indexer_uses_the_params_it_is_given():
    V, F = plane(9)
    _, X = dataset(V)
    bf = np.arange(3, len(F), 17)
    bb = np.full((len(bf), 3), 1 / 3)
    gi = GeometricIndexer(V, F, X, bf, bb, uvs=V[:, :2], params=IndexerParams(threads=1, temporal_bias=0.5))
    fs = gi.dataset.face_size
    # the plane's natural-neighbour domain is the whole unit square: face size sqrt(2)
    assert fs == pytest.approx(np.sqrt(2), rel=1e-12)
    assert gi.clouds.merge_tolerance == pytest.approx(2e-4 * fs, rel=1e-15)
    assert gi.locator.tie_tolerance == pytest.approx(1e-5 * fs, rel=1e-15)
    assert gi.locator.temporal_bias == 0.5 and gi.stitcher.threads == 1 and gi.grid.density == 1.0
    gi.close()
    gi = GeometricIndexer(V, F, X, bf, bb, uvs=V[:, :2], params=IndexerParams(threads=1, merge_tolerance=0.01,
                                                                               tie_tolerance=0.0, grid_density=8.0))
    assert (gi.clouds.merge_tolerance, gi.locator.tie_tolerance, gi.grid.density) == (0.01, 0.0, 8.0)
    gi.close()
