"""Refine Lips from two cameras (core, no bpy): the route benchmark's posed case in miniature.

The head is nodded 20 degrees relative to the main camera (as ``benchmarks/any_face.py`` poses its armature), so
a lip gap error along the face's up-down axis has a component along the main camera's rays that this camera
cannot see. A second camera 35 degrees below the first (the lower camera of a helmet rig,
``testing.route.CAMERAS``) sees it. Ground truth: an ICT-FaceKit pose; sketches: its inner-lip silhouettes.
"""

import numpy as np
import pytest

from facelab_addon.core.capture.camera import Camera
from facelab_addon.core.errors import FaceLabError
from facelab_addon.core.geometry.laplacian import uniform_laplacian
from facelab_addon.core.lips.mouth import find_mouth
from facelab_addon.core.lips.refine_params import RefineParams
from facelab_addon.core.lips.sketch import refine_lips_views
from facelab_addon.core.lips.views import SketchView
from facelab_addon.core.lips.sketch_prior import depth_terms
from facelab_addon.core.lips.views import SketchView
from facelab_addon.testing import synthetic as S

from .test_laplacian import grid


def _case(ict, nod_deg):
    F = ict.faces
    fixed = ~ict.part_vertex_mask("M_Face")
    mm = 0.1 * ict.scale
    T = ict.pose({"mouthPress_L": 0.25, "mouthPress_R": 0.25})
    mouth = find_mouth(T, F, fixed, units_per_mm=mm)
    w, side = S.lip_error_weights(T, F, fixed, mouth=mouth)
    C = T + (1.25 * mm * w * side)[:, None] * mouth.up  # the lips pulled apart along the face's up, as on the route

    def camera(elevation_deg):
        e = np.radians(elevation_deg)
        d = np.cos(e) * mouth.forward + np.sin(e) * mouth.up
        return Camera.look_at(mouth.center + 40.0 * ict.scale * d, mouth.center, mouth.up, 50, 36, 1920, 1080)

    # the face nodded away from the main camera = the main camera that far above the face's front
    main, lower = camera(nod_deg), camera(nod_deg - 35.0)
    views = [SketchView(c, *S.lip_contours(T, F, c, mouth=mouth, margin_mm=3.0), name=n)
             for c, n in ((main, "main"), (lower, "lower"))]
    return dict(F=F, fixed=fixed, mm=mm, T=T, C=C, lip=w > 1e-3, views=views, ray=main.R[2], mouth=mouth)


@pytest.fixture(scope="module")
def nodded(ict):
    return _case(ict, 20.0)


@pytest.fixture(scope="module")
def at_rest(ict):
    return _case(ict, 0.0)


def _rms(c, X):
    return np.sqrt((np.linalg.norm(X - c["T"], axis=1)[c["lip"]] ** 2).mean()) / c["mm"]


def _along_ray(c, X):  # the error component along the main camera's rays (its depth), mm
    return np.sqrt(((((X - c["T"])[c["lip"]]) @ c["ray"]) ** 2).mean()) / c["mm"]


def test_a_lower_camera_recovers_the_depth_the_main_camera_cannot_see(nodded):
    c = nodded
    T, lip, mm, ray = c["T"], c["lip"], c["mm"], c["ray"]

    def rms(X):
        return np.sqrt((np.linalg.norm(X - T, axis=1)[lip] ** 2).mean()) / mm

    def along_ray(X):  # the error component along the main camera's rays (its depth), mm
        return np.sqrt(((((X - T)[lip]) @ ray) ** 2).mean()) / mm

    X1 = refine_lips_views(c["C"], c["F"], c["views"][:1], fixed=c["fixed"])
    X2, info = refine_lips_views(c["C"], c["F"], c["views"], fixed=c["fixed"], return_info=True)
    e0, e1, e2 = rms(c["C"]), rms(X1), rms(X2)
    assert along_ray(c["C"]) > 0.3 * e0  # the capture error has a depth component (measured 0.176 of 0.513 mm)
    assert along_ray(X1) > 0.95 * along_ray(c["C"])  # one view leaves it (measured 1.01)
    assert along_ray(X2) < 0.6 * along_ray(c["C"])  # the lower camera removes half of it (measured 0.48; joint 0.57)
    assert e2 < e1 - 0.25 * e0, (e0, e1, e2)  # measured cuts: one view 34.9 %, two views 66.7 % (joint 60.7 %)
    assert [v["name"] for v in info["views"]] == ["main", "lower"]
    assert all(v["silhouette_px"] < 3.0 for v in info["views"])  # both views end on their sketches


