"""Sealed lips drawn on one line (core.lips.contact) and the Refine error zoo (testing.error_zoo)."""

import numpy as np
import pytest

from facelab_addon.core.lips.contact import contact_terms, one_line


def _line(x0, x1, y):
    x = np.arange(x0, x1 + 1.0)
    return np.c_[x, np.full(len(x), float(y))]


def test_one_line_finds_the_shared_stretch_only():
    up = _line(0, 200, 100.0)
    lo = _line(0, 200, 100.0)
    lo[:80, 1] += 12.0  # apart on the left, on one line from x = 80 on
    p = one_line(up, lo, width=200.0)
    assert (p[:78] == -1).all()
    assert (p[81:] >= 0).all()
    np.testing.assert_allclose(lo[p[81:], 0], up[81:, 0], atol=1.0)


def test_one_line_ignores_lines_apart_and_a_short_crossing():
    up = _line(0, 200, 100.0)
    assert (one_line(up, _line(0, 200, 106.0), width=200.0) == -1).all()
    lo = _line(0, 200, 110.0)
    lo[100:104, 1] = 100.0  # touches over 4 px (< 5 % of the width): not a contact
    assert (one_line(up, lo, width=200.0) == -1).all()


def test_contact_terms_pair_the_lips_with_sample_counts():
    partner = np.array([-1, 0, 1, 2, -1])
    up_v = np.array([5, 6, 6, 7, 8])
    lo_v = np.array([10, 10, 11])
    c = contact_terms(up_v, lo_v, partner, 2.0)
    rows = {tuple(v): s for v, s in zip(c.vertices.tolist(), c.strength)}
    assert rows == {(6, 10): 4.0, (7, 11): 2.0}  # (6,10) made by samples 1 and 2 (partner 0 and 1 -> 10, 10)
    np.testing.assert_allclose(c.bary, [[1.0, -1.0]] * 2)
    np.testing.assert_allclose(c.targets, 0.0)
    assert contact_terms(up_v, lo_v, np.full(5, -1), 1.0) is None


def test_error_families_are_confined_to_their_reach(ict_zoo):
    from scipy.spatial import cKDTree

    from facelab_addon.testing import error_zoo as Z

    zf = ict_zoo
    T = zf.pose(Z.POSES["sealed"])
    d, _ = cKDTree(T[zf.loop]).query(T)
    for case in Z.sample_cases(list(Z.FAMILIES), 1, seed=3):
        e = np.linalg.norm(Z.error_field(zf, T, case), axis=1) / zf.unit_mm
        assert e.max() > 0.3 * case.amount_mm, case.family
        if case.family != "corners":  # corners: within reach of the corners, which lie on the contact line
            assert e[d > case.reach_mm * zf.unit_mm].max() == 0.0, case.family
        assert e[zf.fixed].max() == 0.0


def test_limit_and_gap_measures(ict_zoo):
    from facelab_addon.testing import error_zoo as Z

    zf = ict_zoo
    case = next(c for c in Z.sample_cases(["gap"], 3, seed=0) if c.pose == "sealed")
    mc = Z.make_case(zf, case)
    band = Z.lip_band(zf, mc.truth)
    assert Z.best_possible_cut_pct(mc.capture, mc.truth, band, np.ones(len(band), bool), zf.faces) == \
        pytest.approx(100.0)
    assert Z.best_possible_cut_pct(mc.capture, mc.truth, band, np.zeros(len(band), bool), zf.faces) == \
        pytest.approx(0.0)
    pairs = Z.contact_pairs_of(zf, mc.truth)
    # the gap error parts the sealed lips: the contact pairs are farther apart in the capture
    assert Z.contact_gap(mc.capture, pairs) - Z.contact_gap(mc.truth, pairs) > 0.5 * case.amount_mm * zf.unit_mm
    assert mc.one_line_px[0] > 20  # where the sealed lips touch in the image, they are drawn on one line


