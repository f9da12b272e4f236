"""SketchSolver (core, no bpy): one face re-solved as its strokes change gives refine_lips_views' result.

The small two-tube mouth of ``lipmesh`` seen from the front (and, for two views, from below); the reference
is :func:`refine_lips_views` on the same strokes, solved from scratch.
"""

import numpy as np
import pytest

from facelab_addon.core.capture.camera import Camera
from facelab_addon.core.errors import UsageError
from facelab_addon.core.lips.refine_params import RefineParams
from facelab_addon.core.lips.sketch import refine_lips_views
from facelab_addon.core.lips.sketch_session import SketchSolver
from facelab_addon.core.lips.views import SketchView

from .lipmesh import front_camera, line_px, two_lips


@pytest.fixture(scope="module")
def mouth():
    V, F, upper = two_lips()
    return V, F, np.zeros(len(V), bool)


def _rel(a, b):
    return np.abs(a - b).max() / np.abs(b).max()


CASES = {
    "paper": dict(prior="paper"),
    "band_lips_contact": dict(contact=1.0, lips="inner"),
    "press": dict(crossings="press", prior="smooth"),
    "two_views": dict(views=2),
}


def _views(n, up_y=0.1, lo_y=-0.1):
    cam = front_camera()
    out = [SketchView(cam, line_px(cam, up_y), line_px(cam, lo_y), name="front")]
    if n == 2:
        low = Camera.look_at([0, -8, 18], [0, 0, 0], [0, 1, 0], 50, 36, 1920, 1080)
        out.append(SketchView(low, line_px(low, up_y), line_px(low, lo_y), name="low"))
    return out


@pytest.mark.parametrize("case", sorted(CASES))
def test_a_solve_is_refine_lips_views(mouth, case):
    V, F, fixed = mouth
    kw = dict(CASES[case])
    views = _views(kw.pop("views", 1))
    lips = np.abs(V[:, 0]) < 1.8 if kw.pop("lips", None) == "inner" else None
    params = RefineParams(**kw)
    ref, info_ref = refine_lips_views(V, F, views, params, fixed=fixed, lips=lips, return_info=True)
    solver = SketchSolver(V, F, params, fixed=fixed, lips=lips)
    X, info = solver.solve(views, return_info=True)
    assert np.abs(ref - V).max() > 0.05  # the strokes move the lips: the comparison is not of the capture
    assert _rel(X, ref) <= 1e-9
    assert np.allclose(info["silhouette_px"], info_ref["silhouette_px"], rtol=1e-9)
    assert (info["region"] == info_ref["region"]).all()


def test_a_second_solve_with_one_more_stroke_is_a_fresh_solve(mouth):
    V, F, fixed = mouth
    cam = front_camera()
    up, lo = line_px(cam, 0.1, -1.5, 0.0), line_px(cam, -0.1)
    solver = SketchSolver(V, F, fixed=fixed)
    X1 = solver.solve([SketchView(cam, [up], lo)])
    assert _rel(X1, refine_lips_views(V, F, [SketchView(cam, [up], lo)], fixed=fixed)) <= 1e-9
    more = [up, line_px(cam, 0.12, 0.2, 1.5)]  # the upper lip's other half, drawn as a second stroke
    X2, info = solver.solve([SketchView(cam, more, lo)], return_info=True)
    fresh = refine_lips_views(V, F, [SketchView(cam, more, lo)], fixed=fixed)
    assert _rel(X2, fresh) <= 1e-9
    assert np.abs(X2 - X1).max() > 1e-3  # the new stroke moved the lips
    assert info["rebuilt"] and solver.builds == 2  # it widened the sketch: a new free region and mouth width


def test_the_same_strokes_reuse_the_system(mouth):
    V, F, fixed = mouth
    views = _views(1)
    solver = SketchSolver(V, F, RefineParams(prior="paper"), fixed=fixed)
    X1 = solver.solve(views)
    X2, info = solver.solve(views, return_info=True)
    assert solver.builds == 1 and not info["rebuilt"]
    assert _rel(X2, X1) <= 1e-9


def test_an_edit_inside_the_sketch_keeps_the_system_within_width_tol(mouth):
    V, F, fixed = mouth
    cam = front_camera()
    up, lo = line_px(cam, 0.1), line_px(cam, -0.1)
    edited = up.copy()
    edited[14:17, 1] += 1.0  # three points of the upper stroke moved 1 px down
    edited[-1, 0] += 0.05  # and its end 0.05 px out: the sketch's width changes by about 1e-4
    exact = SketchSolver(V, F, fixed=fixed)
    tolerant = SketchSolver(V, F, fixed=fixed, width_tol=1e-3)
    for s in (exact, tolerant):
        s.solve([SketchView(cam, up, lo)])
    X_exact, i_exact = exact.solve([SketchView(cam, edited, lo)], return_info=True)
    X_tol, i_tol = tolerant.solve([SketchView(cam, edited, lo)], return_info=True)
    fresh = refine_lips_views(V, F, [SketchView(cam, edited, lo)], fixed=fixed)
    assert i_exact["rebuilt"] and not i_tol["rebuilt"]  # the edit moved the mouth width
    assert _rel(X_exact, fresh) <= 1e-9
    assert np.abs(cam.project(X_tol) - cam.project(fresh)).max() < 0.05  # pixels


@pytest.mark.parametrize("iterations", [1, 2, 5, 8])
def test_stopping_at_a_repeated_matching_keeps_the_result(mouth, iterations):
    """The iterations end where ``iterations`` single steps, each matched on the last one's result, end."""
    V, F, fixed = mouth
    views = _views(1)
    X = SketchSolver(V, F, RefineParams(prior="paper", iterations=iterations), fixed=fixed).solve(views)
    step = SketchSolver(V, F, RefineParams(prior="paper", iterations=1), fixed=fixed)
    Y = V
    for _ in range(iterations):
        Y = step.solve(views, start=Y)
    assert _rel(X, Y) <= 1e-9
    assert np.abs(X - V).max() > 0.05


def test_the_iterations_stop_once_the_matching_repeats(mouth):
    V, F, fixed = mouth
    _, info = SketchSolver(V, F, RefineParams(prior="paper", iterations=20),
                           fixed=fixed).solve(_views(1), return_info=True)
    assert info["solves"] < 20 and len(info["silhouette_px"]) == 21


def test_bad_settings_and_no_views_name_the_fix(mouth):
    V, F, fixed = mouth
    with pytest.raises(UsageError, match="width_tol"):
        SketchSolver(V, F, fixed=fixed, width_tol=-1.0)
    with pytest.raises(UsageError, match="at least one SketchView"):
        SketchSolver(V, F, fixed=fixed).solve([])