def test_a_second_view_adds_no_false_depth_at_rest(at_rest):
    """Facing the main camera the error is all across its image: the lower camera must not cost 3D accuracy.

    Matched jointly from the capture, the lower camera's silhouettes (other vertices than the main camera's)
    were pulled across its own image, which mixes in the main camera's depth: 0.15 mm of false depth and a
    73 % cut down to 47 %. Staged (the main view first, the lower one matched from its result, its worst-matched
    samples left out) the two views keep the one-view result.
    """
    c = at_rest
    X1 = refine_lips_views(c["C"], c["F"], c["views"][:1], fixed=c["fixed"])
    X2 = refine_lips_views(c["C"], c["F"], c["views"], fixed=c["fixed"])
    Xj = refine_lips_views(c["C"], c["F"], c["views"], RefineParams(main_view_iterations=0, views_keep=np.inf),
                           fixed=c["fixed"])
    e0, e1, e2, ej = _rms(c, c["C"]), _rms(c, X1), _rms(c, X2), _rms(c, Xj)
    assert _along_ray(c, c["C"]) < 0.01 * e0  # no depth error to find
    assert e1 < 0.35 * e0, (e0, e1)  # one view: measured cut 73.3 %
    assert e2 < e1 + 0.03 * e0, (e0, e1, e2)  # two views: measured 72.2 %
    assert _along_ray(c, X2) < 0.1 * e0  # measured 0.046 mm of 0.51 mm
    assert ej > e1 + 0.15 * e0, (e0, e1, ej)  # the joint match from the capture loses (measured 46.8 %)


def test_one_view_is_unaffected_by_the_multi_view_options(at_rest):
    c = at_rest
    X1 = refine_lips_views(c["C"], c["F"], c["views"][:1], fixed=c["fixed"])
    Xo = refine_lips_views(c["C"], c["F"], c["views"][:1],
                           RefineParams(main_view_iterations=0, views_keep=np.inf, depth_reg=0.0), fixed=c["fixed"])
    np.testing.assert_array_equal(X1, Xo)


def test_depth_stiffness_removes_false_depth_at_rest_and_keeps_the_depth_of_a_nod(at_rest, nodded):
    """``depth_reg``: the Laplacian coordinates' depth along the main camera's rays bends stiffer while the
    lower camera joins. At rest (no depth error) the lower camera's correction then stays in the main image
    (less false depth); nodded (a smooth depth error) the depth is still found and the cut is no smaller."""
    out = {}
    for name, c in (("rest", at_rest), ("nod", nodded)):
        for k in (0.0, 3.0):
            X = refine_lips_views(c["C"], c["F"], c["views"], RefineParams(depth_reg=k), fixed=c["fixed"])
            out[name, k] = (_rms(c, X), _along_ray(c, X))
    e0 = _rms(at_rest, at_rest["C"])
    # at rest: false depth 0.045 -> 0.032 mm (measured), the cut 72.4 -> 72.8 %
    assert out["rest", 3.0][1] < 0.8 * out["rest", 0.0][1], out
    assert out["rest", 3.0][0] <= out["rest", 0.0][0] + 1e-3 * e0, out
    # nodded: the depth error (0.176 mm) still comes down to 0.082 mm (0.085 isotropic); the cut 66.7 -> 67.8 %
    assert out["nod", 3.0][1] < 0.5 * _along_ray(nodded, nodded["C"]), out
    assert out["nod", 3.0][0] < out["nod", 0.0][0], out
    with pytest.raises(FaceLabError, match="depth_reg"):
        refine_lips_views(at_rest["C"], at_rest["F"], at_rest["views"], RefineParams(depth_reg=-1.0),
                          fixed=at_rest["fixed"])


def test_depth_terms_penalise_only_uneven_depth_along_the_rays():
    """The term is zero for a displacement across the rays, and for an even one along them; not for a bump."""
    V, F, _ = grid(9, jitter=0.1)
    L = uniform_laplacian(F, len(V))
    mid = np.array([4.0, 4.0, 0.0])
    cam = Camera.look_at(mid + [0.0, 0.0, 400.0], mid, np.array([0.0, 1.0, 0.0]), 50, 36, 1920, 1080)
    rows = np.linalg.norm(V - mid, axis=1) < 3.0
    C = depth_terms(L, V, cam, rows, 2.0)
    assert len(C) == rows.sum()

    def energy(X):
        pts = np.einsum("ck,ckd->cd", C.bary, X[C.vertices]) - C.targets
        return float((C.strength * (np.einsum("cij,cj->ci", C.metrics, pts) ** 2).sum(1)).sum())

    ray = V - cam.center
    ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    bump = np.exp(-np.linalg.norm(V - mid, axis=1) ** 2 / 2.0)[:, None]
    deep = energy(V + 0.1 * bump * ray)
    assert energy(V) < 1e-20
    assert deep > 1e-4
    assert energy(V + 0.1 * ray) < 1e-6 * deep  # an even depth offset
    assert energy(V + 0.1 * bump * np.array([1.0, 0.0, 0.0])) < 1e-3 * deep  # the same bump across the rays
