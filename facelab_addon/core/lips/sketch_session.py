"""Factor once, solve many: the sketch refinement of one face, re-solved as its strokes change.

:func:`~facelab_addon.core.lips.sketch.refine_lips_views` solves one set of strokes from scratch.
:class:`SketchSolver` holds a face (its captured vertices, triangles, hidden and lip-region masks, rest
pose, shape offsets) and the refinement's settings (:class:`~facelab_addon.core.lips.refine_params.RefineParams`),
and solves any number of stroke sets on it:

* what depends on the face only (the validated mesh, its depth and pixels in each camera) is made once,
  and the geodesic distances from the lip area near the strokes are kept while that area is the same;
* the solve's system (the free region, the Laplacian and the anchor weights of ``E_pos`` / ``E_reg``,
  the fixed depth terms, their factorisation and the Woodbury columns of the constrained vertices) is
  kept for the free region, mouth width and main camera it was made for, and made again only when the
  strokes change one of them; strokes that leave them as they were re-solve on the kept factor;
* the solve/re-match iterations stop early, with the same result, once the matching repeats: the
  constraints depend on the mesh only through which silhouette vertex each sketch sample picks, so a
  repeated matching repeats the solves after it (a fixed point, or a cycle whose state after
  ``iterations`` steps is known);
* ``start`` warm-starts the iterations from an earlier result (the last preview) instead of the capture.

Without ``start`` and with ``width_tol=0`` a solve is :func:`refine_lips_views`' (which calls this
class). With ``width_tol > 0`` the system is also kept for strokes that leave the free region as it was
and move the mouth width by less than that fraction (a point edited inside the sketch), solved with the
kept width. With ``start`` the result is the iterations' end state reached from ``start``, which can be
another state than the one reached from the capture (the iterations do not always settle on one
matching: they may alternate between two).

Shapes: vertices (V,3) float64 scene units, triangles (F,3) int64, masks (V,) bool.
"""

from __future__ import annotations

import time

import numpy as np
import scipy.sparse as sp

from ..capture.camera import Camera
from ..errors import FaceLabError, UsageError
from ..geometry.deform import LaplacianDeformer, PointConstraints
from ..geometry.laplacian import laplacian as make_laplacian
from ..geometry.linsolve import small_dense_threads
from ..geometry.mesh import validate_mesh, vertex_adjacency
from .refine_params import RefineParams
from .sketch_prior import (
    anchor_weights,
    depth_terms,
    free_region,
    local_faces,
    rest_depth_terms,
    seed_distances,
    separate_parts,
    sketch_scale,
)
from .span_prior import fit_span, span_columns, taper
from .views import ViewMatcher

__all__ = ["SketchSolver"]


def _camera_key(cam):
    """A hashable summary of a camera's projection (intrinsics, pose, frame size)."""
    return (np.asarray(cam.K, np.float64).tobytes(), np.asarray(cam.R, np.float64).tobytes(),
            np.asarray(cam.t, np.float64).tobytes(), int(cam.width), int(cam.height))


def _same(a, b) -> bool:
    """Whether two concatenated constraint sets (PointConstraints or None) are identical."""
    if a is None or b is None:
        return a is None and b is None
    return all(np.array_equal(x, y) for x, y in ((a.vertices, b.vertices), (a.bary, b.bary),
                                                 (a.targets, b.targets), (a.metrics, b.metrics),
                                                 (a.strength, b.strength)))


class _System:
    """The stroke-independent part of a solve for one free region, mouth width and main camera."""

    def __init__(self, key, W, region, Fl, adj, L, solver, around):
        self.key, self.W, self.region, self.Fl, self.adj = key, W, region, Fl, adj
        self.L, self.solver, self.around = L, solver, around
        self.single = None  # (solver, base, turn) of one view with the rest-depth terms (no basis)
        self.multi = None  # (base, depth solver, its base) of several views (no basis)


