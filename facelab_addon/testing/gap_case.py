"""The timing benchmarks' common case: the ICT-FaceKit neutral face (or it subdivided once) with a 2.5 mm
inner-lip gap, seen by a frontal camera, and the truth's inner-lip silhouettes as the sketch.

:func:`ict_gap_case` builds it without Blender; ``benchmarks/scale.py`` times Refine on it and
``benchmarks/live_sketch.py`` times Live Refine on it. Positions are ICT's (centimetres times ``scale``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..core.lips.mouth import find_mouth
from . import synthetic as syn
from .subdivide import subdivide_midpoint

__all__ = ["GapCase", "ict_gap_case"]


@dataclass
class GapCase:
    """One gap case.

    Attributes
    ----------
    truth : (V,3) float ndarray
        The neutral face, ICT units.
    faces : (F,3) int ndarray
    fixed : (V,) bool ndarray
        Vertices off the ``M_Face`` part (teeth, eyes...): held.
    mouth : facelab_addon.testing.synthetic.Mouth
    camera : facelab_addon.core.capture.camera.Camera
        Frontal, 40 cm from the mouth.
    upper, lower : (N,2) float ndarray
        The truth's inner-lip silhouettes, pixels.
    captured : (V,3) float ndarray
        The face with the 2.5 mm inner-lip gap.
    """

    truth: np.ndarray
    faces: np.ndarray
    fixed: np.ndarray
    mouth: object
    camera: object
    upper: np.ndarray
    lower: np.ndarray
    captured: np.ndarray


def ict_gap_case(model, size: str = "26k") -> GapCase:
    """The gap case on ``model`` (an ICT-FaceKit model, :func:`facelab_addon.core.capture.ict.load_ict`): its
    neutral face as it is (``size`` "26k") or subdivided once at the midpoints (any other ``size``)."""
    T, F, mm = model.neutral, model.faces, 0.1 * model.scale
    fixed = ~model.part_vertex_mask("M_Face")
    if size != "26k":
        T, F, S = subdivide_midpoint(T, F)
        fixed = (S @ fixed.astype(float)) > 0.99
    mouth = find_mouth(T, F, fixed, units_per_mm=mm)
    cam = syn.frontal_camera(T, mouth.center, distance=40.0 * model.scale)
    up, lo = syn.lip_contours(T, F, cam, mouth=mouth)
    C, _ = syn.inject_lip_error(T, F, fixed, kind="gap", amount_mm=2.5, mouth=mouth)
    return GapCase(T, np.asarray(F), fixed, mouth, cam, up, lo, C)