def test_contact_pulls_sealed_lips_together_in_3d(ict_zoo):
    from facelab_addon.core.lips.refine_params import RefineParams
    from facelab_addon.core.lips.sketch import refine_lips_views
    from facelab_addon.core.lips.views import SketchView
    from facelab_addon.testing import error_zoo as Z

    zf = ict_zoo
    case = next(c for c in Z.sample_cases(["gap"], 3, seed=0) if c.pose == "sealed")
    mc = Z.make_case(zf, case)
    pairs = Z.contact_pairs_of(zf, mc.truth)
    views = [SketchView(mc.cameras[0], *mc.strokes[0])]
    gaps = {}
    for w in (0.0, 1.0):
        X, info = refine_lips_views(mc.capture, zf.faces, views, RefineParams(contact=w), fixed=zf.fixed,
                                    lips=zf.lips, return_info=True)
        gaps[w] = Z.contact_gap(X, pairs)
        assert np.linalg.norm(X - mc.capture, axis=1)[~zf.lips].max() == 0.0
    assert info["one_line_samples"][0] > 20
    assert gaps[1.0] < gaps[0.0]  # the contact term brings the lips closer along the contact


def test_fit_span_recovers_a_known_mix_from_ray_terms():
    from facelab_addon.core.geometry.deform import PointConstraints
    from facelab_addon.core.lips.span_prior import fit_span

    rng = np.random.default_rng(0)
    n, S = 40, 3
    X0 = rng.normal(size=(n, 3))
    U = rng.normal(size=(n, 3, S))
    a_true = np.array([0.3, -0.2, 0.5])
    T = X0 + U @ a_true
    # two rays through every target point (each sees it across its own direction only)
    d1 = rng.normal(size=(n, 3))
    d2 = rng.normal(size=(n, 3))
    cons = lambda X: [PointConstraints.rays(np.arange(n), T - 5 * d, d) for d in (d1, d2)]  # noqa: E731
    X, a = fit_span(X0, U, cons, iterations=2, reg=1e-9)
    np.testing.assert_allclose(a, a_true, atol=1e-6)
    np.testing.assert_allclose(X, T, atol=1e-6)
    _, a_reg = fit_span(X0, U, cons, iterations=2, reg=10.0)
    assert np.linalg.norm(a_reg) < np.linalg.norm(a_true)  # the ridge keeps the mix small


def test_basis_start_moves_only_the_inside_of_the_lip_region(ict_zoo):
    from facelab_addon.core.lips.refine_params import RefineParams
    from facelab_addon.core.lips.sketch import refine_lips_views
    from facelab_addon.core.lips.views import SketchView
    from facelab_addon.core.lips.span_prior import taper
    from facelab_addon.core.lips.views import SketchView
    from facelab_addon.testing import error_zoo as Z

    zf = ict_zoo
    case = next(c for c in Z.sample_cases(["gap"], 3, seed=0) if c.pose == "sealed")
    mc = Z.make_case(zf, case)
    X, info = refine_lips_views(mc.capture, zf.faces, [SketchView(mc.cameras[0], *mc.strokes[0])],
                                RefineParams(basis_reg=1.0), fixed=zf.fixed, lips=zf.lips, basis=mc.basis(zf),
                                return_info=True)
    assert np.abs(info["span_weights"]).max() > 0
    assert np.linalg.norm(X - mc.capture, axis=1)[~zf.lips].max() == 0.0
    w = taper(mc.capture, zf.faces, info["region"])
    assert w[~info["region"]].max() == 0.0 and w.max() == pytest.approx(1.0)


def test_refine_keeps_the_truth_under_its_own_clean_sketch(ict_zoo):
    """The zoo's sketch is the truth's silhouettes as Refine reads them: refined from the truth, the lips stay."""
    import dataclasses

    from facelab_addon.core.lips.sketch import refine_lips_views
    from facelab_addon.core.lips.views import SketchView
    from facelab_addon.testing import error_zoo as Z

    zf = ict_zoo
    for case in Z.sample_cases(["roll"], 1, seed=0) + Z.sample_cases(["gap"], 1, seed=0):
        case = dataclasses.replace(case, noise_px=0.0, end_px=(0.0, 0.0, 0.0, 0.0), pieces=1)
        mc = Z.make_case(zf, case)
        band = Z.lip_band(zf, mc.truth)
        X = refine_lips_views(mc.truth, zf.faces, [SketchView(mc.cameras[0], *mc.strokes[0])], fixed=zf.fixed,
                              lips=zf.lips, rest_vertices=mc.rest)
        assert Z.rms_mm(X, mc.truth, band, zf.unit_mm) < 0.08, case.pose
