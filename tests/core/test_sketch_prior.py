"""Refine Lips beyond the paper's energy (core, no bpy): the smooth prior, settings in mouth widths
(scale and resolution independent), the painted lip region, several views, the safe default for
separate mesh parts. ICT cases are the benchmark's (``benchmarks/sketch_refine.py``): truth = an ICT
pose, sketch = its inner-lip silhouettes, capture = truth + a smooth inner-lip error."""

import numpy as np
import pytest

from facelab_addon.core.capture.camera import Camera
from facelab_addon.core.errors import FaceLabError
from facelab_addon.core.lips.mouth import find_mouth
from facelab_addon.core.lips.regions import auto_regions
from facelab_addon.core.lips.refine_params import RefineParams
from facelab_addon.core.lips.sketch import refine_lips, refine_lips_views
from facelab_addon.core.lips.views import SketchView
from facelab_addon.core.lips.sketch_prior import (
    BAND_RINGS,
    anchor_weights,
    free_region,
    mean_edge_length,
    separate_parts,
)
from facelab_addon.core.lips.views import SketchView
from facelab_addon.testing import synthetic as S

from .lipmesh import front_camera, line_px, tube, two_lips

CLOSED = {"mouthPress_L": 0.25, "mouthPress_R": 0.25}


@pytest.fixture(scope="module")
def closed(ict):
    F = ict.faces
    fixed = ~ict.part_vertex_mask("M_Face")
    mm = 0.1 * ict.scale
    T = ict.pose(CLOSED)
    mouth = find_mouth(T, F, fixed, units_per_mm=mm)
    cam = S.frontal_camera(T, mouth.center, distance=40.0 * ict.scale)
    up, lo = S.lip_contours(T, F, cam, mouth=mouth)
    return dict(F=F, fixed=fixed, mm=mm, T=T, mouth=mouth, cam=cam, up=up, lo=lo)


def rms(X, T, mask, mm):
    return np.sqrt((np.linalg.norm(X - T, axis=1)[mask] ** 2).mean()) / mm


def test_smooth_prior_corrects_a_wide_lip_error_better_than_the_papers(closed):
    c = closed
    C, _ = S.inject_lip_error(c["T"], c["F"], c["fixed"], mouth=c["mouth"], radius_mm=12.0)
    lip = S.inner_lip_mask(c["T"], c["F"], c["fixed"], mouth=c["mouth"], radius_mm=12.0)
    e0 = rms(C, c["T"], lip, c["mm"])
    cut = {}
    for prior in ("paper", "smooth"):
        X, info = refine_lips(C, c["F"], c["cam"], c["up"], c["lo"], RefineParams(prior=prior), fixed=c["fixed"],
                              return_info=True)
        cut[prior] = 1 - rms(X, c["T"], lip, c["mm"]) / e0
        assert info["silhouette_px"][-1] < 0.5 * info["silhouette_px"][0]  # on the sketch in both
        assert np.abs(X - C)[c["fixed"]].max() < (1e-12 if prior == "smooth" else 1e-3)  # hidden parts held
    assert cut["smooth"] >= 0.5, cut  # measured 0.576 (paper 0.448)
    assert cut["smooth"] > cut["paper"] + 0.08, cut


def test_without_fixed_separate_teeth_are_held_and_never_matched(closed, ict):
    c = closed
    C, _ = S.inject_lip_error(c["T"], c["F"], c["fixed"], mouth=c["mouth"])
    lip = S.inner_lip_mask(c["T"], c["F"], c["fixed"], mouth=c["mouth"])
    X, info = refine_lips(C, c["F"], c["cam"], c["up"], c["lo"], return_info=True)  # no 'fixed'
    parts = ict.part_vertex_mask("M_Teeth") | ict.part_vertex_mask("M_GumsTongue")
    assert np.abs(X - C)[parts].max() == 0.0
    matched = np.r_[info["matched_upper"], info["matched_lower"]]
    assert not parts[matched].any()
    assert rms(X, c["T"], lip, c["mm"]) < 0.6 * rms(C, c["T"], lip, c["mm"])
    np.testing.assert_array_equal(separate_parts(c["F"], len(C)), ~(ict.part_vertex_mask("M_Face")
                                                                       | ict.part_vertex_mask("M_BackHead")))


