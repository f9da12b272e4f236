"""Refine Lips from two cameras (core, no bpy): the route benchmark's posed case in miniature.

The head is nodded 20 degrees relative to the main camera (as ``benchmarks/any_face.py`` poses its armature), so
a lip gap error along the face's up-down axis has a component along the main camera's rays that this camera
cannot see. A second camera 35 degrees below the first (the lower camera of a helmet rig,
``testing.route.CAMERAS``) sees it. Ground truth: an ICT-FaceKit pose; sketches: its inner-lip silhouettes.
"""

import numpy as np
import pytest

from facelab_addon.core.capture.camera import Camera
from facelab_addon.core.lips.sketch import SketchView, refine_lips_views
from facelab_addon.testing import synthetic as S


@pytest.fixture(scope="module")
def nodded(ict):
    F = ict.faces
    fixed = ~ict.part_vertex_mask("M_Face")
    mm = 0.1 * ict.scale
    T = ict.pose({"mouthPress_L": 0.25, "mouthPress_R": 0.25})
    mouth = S.find_mouth(T, F, fixed, units_per_mm=mm)
    w, side = S.lip_error_weights(T, F, fixed, mouth=mouth)
    C = T + (1.25 * mm * w * side)[:, None] * mouth.up  # the lips pulled apart along the face's up, as on the route

    def camera(elevation_deg):
        e = np.radians(elevation_deg)
        d = np.cos(e) * mouth.forward + np.sin(e) * mouth.up
        return Camera.look_at(mouth.center + 40.0 * ict.scale * d, mouth.center, mouth.up, 50, 36, 1920, 1080)

    # the face nodded 20 degrees away from the main camera = the main camera 20 degrees above the face's front
    main, lower = camera(20.0), camera(20.0 - 35.0)
    views = [SketchView(c, *S.lip_contours(T, F, c, mouth=mouth, margin_mm=3.0), name=n)
             for c, n in ((main, "main"), (lower, "lower"))]
    return dict(F=F, fixed=fixed, mm=mm, T=T, C=C, lip=w > 1e-3, views=views, ray=main.R[2])


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
    assert along_ray(X2) < 0.8 * along_ray(c["C"])  # the lower camera removes part of it (measured 0.71)
    assert e2 < e1 - 0.15 * e0, (e0, e1, e2)  # measured cuts: one view 19.6 %, two views 44.9 %
    assert [v["name"] for v in info["views"]] == ["main", "lower"]
    assert all(v["silhouette_px"] < 3.0 for v in info["views"])  # both views end on their sketches
