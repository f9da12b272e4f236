"""``core.geometry.weld``: coincident vertices of a mesh split along its seams are welded back, but a lip cut
(twins coincident at rest that a shape key parts) is not, at any scale."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from facelab_addon.core.geometry.mesh import connected_components
from facelab_addon.core.geometry.weld import Weld, weld, weld_tolerance


def _square_split():
    """Two triangles sharing the edge 1-2 of a unit square, split along it: 4 corners -> 6 vertices."""
    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [1, 0, 0], [0, 1, 0]], float)
    F = np.array([[0, 1, 2], [4, 3, 5]])
    return V, F


def _lip_cut(n=6):
    """A closed mouth: an upper strip (rows 0, 1) and a lower strip (rows 2, 3) whose rows 1 and 2 coincide at rest
    (the contact, a cut: no face joins them); the key "open" moves the lower strip down."""
    x = np.arange(n, dtype=float)
    rows = [np.c_[x, np.full(n, y), np.zeros(n)] for y in (1.0, 0.0, 0.0, -1.0)]
    V = np.vstack(rows)
    F = []
    for top in (0, 2):
        for i in range(n - 1):
            a, b, c, d = top * n + i, top * n + i + 1, (top + 1) * n + i, (top + 1) * n + i + 1
            F += [[a, c, b], [b, c, d]]
    open_ = V.copy()
    open_[2 * n:, 1] -= 0.5
    return V, np.array(F), open_


def test_a_split_edge_is_welded_back_to_one_surface():
    V, F = _square_split()
    assert connected_components(F, len(V)).max() == 1  # two pieces
    w = weld(F, V)
    np.testing.assert_array_equal(w.representative, [0, 1, 2, 3, 1, 2])
    np.testing.assert_array_equal(w.faces, [[0, 1, 2], [1, 3, 2]])
    assert w.n_duplicates == 2 and list(w.duplicates) == [4, 5]
    lab = connected_components(w.faces, len(V))
    assert len(np.unique(lab[:4])) == 1  # the four corners are one piece
    # a value computed on the welded surface is given to the duplicates
    vals = np.array([10.0, 11.0, 12.0, 13.0, -1.0, -1.0])
    np.testing.assert_array_equal(w.spread(vals), [10, 11, 12, 13, 11, 12])
    allv, take = w.expand([1, 3])
    np.testing.assert_array_equal(allv, [1, 3, 4])
    np.testing.assert_array_equal(np.array([7.0, 8.0])[take], [7, 8, 7])


def test_a_shape_key_that_keeps_the_twins_together_welds_them():
    V, F = _square_split()
    key = V + np.array([0.0, 0.0, 0.3]) * V[:, :1]  # a bend: the twins move together
    assert weld(F, V, [key]).n_duplicates == 2


def test_a_lip_cut_parted_by_a_shape_key_is_not_welded():
    V, F, open_ = _lip_cut()
    n = 6
    assert weld(F, V).n_duplicates == n  # at rest alone the contact rows coincide ...
    w = weld(F, V, [V, open_])  # ... but the mouth opens in a key: nothing is welded
    assert w.n_duplicates == 0
    np.testing.assert_array_equal(w.representative, np.arange(len(V)))
    assert w.faces is F or np.array_equal(w.faces, F)
    assert w.spread(V) is V  # nothing welded: the arrays as they are
    # a key that parts only one pair of twins keeps the others welded
    one = V.copy()
    one[2 * n + 3, 1] -= 0.5
    w = weld(F, V, [one])
    assert w.n_duplicates == n - 1 and w.representative[2 * n + 3] == 2 * n + 3


def test_poses_are_not_read_without_coincident_vertices():
    V, F, _ = _lip_cut()
    V[2 * 6:, 1] -= 0.01  # the mouth modelled slightly open: no twins

    def poses():
        raise AssertionError("read")
        yield V

    w = weld(F, V, poses())
    assert w.n_duplicates == 0 and w.faces is F


@pytest.mark.parametrize("scale", [1e-3, 1.0, 1e3])
def test_the_tolerance_is_relative_to_the_mesh(scale):
    V, F = _square_split()
    V = V * scale + np.array([5.0, -2.0, 1.0]) * scale
    near = V.copy()
    near[4] += np.array([0.3e-4, 0, 0]) * scale  # within 1e-4 median edge lengths: float round-off
    assert weld(F, near).n_duplicates == 2
    far = V.copy()
    far[4] += np.array([3e-4, 0, 0]) * scale  # beyond it: a distinct vertex; the pieces would touch at one vertex
    assert weld(F, far).n_duplicates == 0
    assert weld_tolerance(V, F) == pytest.approx(1e-4 * scale)
    # an absolute tolerance overrides
    assert weld(F, far, tol=1e-3 * scale).n_duplicates == 2


def test_a_part_glued_onto_the_surface_stays_separate():
    """Eyelashes glued to the lid's rim (ICT-FaceKit: 250 vertices coincident in the rest pose and all 57
    expressions): a fin on an edge already shared by two triangles, or a part touching at one vertex."""
    V, F = _square_split()
    welded = weld(F, V)
    # a fin: a third piece whose edge coincides with the (welded) diagonal: three triangles on one edge
    fin = np.array([[1, 0, 0], [0, 1, 0], [0.5, 0.5, 1]], float)
    V2 = np.vstack([V, fin])
    F2 = np.vstack([F, [[6, 7, 8]]])
    w = weld(F2, V2)
    # the fin rides on the seam: the diagonal would carry three triangles, so nothing is welded there
    assert w.n_duplicates == 0
    # a fin on the square's side (away from the seam) is not welded; the seam is
    V3 = np.vstack([V, [[0, 0, 0], [1, 0, 0], [0.5, -0.5, 1]]])  # a fin on the edge 0-1 (the square's side)
    F3 = np.vstack([F, [[6, 7, 8]]])
    w = weld(F3, V3)
    np.testing.assert_array_equal(w.representative, [0, 1, 2, 3, 1, 2, 6, 7, 8])
    # a part touching the surface at one vertex
    V4 = np.vstack([V, [[1, 1, 0], [2, 1, 0], [1, 2, 0]]])
    F4 = np.vstack([F, [[6, 7, 8]]])
    w = weld(F4, V4)
    assert w.representative[6] == 6 and w.n_duplicates == welded.n_duplicates


def test_a_pose_of_the_wrong_shape_is_refused():
    V, F = _square_split()
    with pytest.raises(ValueError, match="shape"):
        weld(F, V, [V[:4]])


def test_weld_is_a_frozen_record():
    w = weld(*reversed(_square_split()))
    assert isinstance(w, Weld)
    with pytest.raises(Exception):
        w.faces = None


def test_compact_and_uncompact_drop_and_restore_the_duplicates():
    V, F = _square_split()
    w = weld(F, V)
    Vc, Fc = w.compact(V)
    np.testing.assert_array_equal(w.kept, [0, 1, 2, 3])
    np.testing.assert_array_equal(Vc, V[:4])
    np.testing.assert_array_equal(Fc, [[0, 1, 2], [1, 3, 2]])
    np.testing.assert_array_equal(w.uncompact(np.arange(4) * 10), [0, 10, 20, 30, 10, 20])


def test_the_ict_face_welds_nothing_and_its_uv_split_welds_back_to_it(ict):
    """ICT-FaceKit has 367 vertices coincident at rest (250 in every expression too): its eyelashes, eye-occlusion
    shell and tear film glued to the lid rims. They are parts, not seams: nothing is welded. Split by its own UVs
    (26,719 -> 28,911 vertices), the split welds back to exactly ICT's vertices and triangles."""
    from facelab_addon.testing.split_seams import split_seams

    F, V = np.asarray(ict.faces), ict.neutral
    assert weld(F, V, tol=weld_tolerance(V, F)).n_duplicates == 0
    pairs_at_rest = cKDTree(V).query_pairs(weld_tolerance(V, F))
    assert len(pairs_at_rest) > 300  # the glued parts
    w = weld(F, V, ict.expressions.values())
    assert w.n_duplicates == 0 and w.faces is F
    s = split_seams(ict)
    assert (len(V), len(s.neutral)) == (26719, 28911)
    ws = weld(s.faces, s.neutral, s.expressions.values())
    assert ws.n_duplicates == len(s.neutral) - len(V)
    np.testing.assert_array_equal(s.source[ws.kept], np.arange(len(V)))
    np.testing.assert_array_equal(ws.compact(s.neutral)[1], F)


def test_poses_are_not_read_for_parts_that_only_touch(ict):
    """ICT's glued eyelashes and eye shells coincide with the lid rims at rest, but close no seam: the poses (the
    57 expressions, or the frames a step evaluates) are never read."""
    def poses():
        raise AssertionError("read")
        yield ict.neutral

    assert weld(np.asarray(ict.faces), ict.neutral, poses()).n_duplicates == 0