def test_painted_lip_region_moves_only_its_inside(closed, ict):
    c = closed
    C, _ = S.inject_lip_error(c["T"], c["F"], c["fixed"], mouth=c["mouth"])
    mouth_r, lips = auto_regions(ict.neutral, c["F"])  # Auto Regions on the rest pose, as the pipeline does
    X = refine_lips(C, c["F"], c["cam"], c["up"], c["lo"], fixed=c["fixed"], lips=lips)
    inside = lips[c["F"]].all(axis=1)
    border = np.zeros(len(C), bool)
    border[c["F"][~inside].ravel()] = True
    moved = np.linalg.norm(X - C, axis=1)
    assert moved[~lips | border].max() == 0.0  # FL_mouth shares only the border ring with FL_lips: held
    assert moved[mouth_r].max() == 0.0
    assert moved[lips].max() > 0.5 * c["mm"]  # the lips did move (the gap is 1.25 mm per lip)


def test_two_views_fix_depth_one_view_cannot_see(closed):
    c = closed
    T, F, mouth, mm = c["T"], c["F"], c["mouth"], c["mm"]
    w, side = S.lip_error_weights(T, F, c["fixed"], mouth=mouth)
    lip = w > 1e-3
    C = T + (1.25 * mm * w * side)[:, None] * mouth.up + (2.0 * mm * w)[:, None] * mouth.forward
    e = np.radians(20.0)
    d = np.cos(e) * mouth.forward - np.sin(e) * mouth.up
    below = Camera.look_at(mouth.center + 40.0 * d, mouth.center, mouth.up, 50, 36, 1920, 1080)
    one = SketchView(c["cam"], c["up"], c["lo"], "front")
    two = SketchView(below, *S.lip_contours(T, F, below, mouth=mouth, margin_mm=3.0), "below")  # the whole contour
    X1 = refine_lips_views(C, F, [one], fixed=c["fixed"])
    X2, info = refine_lips_views(C, F, [one, two], fixed=c["fixed"], return_info=True)
    e0, e1, e2 = rms(C, T, lip, mm), rms(X1, T, lip, mm), rms(X2, T, lip, mm)
    fwd = lambda X: np.sqrt(((((X - T)[lip]) @ mouth.forward) ** 2).mean()) / mm  # noqa: E731
    assert fwd(X1) > 0.95 * fwd(C)  # the frontal view cannot see the depth error (measured 1.00)
    assert fwd(X2) < 0.85 * fwd(C)  # the second view corrects part of it (measured 0.76)
    assert e2 < e1 - 0.1 * e0, (e0, e1, e2)  # measured cuts: one view 13.5 %, two views 30.7 %
    assert [v["name"] for v in info["views"]] == ["front", "below"]
    assert all(v["silhouette_px"] < 3.0 for v in info["views"])


def test_same_result_at_any_scale():
    V, F, _ = two_lips(gap=0.4)
    cam = front_camera()
    up, lo = line_px(cam, 0.1), line_px(cam, -0.1)
    res = {}
    for s in (0.01, 1.0, 100.0):
        cs = Camera(cam.K, cam.R, cam.t * s, cam.width, cam.height)  # the same view of the scaled scene
        for prior in ("smooth", "paper"):
            res[s, prior] = refine_lips(V * s, F, cs, up, lo, RefineParams(prior=prior),
                                        fixed=np.zeros(len(V), bool)) / s
    for prior in ("smooth", "paper"):
        np.testing.assert_allclose(res[0.01, prior], res[1.0, prior], atol=1e-7)
        np.testing.assert_allclose(res[100.0, prior], res[1.0, prior], atol=1e-7)
        assert np.abs(res[1.0, prior] - V).max() > 0.05  # the lips moved (0.1 drawn)


def test_smooth_prior_reach_is_in_scene_units_not_edge_rings():
    """The same surface at two densities: the smooth prior's anchor weights give the same decay length."""
    for nx, nt in ((31, 21), (61, 41)):
        V, F = tube(0.0, -np.pi / 2, np.pi / 2, 0.5, nx=nx, nt=nt)
        h = mean_edge_length(V, F)
        w = anchor_weights(V, F, np.ones(len(V), bool), prior="smooth", lambda_pos=0.1, lambda_reg=3.0, reach=0.5)
        # decay length (lambda_reg / w)^(1/4) edges times the edge length: the reach, in scene units
        inner = h > 0
        np.testing.assert_allclose(((3.0 / w[inner]) ** 0.25 * h[inner]), 0.5, rtol=1e-9)
    wp = anchor_weights(V, F, np.ones(len(V), bool), prior="paper", lambda_pos=0.1, lambda_reg=3.0)
    assert (wp == 0.1).all()
    with pytest.raises(FaceLabError):
        anchor_weights(V, F, np.ones(len(V), bool), prior="smooth", lambda_pos=0.1, lambda_reg=3.0)


