"""Sketch-based lip refinement (Dinev et al. 2018, §5), from one or several camera views.

The artist draws the upper and lower inner-lip contours over a camera view.
We minimise, in the least-squares sense and over 5 iterations,

    E = lambda_pos * E_pos + lambda_silh * E_silh + lambda_reg * E_reg        (Eq. 1)

* ``E_pos = sum_i w_i ||v_i - v̄_i||^2`` keeps vertices near their captured position.
* ``E_reg = ||L(v) - L(v̄)||^2`` preserves the Laplacian coordinates of the
  captured mesh ([SCOL*04] umbrella operator).
* ``E_silh = sum_p ||r_p - v_p||^2``: for every pixel ``p`` of a sketched
  contour, the distance from its camera ray ``r_p`` to the closest silhouette
  vertex ``v_p`` of the matching lip. Silhouette vertices are split into upper
  and lower lip by the sign of the y component of their projected normals.
  With several views (:class:`~facelab_addon.core.lips.views.SketchView`, one
  camera each) every view adds its own terms to the one solve, which fixes the
  depth of the lips that a single view cannot see. The first view is the main
  one: it is solved alone first, and the other views are matched on its result
  (``main_view_iterations``), their worst-matched samples left out (``views_keep``);
  while they take part, the depth along the main camera's rays bends stiffer
  (``depth_reg``), so they correct what the main view left with motion it sees,
  not with false depth.

Silhouettes and correspondences are recomputed at every iteration on the
current result, while ``E_pos`` and ``E_reg`` keep referring to the captured
mesh as Eq. 1 is written. Where the lower contour is drawn above the upper
one, the lips are made to cross as drawn (``crossings="follow"``: one lip in
front of the other, as overlapping lips look on the plate; the truth's
silhouettes of lips that roll over each other cross so); ``crossings="press"``
reads a crossing as a request to press the lips together (both to their mid-line).

Three priors (``prior``):

* ``"paper"``: ``w_i = lambda_pos`` (0.1) on every vertex, 1 on ``fixed`` ones: Eq. 1
  verbatim. The bi-Laplacian ``E_reg`` then carries a silhouette's displacement only about
  ``(lambda_reg / lambda_pos)^(1/4)`` edge rings (2.3), so an error that is smooth across the
  lip band is corrected beside the silhouette only.
* ``"smooth"`` (default): ``w_i = lambda_reg (h_i / reach)^4`` (``h_i`` the local edge
  length, ``reach`` a fraction of the mouth width), so the displacement of the silhouette
  carries across the lip band, the same distance on any mesh density; hidden
  (``fixed``) vertices are held exactly. On the sketch benchmark it removes more of the
  3D lip error (``benchmarks/sketch_refine.py``).
* ``"band"`` (default): the smooth prior, except inside a painted lip region ``lips``
  (``FL_lips``, whose border is held and so bounds the correction): there the reach is at least
  3 edge lengths (:data:`~facelab_addon.core.lips.sketch_prior.BAND_RINGS`). The bi-Laplacian
  carries a displacement about ``(lambda_reg / w)^(1/4)`` edge rings, so on a coarse mesh (edges
  of 4 mm, a reach of 0.12 mouth widths is about one edge) the smooth prior leaves the correction
  on the silhouettes' own ring and the rest of the band keeps its error; on the artist route
  benchmark (one view, a quad remesh of ICT) the band prior removes 60.2 % of the 3D error where
  the smooth one removes 51.1 %. Without ``lips`` it is the smooth prior.

Two options go beyond the paper's energy, both off by default: ``contact`` (sealed lips drawn on one line: the
lips' silhouette vertices matched along the shared stretch are pulled together in 3D,
:mod:`~facelab_addon.core.lips.contact`) and ``basis`` (the face's own expression offsets: the correction starts
as their mix whose silhouettes match the sketch, :mod:`~facelab_addon.core.lips.span_prior`).

Only the vertices within ``free_radius`` mouth widths (geodesic) of the lip area near
the sketch are solved for (or, given a painted lip region ``lips`` such as ``FL_lips``,
that region's interior, its border held in place but free to bend: ``E_reg`` has no rows for
the border vertices); everything else is held exactly. The mouth
width is measured on the sketch (:func:`~facelab_addon.core.lips.sketch_prior.sketch_scale`),
so the settings mean the same on any mesh, in any units. The system matrix does not change
between iterations, so it is factored once, and the moving silhouette constraints are
added exactly with the Woodbury identity (``deform.LaplacianDeformer``). To re-solve one face as its
strokes change (Live Refine), :class:`~facelab_addon.core.lips.sketch_session.SketchSolver` keeps that
system between solves.
"""