class SketchSolver:
    """The sketch refinement of one face, solved for any number of stroke sets.

    Parameters
    ----------
    vertices : (V,3) float
        Captured mesh, scene units. Not modified.
    faces : (F,3) int
    params : RefineParams, optional
        The refinement's settings; default ``RefineParams()``.
    fixed, lips, rest_vertices, basis
        As in :func:`~facelab_addon.core.lips.sketch.refine_lips_views`.
    width_tol : float
        Keep the system for strokes whose free region is the same and whose mouth width (the unit of the
        anchor weights' reach and of the rest-depth fit) is within this fraction of the one it was made for,
        solving with that width. 0 (default): only for the very same width, so a solve is
        :func:`refine_lips_views`'. A point edited inside the sketch moves the width a little (the sketch's
        extent, the median depth of the lip vertices near the strokes); a Live Refine preview keeps its
        system through such edits.

    Raises
    ------
    MeshError, FaceLabError, UsageError
        A bad mesh, mask or setting, with the fix.
    """

    def __init__(self, vertices, faces, params: RefineParams | None = None, *, fixed=None, lips=None,
                 rest_vertices=None, basis=None, width_tol: float = 0.0):
        V0, F = validate_mesh(vertices, faces)
        n = len(V0)
        p = RefineParams() if params is None else params
        if not isinstance(p, RefineParams):
            raise UsageError(f"params must be a RefineParams, got {type(p).__name__}; build one with "
                             "RefineParams(...) (its defaults are the refinement's).")
        if not (np.isfinite(width_tol) and width_tol >= 0):
            raise UsageError(f"width_tol must be a non-negative fraction, got {width_tol!r}; use 0 (exact).")
        fixed = separate_parts(F, n) if fixed is None else np.asarray(fixed, dtype=bool)
        if fixed.shape != (n,):
            raise FaceLabError(f"'fixed' must be a mask of {n} vertices, got {fixed.shape}.")
        if lips is not None:
            lips = np.asarray(lips, dtype=bool)
            if lips.shape != (n,):
                raise FaceLabError(f"'lips' must be a mask of {n} vertices, got {lips.shape}; rebuild the regions.")
        self.V0, self.F, self.n = V0, F, n
        self.fixed, self.lips = fixed, lips
        self.params = p
        self.rest_vertices, self.basis = rest_vertices, basis
        self.width_tol = float(width_tol)
        self._system = None
        self._distances = None  # (near bytes, limit, (V,) seed distances) of the last free region
        self._projections = {}  # camera key -> (depth, pixels) of the captured mesh
        #: How many systems (free region, operators, factorisation) this solver has made.
        self.builds = 0

    # ------------------------------------------------------------------ strokes
    def matchers(self, views) -> list:
        """One :class:`~facelab_addon.core.lips.views.ViewMatcher` per view (validated strokes, rays, the lip
        area near them)."""
        views = list(views) if views is not None else []
        if not views:
            raise UsageError("refine_lips_views needs at least one SketchView (a camera and its two lip strokes).")
        multi = len(views) > 1
        out = []
        for k, v in enumerate(views):
            where = f" in view '{v.name or k + 1}'" if multi else ""
            out.append(ViewMatcher(v, self.V0, self.F, self.fixed, reach_px=self.params.reach_px, where=where,
                                   press=self.params.crossings == "press", contact=self.params.contact,
                                   projection=self._projection(v.camera)))
        return out

    def _projection(self, cam):
        """``(depth (V,), pixels (V,2))`` of the captured mesh in ``cam``, kept per camera; None for a non-camera
        (the matcher names the problem)."""
        if not isinstance(cam, Camera):
            return None
        key = _camera_key(cam)
        if key not in self._projections:
            if len(self._projections) >= 4:
                self._projections.clear()
            self._projections[key] = (cam.depth(self.V0), cam.project(self.V0))
        return self._projections[key]

    def mouth_width(self, views=None, matchers=None) -> float:
        """The sketched mouth's width, scene units (the median over the views of
        :func:`~facelab_addon.core.lips.sketch_prior.sketch_scale`)."""
        ms = self.matchers(views) if matchers is None else matchers
        return float(np.median([sketch_scale(m.camera, m.sketch, self.V0[m.near]) for m in ms]))

    # ------------------------------------------------------------------ system
    def _region(self, near, radius):
        # the seeds' geodesic distances, kept for the same seeds up to radius (1 + width_tol)
        nb = near.tobytes()
        if self._distances is None or self._distances[0] != nb or radius > self._distances[1]:
            limit = radius * (1.0 + self.width_tol)
            self._distances = (nb, limit, seed_distances(self.V0, self.F, near, limit))
        region = free_region(self.V0, self.F, near, radius, fixed=self.fixed, lips=self.lips,
                             distances=self._distances[2])
        if not region.any():
            raise FaceLabError("No vertex near the sketch is free to move (all fixed, or outside the lip region "
                               "'lips'); check the FL_fixed / FL_lips groups.")
        return region

    def _build(self, key, region, W):
        V0, F, n = self.V0, self.F, self.n
        # everything below needs only the triangles near the free region (its rows of L are exact there)
        Fl = F[local_faces(F, region, rings=2)]
        adj = vertex_adjacency(Fl, n)
        p = self.params
        w = anchor_weights(V0, Fl, region, prior=p.prior, lambda_pos=p.lambda_pos, lambda_reg=p.lambda_reg,
                           reach=p.smooth_reach * W, fixed=self.fixed, lips=self.lips)
        L = make_laplacian(V0, Fl, p.laplacian, adjacency=adj)
        if self.lips is not None:
            # the held border of the lip region keeps its position, not its Laplacian coordinates: the
            # correction may meet it at an angle (as Propagate's Poisson solve, which holds the same border,
            # reproduces it), instead of flattening out before it
            L = sp.diags((~(self.lips & ~region & ~self.fixed)).astype(np.float64)) @ L
        # factored at its first use: one view with the rest-depth terms solves a coupled system of its own
        solver = LaplacianDeformer(L, lambda_reg=p.lambda_reg, pos_weights=w, pinned=~region, lazy=True)
        # silhouettes: on triangles of the region and its held ring (a border vertex may be on the silhouette)
        around = region | (adj @ region.astype(np.float64) > 0)
        self.builds += 1
        return _System(key, W, region, Fl, adj, L, solver, around)

    def _system_for(self, matchers, free_radius):
        near = np.zeros(self.n, bool)
        for m in matchers:
            near |= m.near
        W = self.mouth_width(matchers=matchers)
        fr = float(free_radius(W)) if callable(free_radius) else float(free_radius)
        if not (np.isfinite(fr) and fr > 0):
            raise FaceLabError(f"free_radius must be a positive number of mouth widths, got {fr!r}; use the default.")
        # the free region is a function of (near, radius): keep the system while both are as they were
        key = (near.tobytes(), W, fr * W, len(matchers) > 1, _camera_key(matchers[0].camera))
        old = self._system
        if old is not None and old.key == key:
            return old, W
        region = self._region(near, fr * W)
        tol = self.width_tol
        if (old is not None and tol > 0 and old.key[3:] == key[3:] and abs(W / old.W - 1.0) <= tol
                and abs(fr * W / old.key[2] - 1.0) <= tol and np.array_equal(region, old.region)):
            return old, old.W  # the same free region, a mouth width within width_tol: solve as before
        self._system = None  # free the old factor before making the new one
        self._system = self._build(key, region, W)
        return self._system, W

    # ------------------------------------------------------------------ solve
    def solve(self, views, *, start=None, free_radius: float | None = None, return_info: bool = False):
        """Refine the lips to ``views``' strokes.

        Parameters
        ----------
        views : sequence of SketchView
        start : (V,3) float, optional
            Where the solve/re-match iterations start (an earlier result of this solver, such as the last
            preview); default the capture (the result is then :func:`refine_lips_views`').
        free_radius : float or callable, optional
            The free region's reach in mouth widths for this solve (default the solver's), or a function
            of the sketched mouth's width (scene units) giving it (a reach in scene units divided by the
            width).
        return_info : bool
            Also return the dict of :func:`refine_lips_views`, with ``rebuilt`` (whether this solve made
            its system) and ``solves`` (linear solves done).

        Returns
        -------
        (V,3) ndarray, or ((V,3) ndarray, dict) with ``return_info``

        Raises
        ------
        MeshError, CameraError, SketchError, FaceLabError
            With a message naming the fix (and the view, with several).
        """
        t0 = time.perf_counter()
        # BLAS on one thread throughout: its work here is small (3x3 solves and products over the mesh, systems
        # of a few hundred unknowns), where a second thread costs more to start and spin than it shares
        with small_dense_threads(1):
            return self._solve(views, start, free_radius, return_info, t0)

    def _solve(self, views, start, free_radius, return_info, t0):
        views = list(views) if views is not None else []
        matchers = self.matchers(views)
        multi = len(matchers) > 1
        p = self.params
        fr = p.free_radius if free_radius is None else free_radius
        builds = self.builds
        sysm, W = self._system_for(matchers, fr)
        region, Fl, L, solver = sysm.region, sysm.Fl, sysm.L, sysm.solver
        for m in matchers:
            m.restrict(Fl, sysm.around & ~self.fixed, in_lip_region=self.lips is not None)
        lam, rays, keep = p.lambda_silh, p.silhouette_rays, p.views_keep

        def correspondences(X, gates=None, upto=None):  # gates: per view, (N+M,) sample weights or None
            cons, dists, matched = [], [], []
            for k, m in enumerate(matchers[:upto]):
                c, d, mt = m.correspondences(X, lam, rays, sample_weights=None if gates is None else gates[k])
                cons += c
                dists.append(d)
                matched.append(mt)
            return cons, dists, matched

        V0 = self.V0
        ref = V0  # the shape E_pos and E_reg refer to: the capture, or its best mix of the face's own shapes
        span_weights = None
        with_basis = self.basis is not None and len(self.basis)
        if with_basis:
            # the face's own expression offsets, tapered to zero at the free region's border, mixed to match the sketch
            U = span_columns(self.basis, taper(V0, Fl, region), W)
            ref, span_weights = fit_span(V0, U, lambda X: correspondences(X)[0], int(p.iterations),
                                         p.basis_reg)
        turn = None
        counter = [0]
        if not multi:
            if with_basis or sysm.single is None:
                s1, turn = solver, None
                if self.rest_vertices is not None and p.rest_depth_reg > 0:
                    # one view: the depth it cannot see follows the face's rest pose, turned with the head
                    terms, turn = rest_depth_terms(ref, self.rest_vertices, matchers[0].camera, region,
                                                   p.rest_depth_reg, mouth_width=W)
                    if terms is not None:
                        s1 = solver.with_terms(terms, ref)
                base = s1.unconstrained(ref, ref)  # E_pos and E_reg refer to ref: the same every iteration
                if not with_basis:
                    sysm.single = (s1, base, turn)
            else:
                s1, base, turn = sysm.single
            X = ref if start is None else np.asarray(start, dtype=np.float64)
            X, hist, matched = self._iterate(s1, base, ref, X, p.iterations,
                                             lambda Y: correspondences(Y), counter)
        else:
            if with_basis or sysm.multi is None:
                base0 = solver.unconstrained(ref, ref)
                s2, base2 = solver, base0
                if p.depth_reg > 0:
                    # the depth along the main camera's rays bends stiffer (a fixed, coordinate-coupling term:
                    # factored once into the solver the other views join)
                    s2 = solver.with_terms(depth_terms(L, ref, matchers[0].camera, region,
                                                       p.depth_reg * p.lambda_reg), ref)
                    base2 = s2.unconstrained(ref, ref)
                if not with_basis:
                    sysm.multi = (base0, s2, base2)
            else:
                base0, s2, base2 = sysm.multi
            X = ref if start is None else np.asarray(start, dtype=np.float64)
            hist = []
            if int(p.main_view_iterations) > 0:
                # the main (first) view alone first; its result is where the other views are matched from
                X, hist, matched = self._iterate(solver, base0, ref, X, int(p.main_view_iterations),
                                                 lambda Y: correspondences(Y, upto=1), counter)

            def gated(Y):
                g = None
                if np.isfinite(keep):
                    # the added views' sketch samples matched farther than views_keep x their median are left out
                    d0 = [m.correspondences(Y, lam, rays)[1] for m in matchers[1:]]
                    g = [None] + [(d <= keep * np.median(d)).astype(np.float64) for d in d0]
                return correspondences(Y, g)

            X, h2, matched = self._iterate(s2, base2, ref, X, p.iterations, gated, counter)
            hist += h2
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
            prior=p.prior,
            head_turn_deg=turn,
            span_weights=span_weights,
            seconds=time.perf_counter() - t0,
            upper_samples=matchers[0].upper,
            lower_samples=matchers[0].lower,
            views=[dict(name=v.name, silhouette_px=float(d.mean()), matched_upper=mt.get("upper"),
                        matched_lower=mt.get("lower")) for v, d, mt in zip(views, dists, matched)],
            one_line_samples=[int((m.partner >= 0).sum()) for m in matchers],
            rebuilt=self.builds > builds,
            solves=counter[0],
            warnings=[m.warning for m in matchers if m.warning],
        )
        return X, info

    @staticmethod
    def _iterate(solver, base, ref, X, iterations: int, correspondences, counter):
        """``iterations`` solve/re-match steps from ``X``: returns ``(X, hist, matched)``.

        Step ``i`` matches ``X_i`` (constraints ``c_i``) and solves ``X_(i+1) = S(c_i)``. The solve is a
        function of the constraints, so once ``c_i`` equals an earlier ``c_j`` the steps repeat with
        period ``i - j`` and the end state is read off the ones already solved.
        """
        hist, seen = [], []  # seen: per step (constraints, mean distance, matched, X after the step)
        for i in range(int(iterations)):
            cons, dists, matched = correspondences(X)
            c = PointConstraints.concat(cons)
            d = float(np.mean(np.concatenate(dists)))
            j = next((k for k, s in enumerate(seen) if _same(s[0], c)), None)
            if j is not None:
                # X_(i+1) = X_(j+1): from step j + 1 on, X_m = X_(j + 1 + (m - j - 1) % p)
                p, n = i - j, int(iterations)
                states = seen + [(c, d, matched, None)]  # states[m]: matching of X_m; states[m - 1][3] = X_m
                hist.append(d)
                for m in range(i + 1, n):
                    hist.append(states[j + 1 + (m - j - 1) % p][1])
                last = j + 1 + (n - 2 - j) % p if n - 1 > i else i
                return seen[j + (n - j - 1) % p][3], hist, states[last][2]
            hist.append(d)
            X = solver.constrain(base, ref, c)
            counter[0] += 1
            seen.append((c, d, matched, X))
        return X, hist, matched
