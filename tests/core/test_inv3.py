"""The one closed-form 3x3 inverse (``core.geometry.inv3``) against hand-computed inverses."""

import warnings

import numpy as np

from facelab_addon.core.geometry.inv3 import inv3


def test_hand_computed_inverses_and_determinants():
    A = np.array([[[2.0, 0, 0], [0, 3, 0], [0, 0, 4]],
                  [[1.0, 2, 3], [0, 1, 4], [5, 6, 0]]])
    want = np.array([[[0.5, 0, 0], [0, 1 / 3, 0], [0, 0, 0.25]],
                     [[-24.0, 18, 5], [20, -15, -4], [-5, 4, 1]]])
    inv, det = inv3(A, return_det=True)
    np.testing.assert_allclose(inv, want, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(det, [24.0, 1.0])
    np.testing.assert_allclose(inv3(A), want, rtol=0, atol=1e-15)


def test_any_leading_shape_and_the_identity():
    rng = np.random.default_rng(1)
    A = rng.normal(size=(2, 5, 3, 3)) + 3 * np.eye(3)
    inv = inv3(A)
    assert inv.shape == (2, 5, 3, 3)
    np.testing.assert_allclose(inv @ A, np.broadcast_to(np.eye(3), A.shape), atol=1e-12)
    np.testing.assert_allclose(inv, np.linalg.inv(A), rtol=1e-12, atol=1e-14)


def test_singular_matrix_gives_non_finite_entries_without_a_warning():
    A = np.array([[[1.0, 2, 3], [2, 4, 6], [0, 0, 1]]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        inv, det = inv3(A, return_det=True)
    assert det[0] == 0.0 and not np.isfinite(inv).all()