from __future__ import annotations

from ..errors import UsageError
from ..geometry.mesh import validate_mesh
from ..geometry.polyline import resample_polyline  # noqa: F401  (re-exported for the benchmark)
from .contact import CONTACT_WEIGHT
from .sketch_session import CROSSINGS, SketchSolver
from .span_prior import SPAN_REG
from .views import SketchView, prepare_sketch, press_lips

__all__ = ["refine_lips", "refine_lips_views", "press_lips", "prepare_sketch", "SketchView", "SketchSolver",
           "CROSSINGS"]


def refine_lips(
    vertices,
    faces,
    camera,
    upper,
    lower,
    *,
    fixed=None,
    lips=None,
    prior: str = "band",
    iterations: int = 5,
    lambda_pos: float = 0.1,
    lambda_reg: float = 3.0,
    lambda_silh: float = 1.0,
    smooth_reach: float = 0.12,
    free_radius: float = 0.1,
    laplacian: str = "uniform",
    reach_px: float | None = None,
    silhouette_rays: str = "nearest",
    crossings: str = "follow",
    rest_vertices=None,
    rest_depth_reg: float = 10.0,
    contact: float = CONTACT_WEIGHT,
    basis=None,
    basis_reg: float = SPAN_REG,
    return_info: bool = False,
):
    """Deform a face mesh so its inner-lip silhouettes match sketched contours (one camera).

    Parameters
    ----------
    vertices : (V,3) float
        Captured mesh on the problem frame, scene units. Not modified.
    faces : (F,3) int
        Triangles (the adapters triangulate polygons).
    camera : Camera
        The camera the sketch was drawn in.
    upper, lower : (N,2), (M,2) float, or lists of such polylines
        Upper and lower inner-lip contours in pixels (top-left origin, y down).
    fixed : (V,) bool, optional
        Hidden vertices (back of the head, inner mouth, teeth): never lip
        silhouettes, weight 1 in the paper's prior and held exactly in the
        smooth one. Default: every vertex off the largest connected piece of
        the mesh (separate teeth, tongue, eyes), as the Refine Lips operator does.
    lips : (V,) bool, optional
        A painted inner-lip region (``FL_lips``): only its interior moves, its
        border is held (as Propagate's Poisson solve holds it).
    prior : {"band", "smooth", "paper"}
        Anchoring of ``E_pos`` (see the module docstring).
    iterations : int
        Number of solve/re-match iterations (the paper uses 5).
    lambda_pos, lambda_reg, lambda_silh : float
        Weights of Eq. 1 (paper: 0.1, 3, 1). With the smooth prior
        ``lambda_pos`` is the largest anchor weight.
    smooth_reach : float
        Smooth prior: how far a silhouette's displacement carries across the
        lips, in mouth widths (the sketch's width at the depth of the lips).
    free_radius : float
        Geodesic reach of the solved region from the lip area near the sketch,
        in mouth widths; vertices beyond are held exactly.
    laplacian : {"uniform", "cotangent"}
        Laplacian used by ``E_reg``.
    reach_px : float, optional
        Silhouette vertices farther than this (pixels) from the sketch are
        ignored; default ``max(20, 0.15 * sketch width)`` (about 6 mm on a mouth).
    silhouette_rays : {"nearest", "pixel"}
        Which ray a matched silhouette vertex is pulled to. Matching is always
        the paper's: every sketch pixel picks the closest silhouette vertex of
        its lip, and ``E_silh`` sums point-to-ray distances over the pixels.
        ``"pixel"`` uses each pixel's own ray, literally; pixels on either side
        of a vertex then also pull it *along* the contour, which slides the
        lips sideways. ``"nearest"`` (default) uses, for all the pixels that
        picked a vertex, the ray through the sketch sample nearest to the
        vertex's projection (the same number of terms), which removes that
        sideways pull.
    crossings : {"follow", "press"}
        Where the lower contour is drawn above the upper one. ``"follow"``
        (default): as drawn, one lip in front of the other, as the truth's
        silhouettes of overlapping lips are; draw both contours on one line
        to close the lips. ``"press"``: the older convention, the crossing asks
        to press the lips together: both go to their mid-line by what the
        crossing adds to the overlap the capture already has
        (:func:`~facelab_addon.core.lips.views.press_lips`).
    rest_vertices, rest_depth_reg
        The face at rest and how strongly the depth the camera cannot see follows it, turned with the
        head (see :func:`refine_lips_views`).
    contact : float
        Sealed lips: where the upper and lower contours are drawn on one line, the lips' matched silhouette
        vertices are pulled together in 3D with this weight per sketch sample, in units of ``lambda_silh``
        (:mod:`~facelab_addon.core.lips.contact`); 0 (default): the lips meet in the image only.
    basis, basis_reg
        The face's own shape offsets the correction starts from, and the ridge on their mix (see
        :func:`refine_lips_views`).
    return_info : bool
        Also return a dict of diagnostics.

    Returns
    -------
    (V,3) ndarray
        Refined vertices, scene units.
    info : dict, only with ``return_info``
        ``region`` (V,) bool free vertices, ``silhouette_px``: mean distance
        (pixels) from the sketch rays to their matched silhouette vertices
        before each iteration and, last, for the result,
        ``matched_upper``/``matched_lower`` vertex indices of the last
        iteration (first view), ``mouth_width`` (scene units), ``n_free``,
        ``seconds``, ``upper_samples``/``lower_samples`` (first view).

    Raises
    ------
    MeshError, CameraError, SketchError
        With a message naming the fix.
    """
    return refine_lips_views(
        vertices, faces, [SketchView(camera, upper, lower)], fixed=fixed, lips=lips, prior=prior,
        iterations=iterations, lambda_pos=lambda_pos, lambda_reg=lambda_reg, lambda_silh=lambda_silh,
        smooth_reach=smooth_reach, free_radius=free_radius, laplacian=laplacian, reach_px=reach_px,
        silhouette_rays=silhouette_rays, crossings=crossings, rest_vertices=rest_vertices,
        rest_depth_reg=rest_depth_reg, contact=contact, basis=basis, basis_reg=basis_reg, return_info=return_info)


