"""Mouth deformation-gradient features (core/lips/regressor/features.py) on a 2-triangle patch.

A similarity map ``x -> s Q x + t`` deforms every triangle with gradient ``s Q`` exactly, phantom column
included (the normal scales by ``s²``, ``n / sqrt|n|`` by ``s``), so the hand truth is ``s Q``."""

import numpy as np
import pytest

from facelab_addon.core.errors import FaceLabError, MeshError
from facelab_addon.core.geometry.gradients import rest_inverse
from facelab_addon.core.lips.regressor.features import (
    as_frames,
    coordinate_major,
    feature_rows,
    fold_directions,
    gradient_features,
    gradients,
    mouth_coefficients,
    mouth_feature_matrix,
    mouth_terms,
)

REST = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 1.0, 0.0], [5.0, 5.0, 5.0]])
FACES = np.array([[0, 1, 2], [1, 3, 2]])  # vertex 4 is not in the patch
VERTS = np.arange(4)


def _rot(angle, axis):
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


MAPS = [1.5 * _rot(0.4, (1, 2, 3)), 0.5 * _rot(-1.0, (0, 0, 1)), np.eye(3)]


def _frames():
    return np.stack([REST @ A.T + [0.3, -2.0, 1.0] for A in MAPS])  # (3, V, 3)


def test_gradients_of_a_similarity_are_the_map():
    rinv = rest_inverse(REST, FACES)
    G = gradients(_frames(), rinv, VERTS, FACES)
    assert G.shape == (3, 2, 3, 3)
    for t, A in enumerate(MAPS):
        np.testing.assert_allclose(G[t], [A, A], atol=1e-12)


def test_feature_rows_are_row_major_and_centred_on_the_identity():
    rinv = rest_inverse(REST, FACES)
    want = np.stack([np.tile((A - np.eye(3)).ravel(), 2) for A in MAPS])  # (3, 18)
    np.testing.assert_allclose(gradient_features(_frames(), VERTS, FACES, rinv, True), want, atol=1e-12)
    np.testing.assert_allclose(feature_rows(gradients(_frames(), rinv, VERTS, FACES), "rest"), want, atol=1e-12)
    np.testing.assert_allclose(mouth_feature_matrix(_frames(), REST, FACES, [0, 1]), want, atol=1e-12)
    plain = np.stack([np.tile(A.ravel(), 2) for A in MAPS])
    np.testing.assert_allclose(gradient_features(_frames(), VERTS, FACES, rinv, False), plain, atol=1e-12)
    np.testing.assert_allclose(feature_rows(gradients(_frames(), rinv, VERTS, FACES), None), plain, atol=1e-12)
    assert not gradient_features(_frames(), VERTS, FACES, rinv, True)[2].any()  # the identity map: zeros


def test_folded_projections_equal_the_projections_of_the_features():
    """``Aᵀ vec(D D_r⁻¹)`` and ``||vec(D D_r⁻¹)||²`` from the folded maps, never forming the gradients."""
    rinv = rest_inverse(REST, FACES)
    P = np.matmul(rinv, rinv.transpose(0, 2, 1))
    A = np.random.default_rng(2).standard_normal((18, 4))
    Mx, Mc = fold_directions(A, rinv, FACES, len(VERTS))
    assert Mx.shape == (12, 4) and Mc.shape == (6, 4)
    MxT, McT = coordinate_major(Mx, len(VERTS)), coordinate_major(Mc, 2)
    y = np.stack([np.tile(M.ravel(), 2) for M in MAPS])  # uncentred features (3, 18)
    np.testing.assert_allclose(mouth_coefficients(_frames(), VERTS, FACES, MxT, McT), y @ A, atol=1e-12)
    Z, sq = mouth_terms(_frames(), VERTS, FACES, MxT, McT, P)
    np.testing.assert_allclose(Z, y @ A, atol=1e-12)
    np.testing.assert_allclose(sq, [2 * np.sum(M * M) for M in MAPS], rtol=1e-12)  # 2 triangles x ||s Q||² = 6 s²


def test_as_frames_views_float_frames_and_names_bad_ones():
    f32 = _frames().astype(np.float32)
    assert as_frames(f32, 5, "frames") is f32  # no copy
    one = as_frames(f32[0], 5, "frames")
    assert one.shape == (1, 5, 3) and np.shares_memory(one, f32)
    assert as_frames(_frames().astype(int), 5, "frames").dtype == np.float64
    bad = _frames()
    bad[1, 4, 0] = np.nan  # vertex 4 is outside the patch: only the used vertices are checked
    assert as_frames(bad, 5, "frames", used=VERTS) is bad
    with pytest.raises(MeshError, match=r"frames \[1\]"):
        as_frames(bad, 5, "frames")
    with pytest.raises(MeshError, match="topology differs"):
        as_frames(bad, 4, "frames")
    with pytest.raises(FaceLabError, match="0 frames"):
        as_frames(np.zeros((0, 5, 3)), 5, "frames")
