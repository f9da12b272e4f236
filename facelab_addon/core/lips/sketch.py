"""Sketch-based lip refinement (Dinev et al. 2018, §5), from one or several camera views.

The artist draws the upper and lower inner-lip contours over a camera view.
We minimise, in the least-squares sense and over ``RefineParams.iterations`` (5) iterations,

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

Three priors (``RefineParams.prior``):

* ``"paper"``: ``w_i = lambda_pos`` (0.1) on every vertex, 1 on ``fixed`` ones: Eq. 1
  verbatim. The bi-Laplacian ``E_reg`` then carries a silhouette's displacement only about
  ``(lambda_reg / lambda_pos)^(1/4)`` edge rings (2.3), so an error that is smooth across the
  lip band is corrected beside the silhouette only.
* ``"smooth"``: ``w_i = lambda_reg (h_i / reach)^4`` (``h_i`` the local edge length, in the
  mesh's units; ``reach = smooth_reach`` times the mouth width), capped at ``lambda_pos``, so
  the displacement of the silhouette carries across the lip band, the same distance on any mesh
  density; hidden (``fixed``) vertices are held exactly.
* ``"band"`` (default): the smooth prior, except inside a painted lip region ``lips``
  (``FL_lips``, whose border is held and so bounds the correction): there the reach is at least
  :data:`~facelab_addon.core.lips.sketch_prior.BAND_RINGS` edge lengths. The bi-Laplacian
  carries a displacement about ``(lambda_reg / w)^(1/4)`` edge rings, so on a coarse mesh (a
  reach of ``smooth_reach`` mouth widths shorter than one edge) the smooth prior leaves the
  correction on the silhouettes' own ring; the band prior carries it across the band. Without
  ``lips`` it is the smooth prior.

Two options go beyond the paper's energy, both off by default: ``RefineParams.contact`` (sealed lips
drawn on one line: the lips' silhouette vertices matched along the shared stretch are pulled together in 3D,
:mod:`~facelab_addon.core.lips.contact`) and ``basis`` (the face's own expression offsets: the correction starts
as their mix whose silhouettes match the sketch, :mod:`~facelab_addon.core.lips.span_prior`).

The settings (weights, priors, reaches) are one :class:`~facelab_addon.core.lips.refine_params.RefineParams`;
the face's own data (vertices, triangles, the ``fixed`` and ``lips`` masks, the rest pose, the shape offsets)
are separate arguments.

Only the vertices within ``RefineParams.free_radius`` mouth widths (geodesic) of the lip area near
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

from .refine_params import RefineParams
from .sketch_session import SketchSolver
from .views import SketchView

__all__ = ["refine_lips", "refine_lips_views"]


def refine_lips(vertices, faces, camera, upper, lower, params: RefineParams | None = None, *, fixed=None, lips=None,
                rest_vertices=None, basis=None, return_info: bool = False):
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
    params : RefineParams, optional
        The refinement's settings (weights, prior, reaches; see
        :class:`~facelab_addon.core.lips.refine_params.RefineParams`); default ``RefineParams()``.
    fixed : (V,) bool, optional
        Hidden vertices (back of the head, inner mouth, teeth): never lip
        silhouettes, weight 1 in the paper's prior and held exactly in the
        band and smooth ones. Default: every vertex off the largest connected piece of
        the mesh (separate teeth, tongue, eyes), as the Refine Lips operator does.
    lips : (V,) bool, optional
        A painted inner-lip region (``FL_lips``): only its interior moves, its
        border is held (as Propagate's Poisson solve holds it).
    rest_vertices : (V,3) float, optional
        The face at rest (see :func:`refine_lips_views`).
    basis : (K,V,3) float, optional
        The face's own shape offsets the correction starts from (see :func:`refine_lips_views`).
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
        ``seconds``, ``upper_samples``/``lower_samples`` (first view), ``warnings``: what the artist should
        check in the sketch (list of str; :func:`~facelab_addon.core.lips.swapped_strokes.check_swapped_strokes`).

    Raises
    ------
    MeshError, CameraError, SketchError
        With a message naming the fix.
    """
    return refine_lips_views(vertices, faces, [SketchView(camera, upper, lower)], params, fixed=fixed, lips=lips,
                             rest_vertices=rest_vertices, basis=basis, return_info=return_info)


def refine_lips_views(vertices, faces, views, params: RefineParams | None = None, *, fixed=None, lips=None,
                      rest_vertices=None, basis=None, return_info: bool = False):
    """Refine the lips to sketches drawn through one or several cameras, in one solve.

    Parameters
    ----------
    vertices : (V,3) float
        Captured mesh, scene units. Not modified.
    faces : (F,3) int
    views : sequence of SketchView
        One camera and its upper/lower strokes each (pixels of that camera). The first is the main
        view (see :class:`~facelab_addon.core.lips.refine_params.RefineParams`' ``main_view_iterations``,
        ``views_keep``, ``depth_reg``).
    params : RefineParams, optional
        The refinement's settings; default ``RefineParams()``.
    fixed, lips, return_info
        As in :func:`refine_lips`; ``silhouette_px`` in the info is over all views, and
        ``views`` lists per view its ``name``, ``silhouette_px`` (mean, last) and matched vertices.
    rest_vertices : (V,3) float, optional
        The face at rest (its Basis: no head turn, no expression), in the space and units of ``vertices``.
        With one view, the depth the camera cannot see is then taken from it: the correction is held
        (``params.rest_depth_reg``) off the main camera's rays as they cross the face at rest, turned with
        the head (:func:`~facelab_addon.core.lips.sketch_prior.rest_depth_terms`). With the head as at rest
        this changes nothing; with the head turned, the turn's share of the correction along the rays is
        kept. Several views: no effect (they see the depth).
    basis : (K,V,3) float, optional
        The face's own shape offsets (its expression shapes minus its rest shape, scene units, in the space of
        ``vertices``). Given, the correction starts as the mix of them (tapered to zero at the free region's
        border) whose silhouettes best match the sketch (:mod:`~facelab_addon.core.lips.span_prior`, ridge
        ``params.basis_reg``): the lip band and its depth follow as this face's lips move; ``E_pos`` and
        ``E_reg`` then refer to that shape.

    Returns
    -------
    (V,3) ndarray, or ((V,3) ndarray, dict) with ``return_info``

    Raises
    ------
    MeshError, CameraError, SketchError
        With a message naming the fix (and the view, with several).
    """
    # the solver checks the mesh (once) and the views (at least one)
    solver = SketchSolver(vertices, faces, params, fixed=fixed, lips=lips, rest_vertices=rest_vertices, basis=basis)
    return solver.solve(views, return_info=return_info)
