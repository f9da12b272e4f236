"""Refine Lips' mouth-corner constraint (core, no bpy): where the upper and lower strokes' ends meet, the sketch
shows the mouth corner, and a capture whose corners were pulled in along the mouth (lost corner fleshiness,
``testing.route.ERRORS["corners"]``) is pulled back out to it. Ground truth: an ICT-FaceKit pose; sketches: its
inner-lip silhouettes.
"""

import numpy as np
import pytest

from facelab_addon.core.capture.camera import Camera
from facelab_addon.core.geometry.polyline import resample_polyline
from facelab_addon.core.lips import views as views_mod
from facelab_addon.core.lips.mouth import find_mouth
from facelab_addon.core.lips.sketch import refine_lips_views
from facelab_addon.core.lips.views import SketchView, _mouth_corners, _stroke_ends
from facelab_addon.testing import synthetic as S


def _corners(upper, lower):  # on the matcher's 1 px samples
    upper, lower = resample_polyline(np.asarray(upper, float), 1.0), resample_polyline(np.asarray(lower, float), 1.0)
    return _mouth_corners(upper, lower, _stroke_ends(upper), _stroke_ends(lower))


def _lips(scale=1.0, gap=0.0):
    x = np.linspace(-100, 100, 201)
    up = np.c_[x, 300 - 20 * (1 - (x / 100) ** 2) - gap]
    lo = np.c_[x, 300 + 25 * (1 - (x / 100) ** 2) + gap]
    return scale * up, scale * lo


@pytest.mark.parametrize("scale", [0.5, 1.0, 4.0])
def test_meeting_stroke_ends_are_the_mouth_corners_at_any_scale(scale):
    up, lo = _lips(scale)
    axis, corners = _corners(up, lo)
    assert np.allclose(np.abs(axis), [1, 0], atol=1e-6)
    assert [c[0] for c in corners] == [-1.0, 1.0]
    assert np.allclose(corners[0][1], scale * np.array([-100, 300]), atol=0.5)
    assert np.allclose(corners[1][1], scale * np.array([100, 300]), atol=0.5)


def test_stroke_ends_that_do_not_meet_give_no_corner():
    up, lo = _lips(gap=12.0)  # the mouth drawn open at the corners: ends 24 px apart, 12 % of its width
    assert _corners(up, lo)[1] == []
    up, lo = _lips()
    _, corners = _corners(up, lo[:150])  # the lower lip drawn only partly: its right end is far from the upper's
    assert [c[0] for c in corners] == [-1.0]


def _corner_error(T, F, fixed, mm, mouth, size_mm=1.25, radius_mm=8.0):
    """The capture of ``testing.route.ERRORS['corners']``: the skin near each corner pulled in along the mouth."""
    c = np.minimum(*(np.linalg.norm(T - T[k], axis=1) for k in mouth.corners))
    w = np.clip(1 - (c / (radius_mm * mm)) ** 2, 0, 1) ** 2 * ~fixed
    inward = -np.sign((T - mouth.center) @ mouth.lateral)
    return T + (inward * w * size_mm * mm)[:, None] * mouth.lateral, w


@pytest.fixture(scope="module")
def corner_case(ict):
    F = ict.faces
    fixed = ~ict.part_vertex_mask("M_Face")
    mm = 0.1 * ict.scale
    T = ict.pose({"jawOpen": 0.15})
    mouth = find_mouth(T, F, fixed, units_per_mm=mm)
    C, w = _corner_error(T, F, fixed, mm, mouth)
    cam = Camera.look_at(mouth.center + 40.0 * ict.scale * mouth.forward, mouth.center, mouth.up, 50, 36, 1920, 1080)
    view = SketchView(cam, *S.lip_contours(T, F, cam, mouth=mouth, margin_mm=3.0))
    il = S.inner_lip_mask(T, F, fixed, mouth=mouth)
    return dict(F=F, fixed=fixed, mm=mm, T=T, C=C, view=view, region=il & (w > 0.05))


def _rms(c, X):
    return np.sqrt((np.linalg.norm(X - c["T"], axis=1)[c["region"]] ** 2).mean()) / c["mm"]


def test_the_sketched_corners_pull_the_corners_back_out(corner_case, monkeypatch):
    c = corner_case
    assert len(_corners(c["view"].upper, c["view"].lower)[1]) == 2
    with_corners = refine_lips_views(c["C"], c["F"], [c["view"]], fixed=c["fixed"])
    monkeypatch.setattr(views_mod, "CORNER_WEIGHT", 0.0)
    without = refine_lips_views(c["C"], c["F"], [c["view"]], fixed=c["fixed"])
    cap, a, b = _rms(c, c["C"]), _rms(c, with_corners), _rms(c, without)
    print(f"corner-region RMS mm: capture {cap:.4f}, without corners {b:.4f}, with {a:.4f}")
    assert a < b - 0.05 * cap  # the corner constraint removes at least 5 % more of the capture's corner error


def test_an_error_free_capture_keeps_its_corners(corner_case, monkeypatch):
    c = corner_case
    X = refine_lips_views(c["T"], c["F"], [c["view"]], fixed=c["fixed"])
    monkeypatch.setattr(views_mod, "CORNER_WEIGHT", 0.0)
    Y = refine_lips_views(c["T"], c["F"], [c["view"]], fixed=c["fixed"])
    assert np.linalg.norm(X - Y, axis=1).max() / c["mm"] < 0.02  # the corners already where the sketch shows them
