"""Auto Regions and the lip-loop finder end every bad input in a RegionError (issue 13)."""

import numpy as np
import pytest

from facelab_addon.core.errors import MeshError, RegionError, RegionMeshError
from facelab_addon.core.lips.lip_loop import inner_lip_loop
from facelab_addon.core.lips.regions import auto_regions
from facelab_addon.testing.meshes import grid_mesh

from .lipmesh import tube, two_lips


def _noisy_lips():
    """Two small noisy half tubes whose only facing pairs are near on the mesh (was an IndexError)."""
    rng = np.random.default_rng(66)
    nx, nt = rng.integers(3, 15, 2)
    gap, r = rng.uniform(0, 0.6), rng.uniform(0.1, 1)
    Vu, Fu = tube(gap / 2 + r, -np.pi / 2 - rng.uniform(0, 0.6), np.pi / 2, r, nx=nx, nt=nt)
    Vl, Fl = tube(-gap / 2 - r, -np.pi / 2, np.pi / 2 + rng.uniform(0, 0.6), r, nx=nx, nt=nt)
    V = np.vstack([Vu, Vl]) + rng.normal(0, rng.uniform(0, 0.05), (len(Vu) + len(Vl), 3))
    return V, np.vstack([Fu, Fl + len(Vu)])


def test_contact_pairs_that_are_all_near_on_the_mesh_give_a_region_error():
    V, F = _noisy_lips()
    with pytest.raises(RegionError, match="no pair of facing lip surfaces was found; close the mouth"):
        inner_lip_loop(V, F)
    with pytest.raises(RegionError, match="no pair of facing lip surfaces"):
        auto_regions(V, F)


@pytest.mark.parametrize("faces, match", [
    (np.zeros((0, 3), int), "non-empty \\(F,3\\) array of triangles"),
    (np.array([[0, 1, 99]]), "out of range"),
    (np.array([[0, 1, -1]]), "must not be negative"),
    (np.array([[0.0, 1.0, 2.0]]), "must be integers"),
])
def test_bad_faces_are_refused_as_region_and_mesh_errors(faces, match):
    V, _ = grid_mesh(np.arange(4.0), np.arange(4.0))
    for fn in (inner_lip_loop, auto_regions):
        with pytest.raises(RegionMeshError, match=match) as ei:
            fn(V, faces)
        assert isinstance(ei.value, RegionError) and isinstance(ei.value, MeshError)


def test_nan_vertices_and_bad_widths_are_refused_and_inputs_untouched():
    V, F, _ = two_lips()
    bad = V.copy()
    bad[3, 1] = np.nan
    keep = bad.copy()
    with pytest.raises(RegionMeshError, match="NaN or infinite"):
        auto_regions(bad, F)
    np.testing.assert_array_equal(bad, keep)
    G, GF = grid_mesh(np.arange(4.0), np.arange(4.0))
    with pytest.raises(RegionError, match="lip width must be a distance"):
        auto_regions(G, GF, GF[4], lip_width="wide")
    with pytest.raises(RegionError, match="max_gap must be a positive distance"):
        inner_lip_loop(V, F, max_gap=-1.0)
    with pytest.raises(RegionError, match="must be vertex indices"):
        inner_lip_loop(V, F, loop=[0.5, 1.5, 2.5])
    with pytest.raises(RegionError, match="produced an empty mouth region.*increase the widths"):
        auto_regions(G, GF, GF[4])  # the same loop with valid widths: a clear refusal on this tiny grid


def test_random_height_grids_end_in_a_region_error_not_an_index_error():
    """Random bumpy grids (no lips): the contact search keeps only pairs that are near on the mesh, which used
    to crash with an IndexError on about a third of them; every one now says why no lip line was found."""
    for seed in range(0, 40, 5):
        rng = np.random.default_rng(seed)
        n, m = rng.integers(3, 20, 2)
        V, F = grid_mesh(np.arange(n, dtype=float), np.arange(m, dtype=float),
                         lambda x, y: rng.normal(0, rng.uniform(0, 2), x.shape))
        with pytest.raises(RegionError, match="Cannot find the inner-lip line"):
            auto_regions(V, F)
