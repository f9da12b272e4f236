"""The mouth corners of the automatic inner-lip loop: where the slit between the lips ends (issue 11).

The contact pairs (facing lip vertices far apart on the mesh) need not reach the corners: on a coarse mesh they
stop an edge or two short, on lips parted in the middle they break in two. The corners are found by following the
slit between the lips beyond the contact, to where the upper and lower lip surfaces join.
"""

import numpy as np

from facelab_addon.core.geometry.mesh import edge_length_graph
from facelab_addon.core.lips import lip_loop
from facelab_addon.testing.meshes import grid_mesh


def slit_plane(n=13, m=9, cut=7):
    """A plane with a straight cut along ``y = (m - 1) / 2`` from ``x = 0`` to ``x = cut - 1`` (its end).

    Returns ``V, F, upper (i -> vertex above the cut at x = i), lower (i -> its copy below the cut)``.
    """
    V, F = grid_mesh(np.arange(n, dtype=float), np.arange(m, dtype=float))
    j = (m - 1) // 2
    upper = np.arange(n) * m + j
    lower = upper.copy()
    lower[: cut - 1] = len(V) + np.arange(cut - 1)  # the cut's vertices get a copy for the faces below it
    V = np.vstack([V, V[upper[: cut - 1]]])
    below = V[F].mean(axis=1)[:, 1] < j
    for i in range(cut - 1):
        F[below[:, None] & (F == upper[i])] = lower[i]
    return V, F, upper, lower


def test_the_slit_end_is_where_the_cut_ends():
    V, F, upper, lower = slit_plane()
    G = edge_length_graph(V, F)[0]
    everything = np.ones(len(V), dtype=bool)
    for i in range(4):  # from either side of the cut, anywhere along it (the two sides touch: 0 apart)
        end = lip_loop._slit_end(V, G, everything, int(upper[i]), int(lower[i]))
        np.testing.assert_allclose(V[end], [6.0, 4.0, 0.0])  # the last vertex both sides share
    # a welded plane has no slit: the path is the edge itself, the end stays put
    Vw, Fw = grid_mesh(np.arange(5.0), np.arange(5.0))
    assert lip_loop._slit_end(Vw, edge_length_graph(Vw, Fw)[0], np.ones(25, bool), 12, 13) in (12, 13)


def test_in_sight():
    V = np.array([[0.0, 0, 0], [-1, -1, 1], [1, -1, 1], [0, 1, 1], [5, 5, 0]])
    F = np.array([[1, 2, 3]])  # a triangle 1 in front (+z) of vertex 0, none in front of vertex 4
    f = np.array([0.0, 0.0, 1.0])
    np.testing.assert_array_equal(lip_loop._in_sight(V, F, np.array([0, 4]), f, np.full(2, 0.5)), [False, True])
    # within the tolerance (the lip gap) a surface in front does not hide it; seen from behind nothing does
    assert lip_loop._in_sight(V, F, np.array([0]), f, np.full(1, 1.5)).all()
    assert lip_loop._in_sight(V, F, np.array([0]), -f, np.full(1, 0.5)).all()


def _ends(P):
    c = P.mean(axis=0)
    s = (P - c) @ np.linalg.svd(P - c, full_matrices=False)[2][0]
    ends = P[[np.argmin(s), np.argmax(s)]]
    return ends[np.argsort(ends[:, 0])]


def test_lips_parted_in_the_middle_still_give_the_whole_mouth(ict):
    """ICT with the lower lip pulled down by up to 9 mm in the middle of the mouth (fading out 1 cm to each side):
    the contact falls apart into two halves, neither crossing the midline. The loop still runs from corner to
    corner, the corners where the intact mouth has them (before: 1.9 cm wide facing a camera, 0.8 cm without)."""
    V, F = ict.neutral, ict.faces
    ref = lip_loop.inner_lip_loop(V, F)
    c, W = V[ref].mean(axis=0), lip_loop.loop_width(V, ref)
    lower = ict.part_vertex_mask("M_Face") & (V[:, 1] < c[1]) & (V[:, 1] > c[1] - 1.0) & (V[:, 2] > c[2] - 1.0)
    X = V.copy()
    X[:, 1] -= 0.9 * np.clip(1.0 - np.abs(V[:, 0] - c[0]), 0.0, 1.0) * lower
    h = np.median(np.linalg.norm(V[ref] - V[np.roll(ref, 1)], axis=1))  # the loop's edge length, about 0.6 mm
    for toward in (None, c + [0.0, 0.0, 40.0]):
        loop = lip_loop.inner_lip_loop(X, F, toward=toward)
        assert abs(lip_loop.loop_width(X, loop) - W) < 0.03 * W
        np.testing.assert_allclose(_ends(X[loop]), _ends(V[ref]), atol=1.5 * h)
