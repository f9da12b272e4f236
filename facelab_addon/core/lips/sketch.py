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
added exactly with the Woodbury identity (``deform.LaplacianDeformer``).
"""

from __future__ import annotations

import time

import numpy as np
import scipy.sparse as sp

from ..errors import FaceLabError, UsageError
from ..geometry.deform import LaplacianDeformer
from ..geometry.laplacian import laplacian as make_laplacian
from ..geometry.linsolve import small_dense_threads
from ..geometry.mesh import validate_mesh, vertex_adjacency
from ..geometry.polyline import resample_polyline  # noqa: F401  (re-exported for the benchmark)
from .contact import CONTACT_WEIGHT
from .sketch_prior import (
    PRIORS,
    anchor_weights,
    depth_terms,
    free_region,
    local_faces,
    rest_depth_terms,
    separate_parts,
    sketch_scale,
)
from .span_prior import SPAN_REG, fit_span, span_columns, taper
from .views import SketchView, ViewMatcher, prepare_sketch, press_lips

__all__ = ["refine_lips", "refine_lips_views", "press_lips", "prepare_sketch", "SketchView", "CROSSINGS"]

#: How a crossing drawing (lower contour above the upper one) is read: as drawn, or as a request to press.
CROSSINGS = ("follow", "press")


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
    t0 = time.perf_counter()
    V0, F = validate_mesh(vertices, faces)
    n = len(V0)
    views = list(views) if views is not None else []
    if not views:
        raise UsageError("refine_lips_views needs at least one SketchView (a camera and its two lip strokes).")
    if iterations < 1:
        raise FaceLabError("iterations must be at least 1.")
    if silhouette_rays not in ("nearest", "pixel", "normal"):
        raise UsageError(f"silhouette_rays must be 'nearest', 'normal' or 'pixel', got {silhouette_rays!r}")
    if crossings not in CROSSINGS:
        raise UsageError(f"crossings must be one of {CROSSINGS}, got {crossings!r}")
    if not (np.isfinite(depth_reg) and depth_reg >= 0):
        raise FaceLabError(f"depth_reg must be a non-negative number, got {depth_reg!r}; use the default 3.")
    if not (np.isfinite(rest_depth_reg) and rest_depth_reg >= 0):
        raise FaceLabError(f"rest_depth_reg must be a non-negative number, got {rest_depth_reg!r}; use the "
                           "default 10.")
    if prior not in PRIORS:
        raise UsageError(f"prior must be one of {PRIORS}, got {prior!r}")
    if not (np.isfinite(contact) and contact >= 0):
        raise FaceLabError(f"contact must be a non-negative number, got {contact!r}; use the default "
                           f"{CONTACT_WEIGHT} (0: off).")
    if not (np.isfinite(basis_reg) and basis_reg >= 0):
        raise FaceLabError(f"basis_reg must be a non-negative number, got {basis_reg!r}; use the default {SPAN_REG}.")
    for nm, val in (("smooth_reach", smooth_reach), ("free_radius", free_radius)):
        if not (np.isfinite(val) and val > 0):
            raise FaceLabError(f"{nm} must be a positive number of mouth widths, got {val!r}; use the default.")
    fixed = separate_parts(F, n) if fixed is None else np.asarray(fixed, dtype=bool)
    if fixed.shape != (n,):
        raise FaceLabError(f"'fixed' must be a mask of {n} vertices, got {fixed.shape}.")
    if lips is not None:
        lips = np.asarray(lips, dtype=bool)
        if lips.shape != (n,):
            raise FaceLabError(f"'lips' must be a mask of {n} vertices, got {lips.shape}; rebuild the regions.")

    multi = len(views) > 1
    matchers = []
    for k, v in enumerate(views):
        where = f" in view '{v.name or k + 1}'" if multi else ""
        matchers.append(ViewMatcher(v, V0, F, fixed, reach_px=reach_px, where=where, press=crossings == "press",
                                    contact=contact))
    near = np.zeros(n, bool)
    for m in matchers:
        near |= m.near
    widths = [sketch_scale(m.camera, m.sketch, V0[m.near]) for m in matchers]
    W = float(np.median(widths))

    region = free_region(V0, F, near, free_radius * W, fixed=fixed, lips=lips)
    if not region.any():
        raise FaceLabError("No vertex near the sketch is free to move (all fixed, or outside the lip region "
                           "'lips'); check the FL_fixed / FL_lips groups.")
    # everything below needs only the triangles near the free region (its rows of L are exact there)
    Fl = F[local_faces(F, region, rings=2)]
    adj = vertex_adjacency(Fl, n)
    w = anchor_weights(V0, Fl, region, prior=prior, lambda_pos=lambda_pos, lambda_reg=lambda_reg,
                       reach=smooth_reach * W, fixed=fixed, lips=lips)
    L = make_laplacian(V0, Fl, laplacian, adjacency=adj)
    if lips is not None:
        # the held border of the lip region keeps its position, not its Laplacian coordinates: the
        # correction may meet it at an angle (as Propagate's Poisson solve, which holds the same border,
        # reproduces it), instead of flattening out before it
        L = sp.diags((~(lips & ~region & ~fixed)).astype(np.float64)) @ L
    solver = LaplacianDeformer(L, lambda_reg=lambda_reg, pos_weights=w, pinned=~region)
    # silhouettes: on triangles of the region and its held ring (a border vertex may be on the silhouette)
    around = region | (adj @ region.astype(np.float64) > 0)
    for m in matchers:
        m.restrict(Fl, around & ~fixed, in_lip_region=lips is not None)

    def correspondences(X, gates=None, upto=None):  # gates: per view, (N+M,) sample weights or None
        cons, dists, matched = [], [], []
        for k, m in enumerate(matchers[:upto]):
            c, d, mt = m.correspondences(X, lambda_silh, silhouette_rays,
                                         sample_weights=None if gates is None else gates[k])
            cons += c
            dists.append(d)
            matched.append(mt)
        return cons, dists, matched

    ref = V0  # the shape E_pos and E_reg refer to: the capture, or its best mix of the face's own shapes
    span_weights = None
    if basis is not None and len(basis):
        # the face's own expression offsets, tapered to zero at the free region's border, mixed to match the sketch
        U = span_columns(basis, taper(V0, Fl, region), W)
        ref, span_weights = fit_span(V0, U, lambda X: correspondences(X)[0], iterations, basis_reg)
    turn = None
    if not multi and rest_vertices is not None and rest_depth_reg > 0:
        # one view: the depth it cannot see follows the face's rest pose, turned with the head
        terms, turn = rest_depth_terms(ref, rest_vertices, matchers[0].camera, region, rest_depth_reg,
                                       mouth_width=W)
        if terms is not None:
            solver = solver.with_terms(terms, ref)
    V0 = ref
    X = V0
    hist = []
    with small_dense_threads(1):
        base = solver.unconstrained(V0, V0)  # E_pos and E_reg refer to V0 (``ref``): the same every iteration
        if multi:
            # the main (first) view alone first; its result is where the other views are matched from
            for _ in range(int(main_view_iterations)):
                cons, dists, matched = correspondences(X, upto=1)
                hist.append(float(np.mean(np.concatenate(dists))))
                X = solver.constrain(base, V0, cons)
        if multi and depth_reg > 0:
            # the depth along the main camera's rays bends stiffer (a fixed, coordinate-coupling term:
            # factored once into the solver the other views join)
            solver = solver.with_terms(depth_terms(L, V0, matchers[0].camera, region, depth_reg * lambda_reg), V0)
            base = solver.unconstrained(V0, V0)
        for _ in range(int(iterations)):
            g = None
            if multi and np.isfinite(views_keep):
                # the added views' sketch samples matched farther than views_keep x their median are left out
                d0 = [m.correspondences(X, lambda_silh, silhouette_rays)[1] for m in matchers[1:]]
                g = [None] + [(d <= views_keep * np.median(d)).astype(np.float64) for d in d0]
            cons, dists, matched = correspondences(X, g)
            hist.append(float(np.mean(np.concatenate(dists))))
            X = solver.constrain(base, V0, cons)
    if not np.isfinite(X).all():
        raise FaceLabError("The lip solve diverged (non-finite result); check the strokes and the camera.")
    if not return_info:
        return X
    _, dists, _ = correspondences(X)  # residual of the result itself
    hist.append(float(np.mean(np.concatenate(dists))))
    info = dict(
        region=region,
        silhouette_px=hist,
        matched_upper=matched[0].get("upper"),
        matched_lower=matched[0].get("lower"),
        n_free=int(region.sum()),
        mouth_width=W,
        prior=prior,
        head_turn_deg=turn,
        span_weights=span_weights,
        seconds=time.perf_counter() - t0,
        upper_samples=matchers[0].upper,
        lower_samples=matchers[0].lower,
        views=[dict(name=v.name, silhouette_px=float(d.mean()), matched_upper=mt.get("upper"),
                    matched_lower=mt.get("lower")) for v, d, mt in zip(views, dists, matched)],
        one_line_samples=[int((m.partner >= 0).sum()) for m in matchers],
    )
    return X, info