def refine_lips_views(
    vertices,
    faces,
    views,
    *,
    fixed=None,
    lips=None,
    prior: str = "band",
    iterations: int = 5,
    lambda_pos: float = 0.1,
    lambda_reg: float = 3.0,
    lambda_silh: float = 1.0,
    smooth_reach: float = 0.12,
    free_radius: float = 0.1,
    laplacian: str = "uniform",
    reach_px: float | None = None,
    silhouette_rays: str = "nearest",
    crossings: str = "follow",
    main_view_iterations: int = 1,
    views_keep: float = 1.5,
    depth_reg: float = 3.0,
    rest_vertices=None,
    rest_depth_reg: float = 10.0,
    contact: float = CONTACT_WEIGHT,
    basis=None,
    basis_reg: float = SPAN_REG,
    return_info: bool = False,
):
    """Refine the lips to sketches drawn through one or several cameras, in one solve.

    Parameters
    ----------
    vertices : (V,3) float
        Captured mesh, scene units. Not modified.
    faces : (F,3) int
    views : sequence of SketchView
        One camera and its upper/lower strokes each (pixels of that camera).
    fixed, lips, prior, iterations, lambda_pos, lambda_reg, lambda_silh, smooth_reach, free_radius,
    laplacian, reach_px, silhouette_rays, crossings, contact, return_info
        As in :func:`refine_lips`; ``silhouette_px`` in the info is over all views, and
        ``views`` lists per view its ``name``, ``silhouette_px`` (mean, last) and matched vertices.
    main_view_iterations : int
        With several views, how many iterations the first (main) view is solved alone before
        the other views join for ``iterations`` more (default 1; 0: all views from the capture
        on). Each view pulls its own silhouette vertices across its own image only; matched on
        the capture, a camera below the mouth moves the upper lip's underside along its image's
        up-down, which mixes in the main camera's depth (false depth where there is none to
        find). Matched on the main view's result, the other views start where the main view's
        correction put the lips. One view: no effect.
    views_keep : float
        With several views, the other views' sketch samples matched farther (pixels) than
        ``views_keep`` times their median distance are left out of each iteration (their worst
        matches: silhouettes the main view's correction has not yet brought near, or another
        silhouette); ``inf`` keeps all. The main view keeps every sample. One view: no effect.
    depth_reg : float
        With several views, while the other views take part, the Laplacian coordinates' component along
        the main camera's rays (its depth) is held ``1 + depth_reg`` times as stiffly as ``E_reg`` holds
        them (:func:`~facelab_addon.core.lips.sketch_prior.depth_terms`): a lower camera's correction of
        the in-image error the main view left then comes out as in-image motion, not as false depth at its
        own silhouette vertices, while a depth error smooth over the lips (a nodded head) is still found.
        0: isotropic. One view: no effect.
    rest_vertices : (V,3) float, optional
        The face at rest (its Basis: no head turn, no expression), in the space and units of ``vertices``.
        With one view, the depth the camera cannot see is then taken from it: the correction is held
        (``rest_depth_reg``) off the main camera's rays as they cross the face at rest, turned with the
        head (:func:`~facelab_addon.core.lips.sketch_prior.rest_depth_terms`). With the head as at rest
        this changes nothing; nodded 20° under a rig, it keeps the nod's share of the correction, which lies
        along the rays. Several views: no effect (they see the depth).
    rest_depth_reg : float
        The strength of that hold (``E_pos`` units; 0: off).
    basis : (K,V,3) float, optional
        The face's own shape offsets (its expression shapes minus its rest shape, scene units, in the space of
        ``vertices``). Given, the correction starts as the mix of them (tapered to zero at the free region's
        border) whose silhouettes best match the sketch (:mod:`~facelab_addon.core.lips.span_prior`): the lip
        band and its depth follow as this face's lips move; ``E_pos`` and ``E_reg`` then refer to that shape.
    basis_reg : float
        Ridge on the mix, relative to the sketch terms (dimensionless).

    Returns
    -------
    (V,3) ndarray, or ((V,3) ndarray, dict) with ``return_info``

    Raises
    ------
    MeshError, CameraError, SketchError
        With a message naming the fix (and the view, with several).
    """
    V0, F = validate_mesh(vertices, faces)
    views = list(views) if views is not None else []
    if not views:
        raise UsageError("refine_lips_views needs at least one SketchView (a camera and its two lip strokes).")
    solver = SketchSolver(
        V0, F, fixed=fixed, lips=lips, prior=prior, iterations=iterations, lambda_pos=lambda_pos,
        lambda_reg=lambda_reg, lambda_silh=lambda_silh, smooth_reach=smooth_reach, free_radius=free_radius,
        laplacian=laplacian, reach_px=reach_px, silhouette_rays=silhouette_rays, crossings=crossings,
        main_view_iterations=main_view_iterations, views_keep=views_keep, depth_reg=depth_reg,
        rest_vertices=rest_vertices, rest_depth_reg=rest_depth_reg, contact=contact, basis=basis, basis_reg=basis_reg)
    return solver.solve(views, return_info=return_info)
