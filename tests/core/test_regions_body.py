"""Auto Regions finds the mouth on a body: the ICT head (mouth bag attached to the lips) in one piece with
fingers and eyelid folds whose contact groups are bigger than the lips'."""

import numpy as np
import pytest

from facelab_addon.core.errors import RegionError
from facelab_addon.core.geometry.mesh import vertex_adjacency
from facelab_addon.core.lips import lip_loop, regions
from facelab_addon.testing.bodies import head_with_folds

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def body(ict):
    V, F, folds = head_with_folds(ict)
    return ict, V, F, folds, lip_loop.inner_lip_loop(ict.neutral, ict.faces)


def on_the_lips(ict, V, loop, ref):
    """The loop is ICT's lip contact line: face vertices, mostly the head-only loop, corner to corner."""
    assert ict.part_vertex_mask("M_Face")[loop[loop < len(ict.neutral)]].all() and (loop < len(ict.neutral)).all()
    near = np.linalg.norm(V[loop][:, None] - V[ref][None], axis=2)
    assert near.min(axis=1).max() < 0.3 and near.min(axis=0).max() < 0.3  # within 3 mm of it, all along
    assert abs(lip_loop.loop_width(V, loop) - lip_loop.loop_width(V, ref)) < 0.05 * lip_loop.loop_width(V, ref)


def test_the_folds_are_bigger_contact_groups_than_the_lips(body):
    ict, V, F, folds, ref = body
    # every fold is a contact group the search sees: rays through a finger find the finger
    finger = np.flatnonzero(folds)[:500]
    eye = V[finger].mean(axis=0) + np.array([0, 0, 60.0])
    loop = lip_loop.inner_lip_loop(V, F, rays=(np.repeat(eye[None], 50, 0), V[finger[::10]] - eye))
    assert folds[loop].all()
    # and the folds have many more contact vertices than the lips (so "the largest contact" is not the mouth)
    partner, _ = lip_loop._contact_pairs(V, F, np.ones(len(V), bool), vertex_adjacency(F, len(V)), 0.52, 8)
    face = np.r_[ict.part_vertex_mask("M_Face"), np.zeros(folds.sum(), bool)]
    assert ((partner >= 0) & folds).sum() > 8 * ((partner >= 0) & face).sum()


def test_auto_regions_finds_the_mouth_on_a_body(body):
    ict, V, F, folds, ref = body
    loop = lip_loop.inner_lip_loop(V, F)
    on_the_lips(ict, V, loop, ref)
    mouth, lips = regions.auto_regions(V, F)
    assert not (mouth | lips)[folds].any()
    m0, l0 = regions.auto_regions(ict.neutral, ict.faces)
    n = len(ict.neutral)
    # the same regions as on the head alone, up to the loop's few vertices of difference
    assert (lips[:n] ^ l0).sum() < 0.1 * l0.sum() and (mouth[:n] ^ m0).sum() < 0.1 * m0.sum()
    # in metres, Z up (Blender's axes: x, y, z -> x, -z, y): the same loop
    assert set(lip_loop.inner_lip_loop(np.c_[V[:, 0], -V[:, 2], V[:, 1]] * 0.01, F).tolist()) == set(loop.tolist())


def test_an_asymmetric_body_needs_the_sketch(body):
    ict, _, _, _, ref = body
    V, F, folds = head_with_folds(ict, hands=1)  # one hand: no mirror plane to find the mouth on
    cam = np.array([0.0, V[ref, 1].mean(), V[ref, 2].mean() + 40.0])  # 40 cm in front of the mouth
    P = V[ref] + np.random.default_rng(0).normal(scale=0.05, size=(len(ref), 3))  # a sketch within ~1 mm
    loop = lip_loop.inner_lip_loop(V, F, rays=(np.repeat(cam[None], len(P), 0), P - cam), toward=cam)
    on_the_lips(ict, V, loop, ref)
    mouth, lips = regions.auto_regions(V, F, rays=(np.repeat(cam[None], len(P), 0), P - cam), toward=cam)
    assert lips[ref].all() and not (mouth | lips)[folds].any()


def test_the_front_of_an_attached_interior(ict):
    """ICT's mouth bag is attached to the lips. Flattened so its walls touch 4 cm deep and 7 cm wide (a
    bigger contact than the lips, joined to it), the loop still runs along the front of the contact: the
    side that faces the camera, or the side the skin around the mouth faces."""
    V, F = ict.neutral.copy(), ict.faces
    ref = lip_loop.inner_lip_loop(V, F)
    c, W = V[ref].mean(axis=0), lip_loop.loop_width(V, ref)
    bag = ict.part_vertex_mask("M_BackHead") & ~ict.part_vertex_mask("M_Face")
    inside = bag & (np.abs(V[:, 0] - c[0]) < 0.9 * W) & (V[:, 2] < c[2]) & (V[:, 2] > c[2] - 1.2 * W)
    inside &= np.abs(V[:, 1] - c[1]) < 0.8 * W
    X = V.copy()
    X[inside, 1] = c[1] + 0.08 * (V[inside, 1] - c[1])  # the bag's roof and floor 0.4 mm apart or less
    for toward in (None, c + [0.0, 0.0, 40.0]):  # the skin's front; a camera 40 cm in front
        loop = lip_loop.inner_lip_loop(X, F, toward=toward)
        d = np.linalg.norm(X[loop][:, None] - V[ref][None], axis=2).min(axis=1)
        assert d.max() < 0.5 and abs(lip_loop.loop_width(X, loop) - W) < 0.1 * W
    # a camera behind the head sees the inside: the loop follows the bag's contact, deep in the mouth
    back = lip_loop.inner_lip_loop(X, F, toward=c - [0.0, 0.0, 40.0])
    assert X[back, 2].mean() < V[ref, 2].mean() - 0.5


def test_failure_names_the_option_given():
    from facelab_addon.testing.meshes import grid_mesh

    V, F = grid_mesh(np.arange(9.0), np.arange(9.0))
    with pytest.raises(RegionError, match="raise the Lip Contact Gap") as e:
        lip_loop.inner_lip_loop(V, F, gap_name="the Lip Contact Gap")
    assert "max_gap" not in str(e.value)
