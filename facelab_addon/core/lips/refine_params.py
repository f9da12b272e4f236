"""The settings of the sketch refinement, in one object: :class:`RefineParams`.

:func:`~facelab_addon.core.lips.sketch.refine_lips`, :func:`~facelab_addon.core.lips.sketch.refine_lips_views`
and :class:`~facelab_addon.core.lips.sketch_session.SketchSolver` take one ``RefineParams`` beside the face they
solve (its vertices, triangles, masks, rest pose and shape offsets) and the strokes.

Units. No setting is a length in the mesh's units: the weights multiply squared lengths of the mesh's own units
(``E_pos``, ``E_silh``) or of its Laplacian coordinates (``E_reg``), so only their ratios act and a mesh scaled by
``s`` gives the same result scaled by ``s``; reaches are fractions of the sketched mouth's width (measured on the
sketch at the depth of the lips, :func:`~facelab_addon.core.lips.sketch_prior.sketch_scale`, in the mesh's units);
``reach_px`` is in pixels of the view's camera.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import FaceLabError, UsageError
from .contact import CONTACT_WEIGHT
from .sketch_prior import PRIORS
from .span_prior import SPAN_REG

__all__ = ["RefineParams", "CROSSINGS", "SILHOUETTE_RAYS"]

#: How a crossing drawing (lower contour above the upper one) is read: as drawn, or as a request to press.
CROSSINGS = ("follow", "press")
#: Which ray a matched silhouette vertex is pulled to (see :attr:`RefineParams.silhouette_rays`).
SILHOUETTE_RAYS = ("nearest", "pixel", "normal")


@dataclass(frozen=True)
class RefineParams:
    """How the sketch refinement solves (Dinev et al. 2018, Eq. 1, and FaceLab's priors); see
    :mod:`facelab_addon.core.lips.sketch` for the energy.

    Every setting is checked when the object is made.

    Attributes
    ----------
    prior : {"band", "smooth", "paper"}
        Anchoring of ``E_pos``. ``"band"`` (default): ``"smooth"``, and inside a painted lip region the
        reach is at least :data:`~facelab_addon.core.lips.sketch_prior.BAND_RINGS` edge lengths.
        ``"smooth"``: anchor weights ``lambda_reg (h_i / reach)^4`` (``h_i`` the local edge length, reach
        ``smooth_reach`` mouth widths). ``"paper"``: ``lambda_pos`` on every vertex (Eq. 1 as written).
    iterations : int
        Solve / re-match iterations, at least 1 (the paper uses 5).
    lambda_pos : float
        Weight of ``E_pos`` (squared distance to the captured position); with the band and smooth
        priors, the largest anchor weight. Dimensionless (a ratio to the other weights).
    lambda_reg : float
        Weight of ``E_reg`` (squared change of the Laplacian coordinates). Dimensionless.
    lambda_silh : float
        Weight of ``E_silh`` per sketch sample (squared distance from a sample's ray to its matched
        silhouette vertex). Dimensionless.
    smooth_reach : float
        Band and smooth priors: how far a silhouette's displacement carries across the lips, in mouth
        widths. Positive.
    free_radius : float
        Geodesic reach of the solved region from the lip vertices near the sketch, in mouth widths;
        vertices beyond it are held exactly. Positive.
    laplacian : {"uniform", "cotangent"}
        The Laplacian of ``E_reg``.
    reach_px : float or None
        Silhouette vertices farther than this from the sketch, in pixels, are not matched; None:
        ``max(20, 0.15 * sketch width)``.
    silhouette_rays : {"nearest", "pixel", "normal"}
        Which ray a matched silhouette vertex is pulled to: the ray through the sketch sample nearest to
        its projection (``"nearest"``, default), or each matching pixel's own ray (``"pixel"``, the
        paper's literal term, which also pulls the vertex along the contour).
    crossings : {"follow", "press"}
        A lower contour drawn above the upper one: the lips cross as drawn (``"follow"``), or both go to
        their mid-line (``"press"``, :func:`~facelab_addon.core.lips.views.press_lips`).
    main_view_iterations : int
        Several views: iterations the first view is solved alone before the others join (0: all views
        from the capture on). One view: no effect.
    views_keep : float
        Several views: the other views' samples matched farther than this multiple of their median
        distance (pixels) are left out of an iteration; ``inf`` keeps all. One view: no effect.
    depth_reg : float
        Several views: while the other views take part, the Laplacian coordinates' component along the main
        camera's rays is held ``1 + depth_reg`` times as stiffly as ``E_reg`` holds them. Dimensionless,
        non-negative (0: isotropic). One view: no effect.
    rest_depth_reg : float
        One view with a rest pose: weight of the terms holding the correction off the main camera's rays as
        they cross the face at rest turned with the head
        (:func:`~facelab_addon.core.lips.sketch_prior.rest_depth_terms`), in ``E_pos``'s units (per vertex,
        on squared lengths). Non-negative (0: off). Several views: no effect.
    contact : float
        Sealed lips drawn on one line: weight per sketch sample pulling the two lips' matched silhouette
        vertices together in 3D, a multiple of ``lambda_silh`` (:mod:`~facelab_addon.core.lips.contact`).
        Non-negative; 0 (default): the lips meet in the image only.
    basis_reg : float
        With shape offsets (``basis``): the ridge on their mix, relative to the mean diagonal of the sketch
        terms (dimensionless, :func:`~facelab_addon.core.lips.span_prior.fit_span`). Non-negative.

    Raises
    ------
    UsageError
        An unknown ``prior``, ``silhouette_rays`` or ``crossings``.
    FaceLabError
        A number out of its range; the message names the default to use.
    """

    prior: str = "band"
    iterations: int = 5
    lambda_pos: float = 0.1
    lambda_reg: float = 3.0
    lambda_silh: float = 1.0
    smooth_reach: float = 0.12
    free_radius: float = 0.1
    laplacian: str = "uniform"
    reach_px: float | None = None
    silhouette_rays: str = "nearest"
    crossings: str = "follow"
    main_view_iterations: int = 1
    views_keep: float = 1.5
    depth_reg: float = 3.0
    rest_depth_reg: float = 10.0
    contact: float = CONTACT_WEIGHT
    basis_reg: float = SPAN_REG

    def __post_init__(self):
        if self.iterations < 1:
            raise FaceLabError("iterations must be at least 1.")
        if self.silhouette_rays not in SILHOUETTE_RAYS:
            raise UsageError(f"silhouette_rays must be 'nearest', 'normal' or 'pixel', got {self.silhouette_rays!r}")
        if self.crossings not in CROSSINGS:
            raise UsageError(f"crossings must be one of {CROSSINGS}, got {self.crossings!r}")
        if not (np.isfinite(self.depth_reg) and self.depth_reg >= 0):
            raise FaceLabError(f"depth_reg must be a non-negative number, got {self.depth_reg!r}; use the default 3.")
        if not (np.isfinite(self.rest_depth_reg) and self.rest_depth_reg >= 0):
            raise FaceLabError(f"rest_depth_reg must be a non-negative number, got {self.rest_depth_reg!r}; use the "
                               "default 10.")
        if self.prior not in PRIORS:
            raise UsageError(f"prior must be one of {PRIORS}, got {self.prior!r}")
        if not (np.isfinite(self.contact) and self.contact >= 0):
            raise FaceLabError(f"contact must be a non-negative number, got {self.contact!r}; use the default "
                               f"{CONTACT_WEIGHT} (0: off).")
        if not (np.isfinite(self.basis_reg) and self.basis_reg >= 0):
            raise FaceLabError(f"basis_reg must be a non-negative number, got {self.basis_reg!r}; use the default "
                               f"{SPAN_REG}.")
        for nm, val in (("smooth_reach", self.smooth_reach), ("free_radius", self.free_radius)):
            if not (np.isfinite(val) and val > 0):
                raise FaceLabError(f"{nm} must be a positive number of mouth widths, got {val!r}; use the default.")
