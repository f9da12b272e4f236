"""The reduced ridge regression (core/lips/regressor/reduced.py) against closed forms and brute force."""

import numpy as np
import pytest

from facelab_addon.core.lips.regressor.reduced import (
    choose_ridge,
    loo_residuals,
    loo_span_residuals,
    solve_theta,
    thin_svd,
)


def test_solve_theta_is_the_ridge_closed_form_on_a_2x3_problem():
    """θ̄ (C_Y C_Yᵀ + λ' I) = C_X C_Yᵀ, λ' = λ · mean diag(C_Y C_Yᵀ), worked by hand for a 2x3 C_Y."""
    CY = np.array([[1.0, 0.0, 1.0], [0.0, 2.0, 1.0]])  # C_Y C_Yᵀ = [[2, 1], [1, 5]], mean diag 3.5
    CX = np.array([[3.0, 4.0, 5.0]])  # C_X C_Yᵀ = [[8, 13]]
    # λ = 0: θ̄ = [8, 13] [[2, 1], [1, 5]]⁻¹ = [8, 13] [[5, -1], [-1, 2]] / 9 = [27, 18] / 9
    np.testing.assert_allclose(solve_theta(CY, CX, 0.0), [[3.0, 2.0]], rtol=1e-12)
    # λ = 2/7: λ' = 1, A = [[3, 1], [1, 6]], A⁻¹ = [[6, -1], [-1, 3]] / 17: θ̄ = [35, 31] / 17
    np.testing.assert_allclose(solve_theta(CY, CX, 2.0 / 7.0), [[35 / 17, 31 / 17]], rtol=1e-12)


def test_the_free_rows_are_not_penalized():
    """With ``free=1`` the last row (an intercept) is neither shrunk nor counted in the mean diagonal."""
    CY = np.array([[1.0, -1.0, 2.0], [1.0, 1.0, 1.0]])  # C_Y C_Yᵀ = [[6, 2], [2, 3]]; penalised mean: 6
    CX = np.array([[1.0, 0.0, 4.0]])  # C_X C_Yᵀ = [[9, 5]]
    # λ = 0.5: λ' = 3 on the first row only: A = [[9, 2], [2, 3]], A⁻¹ = [[3, -2], [-2, 9]] / 23
    np.testing.assert_allclose(solve_theta(CY, CX, 0.5, free=1), [[17 / 23, 27 / 23]], rtol=1e-12)
    assert solve_theta(np.zeros((0, 3)), CX, 0.0).shape == (1, 0)  # no mouth rank: an empty map


def test_loo_residuals_equal_brute_force_leave_one_out():
    rng = np.random.default_rng(3)
    CY, CX = rng.standard_normal((3, 6)), rng.standard_normal((2, 6))
    for lam in (0.0, 0.1):
        want = np.empty((2, 6))
        for i in range(6):
            keep = np.arange(6) != i
            A = CY[:, keep] @ CY[:, keep].T
            A += lam * np.mean(np.diag(A)) * np.eye(3)
            th = np.linalg.solve(A, CY[:, keep] @ CX[:, keep].T).T
            want[:, i] = th @ CY[:, i] - CX[:, i]
        np.testing.assert_allclose(loo_residuals(CY, CX, lam), want, rtol=1e-10, atol=1e-12)
    np.testing.assert_array_equal(loo_residuals(CY[:, :1], CX[:, :1], 0.0), -CX[:, :1])  # one frame: minus it


def test_loo_span_residuals_are_distances_from_the_other_columns():
    """Columns e1, e2 and e1 + e2 + e3 of R³: e1 is (1/2, 0, -1/2) away from span{e2, e1 + e3} (squared: 1/2),
    e2 likewise, and e1 + e2 + e3 is e3 away from span{e1, e2} (squared: 1)."""
    C = np.array([[1.0, 0.0, 1.0], [0.0, 1.0, 1.0], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose(loo_span_residuals(C), [0.5, 0.5, 1.0], atol=1e-12)
    C2 = np.array([[3.0, 6.0], [4.0, 8.0]])  # parallel columns: 0; one column alone: its squared norm
    np.testing.assert_allclose(loo_span_residuals(C2), [0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(loo_span_residuals(C2[:, :1]), [25.0])


def test_thin_svd_reconstructs_and_cuts_round_off_directions():
    rng = np.random.default_rng(0)
    M = rng.standard_normal((18, 2)) @ rng.standard_normal((2, 4))  # rank 2, k = 4, two triangles
    M[:, 3] += 1e-13 * rng.standard_normal(18)  # round-off: below the absolute cut
    U, C = thin_svd(M, "rest", 1e-4, 1e-4)
    assert U.shape == (18, 2) and C.shape == (2, 4)
    np.testing.assert_allclose(U.T @ U, np.eye(2), atol=1e-10)
    np.testing.assert_allclose(U @ C, M, atol=1e-10)
    # frames in the rest pose: rank 0 centred (zeros), rank 1 uncentred (the identity gradients, the paper's y)
    ident = np.tile(np.eye(3).ravel(), 2)[:, None] * np.ones((1, 3))
    assert thin_svd(ident - ident, "rest", 1e-4, 1e-4)[0].shape[1] == 0
    U1, C1 = thin_svd(ident, None, 1e-4, 1e-4)
    np.testing.assert_allclose(U1 @ C1, ident, atol=1e-12)
    assert U1.shape[1] == 1


@pytest.mark.parametrize("noise, want_zero", [(0.0, True), (1.0, False)])
def test_choose_ridge_by_leave_one_out(noise, want_zero):
    """Exact linear data: no ridge beats λ = 0; pure noise outputs: shrinking helps, a λ > 0 is chosen."""
    rng = np.random.default_rng(1)
    CY = rng.standard_normal((3, 8))
    CX = (0.0 if noise else 1.0) * (rng.standard_normal((2, 3)) @ CY) + noise * rng.standard_normal((2, 8))
    lam = choose_ridge(CY, CX, "loo")
    assert (lam == 0.0) == want_zero
    assert choose_ridge(CY, CX, 0.25) == 0.25
    assert choose_ridge(CY[:, :2], CX[:, :2], "loo") == 0.0  # fewer than 3 frames
