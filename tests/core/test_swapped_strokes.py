"""Strokes on swapped layers (core.lips.swapped_strokes): refused for an open mouth, never for lips that overlap
in the image along the whole mouth (sealed lips seen from well below, issue 25's oracle views)."""

import numpy as np
import pytest

from facelab_addon.core.errors import SketchError
from facelab_addon.core.lips.swapped_strokes import check_swapped_strokes

X = np.linspace(-200.0, 200.0, 401)  # a mouth 400 px wide
T = X / 200.0
ARC = 500.0 + 50.0 * T**2  # the mouth's line, seen from below: its middle higher in the image (y down)
COLS = np.linspace(-160.0, 160.0, 64)  # the columns the check reads: the inner 80 % (as core.lips.views does)
TC = COLS / 200.0


def _at(y_of_t):
    return np.c_[X, y_of_t(T)]


def test_open_mouth_on_swapped_layers_is_refused():
    """An open mouth's contours meet at the corners; drawn on each other's layer they bound an upside-down lens."""
    up = lambda t: 500.0 + 50.0 * t**2 - 20.0 * (1 - t**2)  # noqa: E731
    lo = lambda t: 500.0 + 50.0 * t**2 + 20.0 * (1 - t**2)  # noqa: E731
    yu, yl = up(TC), lo(TC)  # the capture: the same open mouth
    check_swapped_strokes(_at(up), _at(lo), yu, yl, COLS)  # as drawn: fine
    with pytest.raises(SketchError, match=r"swapped layers.*Move each stroke to its layer"):
        check_swapped_strokes(_at(lo), _at(up), yu, yl, COLS)


def test_lips_overlapping_along_the_mouth_are_read_as_drawn():
    """Sealed lips seen from 30 degrees below: the truth's inner contours cross in an even band (7-11 px) while the
    capture holds the lips about 10 px apart. The strokes lie on the capture's other lip, the band is a little
    deeper in the middle (an upside-down sag of 4 px, more than a quarter of the gap), but it closes toward neither
    corner: correct layers (the oracle view 3 of the zoo's first ICT case was refused for this)."""
    band = lambda t: 7.0 + 4.0 * (1 - t**2)  # noqa: E731  (px: how far the upper stroke lies below the lower)
    lower = _at(lambda t: 500.0 + 50.0 * t**2)
    upper = _at(lambda t: 500.0 + 50.0 * t**2 + band(t))
    yu = 500.0 + 50.0 * TC**2 - 1.0  # the capture's upper lip just above the lower stroke
    yl = 500.0 + 50.0 * TC**2 + band(TC) + 1.0  # its lower lip just below the upper stroke
    assert check_swapped_strokes(upper, lower, yu, yl, COLS) == ""


@pytest.mark.parametrize("depth_px, refused", [(11.0, False), (30.0, True)])
def test_a_shallow_upside_down_lens_warns_a_deep_one_is_refused(depth_px, refused):
    """A crossing that closes at both corners is an upside-down lens: the strokes of an open mouth on swapped
    layers, or lips overlapping a little in the middle of the mouth in this view. Under SURE_DEPTH of the mouth's
    width (20 px here) it is refined as drawn with a warning naming both readings; deeper, it is refused."""
    lens = lambda t: depth_px * (1 - t**2)  # noqa: E731
    lower = _at(lambda t: 500.0 + 50.0 * t**2)
    upper = _at(lambda t: 500.0 + 50.0 * t**2 + lens(t))
    yu = 500.0 + 50.0 * TC**2 - 1.0
    yl = 500.0 + 50.0 * TC**2 + lens(TC) + 1.0
    if refused:
        with pytest.raises(SketchError, match=r"swapped layers.*Move each stroke to its layer"):
            check_swapped_strokes(upper, lower, yu, yl, COLS, " in view 'cam'")
    else:
        msg = check_swapped_strokes(upper, lower, yu, yl, COLS, " in view 'cam'")
        assert "in view 'cam'" in msg and "overlap" in msg and "swapped layers" in msg and "Refined as drawn" in msg


def test_clean_sketch_from_below_sealed_lips_is_not_refused(ict_zoo):
    """The zoo's first ICT case (sealed lips held apart in the capture) drawn exactly from 30 degrees below its
    camera: the truth's contours cross over the whole mouth, correctly layered; the view is accepted, and the same
    sketch of the case's open-mouth sibling on swapped layers is still refused."""
    from facelab_addon.core.lips.views import SketchView, ViewMatcher
    from facelab_addon.testing import error_zoo as Z

    zf = ict_zoo
    case = Z.sample_cases(list(Z.FAMILIES), 3, seed=0)[0]
    assert (case.family, case.pose) == ("gap", "sealed")
    mc = Z.make_case(zf, case)
    c = mc.truth[zf.loop].mean(axis=0)
    cam = Z.zoo_camera(zf, c, case.azim, case.elev - 30.0, case.lens_mm, case.distance_cm)
    up, lo, _ = Z.truth_sketch(zf, mc.truth, cam)
    assert np.median(up[:, 1] - lo[:, 1]) > 4.0  # the truth's contours do cross in this view
    assert ViewMatcher(SketchView(cam, up, lo), mc.capture, zf.faces, zf.fixed).warning == ""
    # an open mouth (the zoo's "funnel" cases) drawn on swapped layers in its main view: refused
    case = next(k for k in Z.sample_cases(list(Z.FAMILIES), 3, seed=0) if k.pose == "funnel" and k.family == "cross")
    mc = Z.make_case(zf, case)
    up, lo, _ = Z.truth_sketch(zf, mc.truth, mc.cameras[0])
    with pytest.raises(SketchError, match="swapped layers"):
        ViewMatcher(SketchView(mc.cameras[0], lo, up), mc.capture, zf.faces, zf.fixed)


def test_a_shallow_swap_is_refined_with_the_warning_in_the_info(ict_zoo):
    """Nearly closed lips (the zoo's "corners" case on a neutral face, the capture's lips 1 % of the mouth's width
    apart) drawn on swapped layers: too shallow to tell from lips overlapping in the image, so Refine runs and its
    info carries the warning (the pipeline reports it)."""
    from facelab_addon.core.lips.sketch import refine_lips_views
    from facelab_addon.core.lips.views import SketchView
    from facelab_addon.testing import error_zoo as Z

    zf = ict_zoo
    case = Z.sample_cases(list(Z.FAMILIES), 3, seed=0)[6]
    assert (case.family, case.pose) == ("corners", "neutral")
    mc = Z.make_case(zf, case)
    up, lo, _ = Z.truth_sketch(zf, mc.truth, mc.cameras[0])
    _, info = refine_lips_views(mc.capture, zf.faces, [SketchView(mc.cameras[0], up, lo)], fixed=zf.fixed,
                                return_info=True)
    assert info["warnings"] == []
    _, info = refine_lips_views(mc.capture, zf.faces, [SketchView(mc.cameras[0], lo, up)], fixed=zf.fixed,
                                return_info=True)
    assert len(info["warnings"]) == 1 and "swapped layers" in info["warnings"][0]