def test_free_region_is_geodesic_and_respects_fixed_and_lips():
    V, F = tube(0.0, -np.pi / 2, np.pi / 2, 0.5, nx=41, nt=3, half_len=2.0)  # a strip along x, 0.1 apart
    seeds = np.abs(V[:, 0]) < 1e-9
    r = free_region(V, F, seeds, 0.5)
    assert set(np.round(np.unique(V[r, 0]), 6)) == set(np.round(np.arange(-0.5, 0.5001, 0.1), 6))
    fixed = V[:, 0] > 0.25
    assert not free_region(V, F, seeds, 0.5, fixed=fixed)[fixed].any()
    lips = np.abs(V[:, 0]) < 0.35  # inside: |x| <= 0.2 (x = +-0.3 is the border ring)
    rl = free_region(V, F, seeds, 0.5, lips=lips)
    assert np.abs(V[rl, 0]).max() == pytest.approx(0.2)


@pytest.fixture(scope="module")
def band_case(ict):
    """Auto Regions' FL_lips and a lip error of the open pose (the sketch benchmark's open_gap, 6 mm reach)."""
    F = ict.faces
    fixed = ~ict.part_vertex_mask("M_Face")
    mm = 0.1 * ict.scale
    T = ict.pose({"jawOpen": 0.2, "mouthFunnel": 0.3})
    mouth = find_mouth(T, F, fixed, units_per_mm=mm)
    cam = S.frontal_camera(T, mouth.center, distance=40.0 * ict.scale)
    up, lo = S.lip_contours(T, F, cam, mouth=mouth)
    C, _ = S.inject_lip_error(T, F, fixed, mouth=mouth)
    lip = S.inner_lip_mask(T, F, fixed, mouth=mouth)
    _, lips = auto_regions(ict.neutral, F)
    return dict(F=F, fixed=fixed, mm=mm, T=T, cam=cam, up=up, lo=lo, C=C, lip=lip, lips=lips)


def test_band_prior_on_a_dense_mesh_with_fl_lips(band_case):
    c = band_case
    e0 = rms(c["C"], c["T"], c["lip"], c["mm"])
    cut = {}
    for prior in ("paper", "smooth", "band"):
        X = refine_lips(c["C"], c["F"], c["cam"], c["up"], c["lo"], RefineParams(prior=prior), fixed=c["fixed"],
                        lips=c["lips"])
        cut[prior] = 1 - rms(X, c["T"], c["lip"], c["mm"]) / e0
        assert np.abs(X - c["C"])[~c["lips"]].max() == 0.0  # only the inside of FL_lips moves
    # measured: band 0.602, smooth 0.594, paper 0.613. On this dense mesh (1.5 mm edges) the two reaches nearly
    # agree; the coarse face is tests/pipeline/test_refine_route.py's remeshed route
    assert cut["band"] > cut["smooth"] + 0.004 and cut["band"] > 0.59, cut


def test_band_prior_reach_is_at_least_band_rings_edges_inside_the_lips(closed):
    c = closed
    C, _ = S.inject_lip_error(c["T"], c["F"], c["fixed"], mouth=c["mouth"])
    # without a lip region the band prior is the smooth one
    Xb = refine_lips(C, c["F"], c["cam"], c["up"], c["lo"], RefineParams(prior="band"), fixed=c["fixed"])
    Xs = refine_lips(C, c["F"], c["cam"], c["up"], c["lo"], RefineParams(prior="smooth"), fixed=c["fixed"])
    np.testing.assert_array_equal(Xb, Xs)
    V, F = c["T"], c["F"]
    region = ~c["fixed"]
    h = mean_edge_length(V, F)
    lips = region & (np.arange(len(V)) % 2 == 0)
    reach = 2.0 * np.median(h[region])
    w = anchor_weights(V, F, region, prior="band", lambda_pos=0.1, lambda_reg=3.0, reach=reach, lips=lips,
                       fixed=c["fixed"])
    ws = anchor_weights(V, F, region, prior="smooth", lambda_pos=0.1, lambda_reg=3.0, reach=reach, fixed=c["fixed"])
    np.testing.assert_array_equal(w[~lips], ws[~lips])
    expect = np.minimum(3.0 * (h / np.maximum(reach, BAND_RINGS * h)) ** 4, 0.1)
    np.testing.assert_allclose(w[lips], expect[lips])
    assert (w[lips] <= 3.0 / BAND_RINGS**4 + 1e-15).all() and (w[lips] < ws[lips]).any()
