"""Blendshape fit and out-of-subspace corrective from markers and contours.

Bhat, Goldenthal, Ye, Mallet, Koperwas 2013, "High fidelity facial animation
capture and retargeting with contours", §4.1-4.3:

* **Constraints (§4.1).** A marker is a surface point ``x = A V`` (see
  ``markers.py``). A tracked 2D marker ``m`` in a camera with projection
  ``Q`` (3x4) gives the residual of Eq. 1, ``(m_x q2ᵀy - q0ᵀy, m_y q2ᵀy -
  q1ᵀy)`` with ``y = (x, 1)``; a 3D bundle ``p`` gives Eq. 2, ``x - p``.
* **Contours (§4.2).** Tracked inner-lip and eyelid curves are matched to the
  mesh's occluding contour each frame by ``contours.match_contours``; every
  matched point lies on a mesh edge and is fitted like a 2D marker (or, for
  eyelid curves projected on the cornea, like a 3D bundle).
* **Blendshape fit (§4.3, Eq. 3).** ``min_w sum_i omega_i E_i(w)`` subject to
  ``-1 <= w <= 1`` with marker and contour weights ``omega = 1``: a bounded
  linear least-squares problem, solved here by a primal active-set method on
  the ``S x S`` normal equations (warm-started from the previous frame).
  Correspondence and solve alternate (the paper finds one iteration enough).
* **Out-of-subspace corrective (§4.3).** A per-frame ``ΔV`` minimising the
  cotangent-Laplacian energy of ``ΔV`` (weight 1) plus the 2D marker (1),
  3D bundle (1), 2D contour (0.5) and 3D eyelid curve (0.5) residuals, with
  the mesh boundary held fixed: a linear least-squares problem solved with the
  shared ``deform.LaplacianDeformer`` (factored once).

Implementation notes (deviations, all documented in docs/solve.md):

* Eq. 1 is the algebraic (DLT) residual: it is the pixel error times the
  point's depth ``q2ᵀy``. We divide each row by the depth at the current
  estimate, so the residual is in pixels and, after the Gauss-Newton style
  re-linearisation of the outer iterations, exactly the reprojection error.
* A tiny ridge (``regularization`` times the mean diagonal of the normal
  matrix) makes the weights of shapes no constraint sees (e.g. eye gaze with
  skin markers only) zero instead of arbitrary.
* The corrective's 2D terms use the linear form of a pixel residual: the
  distance (scene units) of the surface point to the camera ray through the
  pixel (``PointConstraints.rays``); ``pixel_units=True`` measures it in pixels.

Conventions: vertices (V,3) float64 scene units; pixels top-left origin,
y down; cameras ``camera.Camera`` (OpenCV).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg

from ..capture.camera import Camera
from ..capture.markers import SurfacePoints
from ..errors import FaceLabError
from ..geometry.deform import LaplacianDeformer, PointConstraints
from ..geometry.laplacian import cotangent_laplacian
from ..geometry.linsolve import small_dense_threads
from ..geometry.mesh import edge_faces, grow_region, validate_mesh, vertex_adjacency

__all__ = [
    "FrameResult",
    "PerformanceResult",
    "BlendshapeSolver",
    "OutOfSubspaceCorrective",
    "solve_performance",
    "box_least_squares",
    "contour_curve_distance",
]


# --------------------------------------------------------------------------- results
@dataclass
class FrameResult:
    """One solved frame.

    Attributes
    ----------
    weights : (S,) float64
        Blendshape weights, inside the bounds.
    correspondences : list of contours.CurveCorrespondence
        Contour correspondences used in the last iteration (empty without curves).
    info : dict
        ``iterations``, ``markers_used``, ``markers_offscreen``, ``bundles_used``,
        ``contour_points``, ``marker_rms_px``, ``contour_rms_px``, ``time_s`` (wall),
        ``cpu_s`` (process CPU time; with ``solve_performance`` also
        ``corrective_time_s`` / ``corrective_cpu_s``).
    """

    weights: np.ndarray
    correspondences: list = field(default_factory=list)
    info: dict = field(default_factory=dict)


@dataclass
class PerformanceResult:
    """A solved sequence.

    Attributes
    ----------
    weights : (T,S) float64
        Per-frame weights; NaN rows for skipped frames.
    correctives : (T,V,3) float64 or None
        Per-frame corrective ``ΔV`` (scene units); zero rows for skipped
        frames; None when no corrective was asked for.
    skipped : dict int -> str
        Frame index -> why it was skipped (no usable data).
    info : dict
        ``frames`` (list of per-frame info dicts, None for skipped),
        ``time_s``, ``offscreen_markers`` {frame: count}.
    correspondences : list (T) of list of CurveCorrespondence
        The contour correspondences each frame's final result was fitted to:
        the blendshape fit's, or with a corrective the corrective's (matched
        again on the fitted rig, see ``rematch``); empty lists without curves
        or for skipped frames.
    """

    weights: np.ndarray
    correctives: np.ndarray | None
    skipped: dict
    info: dict
    correspondences: list = field(default_factory=list)


# --------------------------------------------------------------------------- bounded LS
def box_least_squares(H, g, lo, hi, w0=None, *, max_iter: int | None = None):
    """Minimise ``0.5 wᵀHw - gᵀw`` subject to ``lo <= w <= hi`` (H SPD, small).

    A primal active-set method (exact for convex box QPs, finite steps);
    warm-started from ``w0`` (clipped into the box). Falls back to
    ``scipy.optimize.lsq_linear`` if it does not converge.

    Parameters
    ----------
    H : (S,S) float
        Normal matrix ``JᵀJ`` (plus ridge), symmetric positive definite.
    g : (S,) float
        ``Jᵀb``.
    lo, hi : (S,) float
        Bounds.
    w0 : (S,) float, optional
        Warm start.

    Returns
    -------
    w : (S,) float64
    n_iter : int
        Active-set iterations taken.
    """
    S = len(g)
    lo = np.broadcast_to(np.asarray(lo, float), (S,))
    hi = np.broadcast_to(np.asarray(hi, float), (S,))
    w = np.zeros(S) if w0 is None else np.clip(np.asarray(w0, float).copy(), lo, hi)
    at_lo = w <= lo
    at_hi = w >= hi
    scale = max(float(np.abs(np.diag(H)).max()), 1e-300)
    tol = 1e-10 * scale * max(1.0, float(np.abs(hi - lo).max()))
    max_iter = 6 * S + 10 if max_iter is None else max_iter
    for it in range(1, max_iter + 1):
        free = ~(at_lo | at_hi)
        target = w.copy()
        if free.any():
            fi = np.flatnonzero(free)
            rhs = g[fi] - H[np.ix_(fi, np.flatnonzero(~free))] @ w[~free]
            Hff = H[np.ix_(fi, fi)]
            try:
                c = scipy.linalg.cho_factor(Hff, lower=True, check_finite=False)
                target[fi] = scipy.linalg.cho_solve(c, rhs, check_finite=False)
            except np.linalg.LinAlgError:  # singular (no ridge, unobserved shapes): least-norm step
                target[fi] = np.linalg.lstsq(Hff, rhs, rcond=1e-12)[0]
        d = target - w
        # longest feasible step along d
        with np.errstate(divide="ignore", invalid="ignore"):
            a_lo = np.where(free & (d < 0), (lo - w) / d, np.inf)
            a_hi = np.where(free & (d > 0), (hi - w) / d, np.inf)
        a = np.minimum(a_lo, a_hi)
        k = int(np.argmin(a))
        if a[k] < 1.0:
            w = w + max(a[k], 0.0) * d
            if a_lo[k] <= a_hi[k]:
                w[k] = lo[k]
                at_lo[k] = True
            else:
                w[k] = hi[k]
                at_hi[k] = True
            continue
        w = target
        grad = H @ w - g
        viol = np.where(at_lo, -grad, 0.0) + np.where(at_hi, grad, 0.0)  # > 0: wants to move inward
        j = int(np.argmax(viol))
        if viol[j] <= tol:
            return np.clip(w, lo, hi), it
        at_lo[j] = at_hi[j] = False
    # fallback (should not happen for SPD H)
    from scipy.optimize import lsq_linear

    ev, U = np.linalg.eigh(0.5 * (H + H.T))
    ev = np.maximum(ev, 1e-14 * max(float(ev.max()), 1e-300))
    R = (U * np.sqrt(ev)).T  # RᵀR = H
    b = (U.T @ g) / np.sqrt(ev)
    res = lsq_linear(R, b, bounds=(lo, hi), method="bvls")
    return np.clip(res.x, lo, hi), max_iter


# --------------------------------------------------------------------------- helpers
def _collect_ints(obj, out, depth=0):
    """All integer arrays inside a (nested) loops object (vertex ids)."""
    if depth > 4 or obj is None:
        return
    if isinstance(obj, np.ndarray):
        if np.issubdtype(obj.dtype, np.integer) and obj.size:
            out.append(obj.ravel())
        return
    if isinstance(obj, dict):
        for v in obj.values():
            _collect_ints(v, out, depth + 1)
        return
    if isinstance(obj, (list, tuple)):
        for v in obj:
            _collect_ints(v, out, depth + 1)
        return
    if hasattr(obj, "__dict__"):
        for v in vars(obj).values():
            _collect_ints(v, out, depth + 1)


def _check_cameras(cameras):
    cams = list(cameras or [])
    for i, c in enumerate(cams):
        if not isinstance(c, Camera):
            raise FaceLabError(
                f"Camera {i} has no calibration (got {type(c).__name__}); give every tracking camera its "
                "intrinsics and pose (solve the camera in the Movie Clip editor or set the lens)."
            )
    return cams


def contour_curve_distance(vertices, cameras, correspondences, curves) -> np.ndarray:
    """Pixel distance of every 2D contour point to its tracked curve (polyline).

    Unlike the matched-point residual, sliding along the curve is not an
    error here: this is how far the mesh's contour lies from the drawn curve.

    Parameters
    ----------
    vertices : (V,3) float
    cameras : list of Camera
    correspondences : list of CurveCorrespondence
    curves : list of TrackedCurve

    Returns
    -------
    (n,) float64
        Distances (pixels) of all points of the 2D correspondences.
    """
    V = np.asarray(vertices, float)
    by = {(c.name, int(c.camera)): np.asarray(c.pixels, float) for c in curves or []}
    out = []
    for cc in correspondences or []:
        if getattr(cc, "pixels", None) is None or cc.camera < 0 or (cc.name, int(cc.camera)) not in by:
            continue
        v, b = np.asarray(cc.vertices), np.asarray(cc.bary, float)
        X = np.einsum("ck,ckd->cd", b, V[v])
        out.append(_point_to_polyline(cameras[cc.camera].project(X), by[(cc.name, int(cc.camera))]))
    return np.concatenate(out) if out else np.zeros(0)


def _point_to_polyline(p, poly):
    """(n,) distance of points p (n,2) to the polyline poly (k,2)."""
    poly = np.asarray(poly, float)
    if len(poly) == 1:
        return np.linalg.norm(p - poly[0], axis=1)
    a, b = poly[:-1], poly[1:]
    ab = b - a
    L2 = np.maximum((ab * ab).sum(1), 1e-300)
    t = np.clip(((p[:, None, :] - a[None]) * ab[None]).sum(-1) / L2[None], 0, 1)
    q = a[None] + t[..., None] * ab[None]
    return np.sqrt(((p[:, None, :] - q) ** 2).sum(-1)).min(axis=1)


# --------------------------------------------------------------------------- solver
class BlendshapeSolver:
    """Per-frame bounded least-squares blendshape fit (Bhat et al. 2013, §4.3, Eq. 3).

    Parameters
    ----------
    neutral : (V,3) float
        Rest mesh, scene units.
    deltas : (S,V,3) float
        Blendshape deltas (target - neutral), scene units.
    faces : (F,3) int
    cameras : list of Camera
        The calibrated tracking cameras (C of them).
    markers : SurfacePoints or None
        The M markers' surface bindings (one set for all cameras: row ``j`` of
        every camera's pixel array is marker ``j``). Unbound rows are ignored.
    bundles : SurfacePoints or None
        The B bundles' surface bindings.
    loops : contours.ContourLoops or None
        Candidate contour loops (needed to use tracked curves).
    bounds : (lo, hi)
        Weight bounds (paper: -1, 1); scalars or (S,) arrays.
    marker_weight, contour_weight, bundle_weight : float
        ``omega`` of each energy (paper: 1).
    regularization : float
        Ridge, relative to the mean diagonal of the normal matrix.
    eyelids : {"3d", "2d", "both"}
        How eyelid curves are fitted (``contours.match_contours``): lifted
        onto the eyeball as 3D targets (paper), as 2D curves, or both.
    contour_huber_px : float or None
        Huber threshold (pixels) on the inner-lip contour points: after the
        contour solve, ``robust_iterations`` re-solves with the same
        correspondence weight each lip point by ``min(1, k / residual)``
        (IRLS). Lips the rig cannot reach (out of its span) then bend the
        whole lower face less; the corrective fits them. Curves the rig can
        match (residuals below ``k``) are fitted exactly as without it.
        None or 0: the paper's plain least squares. Not in the paper.
    robust_iterations : int
        IRLS re-solves for ``contour_huber_px`` (2: a few ms a frame).
    """

    def __init__(self, neutral, deltas, faces, cameras, markers: SurfacePoints | None, bundles: SurfacePoints | None,
                 loops=None, *, bounds=(-1.0, 1.0), marker_weight: float = 1.0, contour_weight: float = 1.0,
                 bundle_weight: float = 1.0, regularization: float = 1e-6, eyelids: str = "3d",
                 contour_huber_px: float | None = 1.0, robust_iterations: int = 2):
        V0, F = validate_mesh(neutral, faces, name="neutral mesh")
        self.contour_huber_px = None if not contour_huber_px else float(contour_huber_px)
        self.robust_iterations = int(robust_iterations)
        self.eyelids = eyelids
        D = np.asarray(deltas, dtype=np.float64)
        if D.ndim != 3 or D.shape[1:] != V0.shape or D.shape[0] == 0:
            raise FaceLabError(
                f"The rig has no usable shape keys (deltas shape {D.shape}, mesh {V0.shape}); add blendshape "
                "shape keys to the face (with the same vertex count as the Basis)."
            )
        self.neutral, self.faces, self.deltas = V0, F, D
        self.S = D.shape[0]
        self.cameras = _check_cameras(cameras)
        self.loops = loops
        lo, hi = bounds
        self.lo = np.broadcast_to(np.asarray(lo, float), (self.S,)).copy()
        self.hi = np.broadcast_to(np.asarray(hi, float), (self.S,)).copy()
        if (self.lo > self.hi).any():
            raise FaceLabError("Lower weight bounds exceed the upper ones; check the bounds.")
        self.marker_weight = float(marker_weight)
        self.contour_weight = float(contour_weight)
        self.bundle_weight = float(bundle_weight)
        self.regularization = float(regularization)
        self._P = [c.P for c in self.cameras]
        self.markers = markers
        self.bundles = bundles
        self._mk = self._bind(markers)
        self._bd = self._bind(bundles)
        # vertices the contour matching needs: loop ids (and anything else loops hold) plus 2 rings
        self._need = None
        self._vbuf = V0.copy()
        if loops is not None:
            ids = []
            _collect_ints(loops, ids)
            if ids:
                m = np.zeros(len(V0), bool)
                ids = np.concatenate(ids)
                m[ids[(ids >= 0) & (ids < len(V0))]] = True
                m = grow_region(m, vertex_adjacency(F, len(V0)), 2)
                self._need = np.flatnonzero(m)
                self._Dneed = np.ascontiguousarray(D[:, self._need].reshape(self.S, -1))
        self._D2 = D.reshape(self.S, -1)

    # ------------------------------------------------------------------ model
    def _bind(self, pts: SurfacePoints | None):
        if pts is None or len(pts) == 0:
            return None
        ok = pts.bound
        vid = np.maximum(pts.vertices, 0)
        x0 = np.einsum("mk,mkd->md", pts.bary, self.neutral[vid])
        B = np.einsum("mk,smkd->mds", pts.bary, self.deltas[:, vid])  # (m,3,S)
        return dict(ok=ok, x0=x0, B=B)

    def vertices(self, weights) -> np.ndarray:
        """(V,3) full mesh ``neutral + sum_s w_s deltas_s``."""
        w = np.asarray(weights, float)
        return self.neutral + (w @ self._D2).reshape(-1, 3)

    def _partial_vertices(self, w):
        """(V,3) buffer exact at the vertices contour matching needs (neutral elsewhere)."""
        if self._need is None:
            return self.vertices(w)
        self._vbuf[self._need] = self.neutral[self._need] + (w @ self._Dneed).reshape(-1, 3)
        return self._vbuf

    def match(self, weights, curves, *, sliding: bool = True, previous=None, vertices=None) -> list:
        """Contour correspondences of tracked curves on the rig at ``weights`` (§4.2).

        Parameters
        ----------
        weights : (S,) float
        curves : list of contours.TrackedCurve
        sliding : bool
            Re-select and re-match (True); False keeps ``previous``'s
            surface points and re-reads only the targets.
        previous : list of CurveCorrespondence, optional
        vertices : (V,3) float, optional
            Match on this mesh instead (e.g. rig plus corrective), scene units.

        Returns
        -------
        list of CurveCorrespondence
            3D eyelid targets are lifted with the lids' heights on this mesh.
        """
        from .matching import match_contours

        if not curves:
            return []
        if self.loops is None:
            raise FaceLabError(
                "Tracked curves were given but the solver has no contour loops; build them with "
                "contours.contour_loops(rest_vertices, faces) and pass loops= to BlendshapeSolver."
            )
        V = self._partial_vertices(np.asarray(weights, float)) if vertices is None else np.asarray(vertices, float)
        return match_contours(V, self.faces, self.cameras, curves, self.loops, sliding=sliding,
                              previous=None if sliding else previous, eyelids=self.eyelids)

    def _edge_model(self, corr):
        """Linear model (x0 (c,3), B (c,3,S)) of the correspondence points on mesh edges."""
        v = np.asarray(corr.vertices, np.int64)
        b = np.asarray(corr.bary, float)
        x0 = np.einsum("ck,ckd->cd", b, self.neutral[v])
        B = np.einsum("ck,sckd->cds", b, self.deltas[:, v])
        return x0, B

    # ------------------------------------------------------------------ rows
    def _proj_rows(self, cam_i, x0, B, px, xcur, weight):
        """Depth-normalised Eq. 1 rows: J (2n,S), r (2n,) with residual J w - r (pixels)."""
        P = self._P[cam_i]
        z = xcur @ P[2, :3] + P[2, 3]
        z = np.where(np.abs(z) < 1e-12, 1e-12, z)
        rows_J, rows_r = [], []
        for a in (0, 1):
            coef = px[:, a, None] * P[2, :3][None] - P[a, :3][None]  # (n,3)
            J = np.einsum("nd,nds->ns", coef, B) / z[:, None]
            c0 = px[:, a] * (x0 @ P[2, :3] + P[2, 3]) - (x0 @ P[a, :3] + P[a, 3])
            rows_J.append(J)
            rows_r.append(-c0 / z)
        s = np.sqrt(np.broadcast_to(np.asarray(weight, float), z.shape))
        s = np.concatenate([s, s])
        return s[:, None] * np.concatenate(rows_J), s * np.concatenate(rows_r)

    def _marker_data(self, markers_px):
        """Visible (camera, marker) pairs; drop off-screen pixels."""
        C = len(self.cameras)
        out, offscreen = [], 0
        if self._mk is None or markers_px is None:
            return out, offscreen
        mp = np.asarray(markers_px, float)
        M = len(self._mk["ok"])
        if mp.ndim == 2:
            mp = mp[None]
        if mp.shape != (C, M, 2):
            raise FaceLabError(
                f"Marker pixels have shape {mp.shape}, expected ({C}, {M}, 2) (cameras, markers, xy); "
                "one track per bound marker in every camera (NaN where not tracked)."
            )
        for c in range(C):
            fin = np.isfinite(mp[c]).all(axis=1)
            inside = self.cameras[c].in_frame(mp[c])
            offscreen += int((fin & ~inside).sum())
            sel = np.flatnonzero(fin & inside & self._mk["ok"])
            if len(sel):
                out.append((c, sel, mp[c, sel]))
        return out, offscreen

    def _bundle_data(self, bundles):
        if self._bd is None or bundles is None:
            return None
        b = np.asarray(bundles, float).reshape(-1, 3)
        if len(b) != len(self._bd["ok"]):
            raise FaceLabError(
                f"Got {len(b)} bundle positions for {len(self._bd['ok'])} bound bundles; pass one row per "
                "bundle (NaN where not reconstructed)."
            )
        sel = np.flatnonzero(np.isfinite(b).all(axis=1) & self._bd["ok"])
        return (sel, b[sel]) if len(sel) else None

    def has_data(self, markers_px, bundles, curves) -> str | None:
        """None if the frame has something to fit, else the reason it has not."""
        md, off = self._marker_data(markers_px)
        bd = self._bundle_data(bundles)
        nc = len(curves or []) if self.loops is not None else 0
        if not md and bd is None and nc == 0:
            why = "no tracked markers, bundles or curves"
            if off:
                why += f" ({off} marker positions off-screen)"
            return why
        return None

    # ------------------------------------------------------------------ solve
    def solve_frame(self, markers_px, bundles=None, curves=None, *, previous: FrameResult | None = None,
                    iterations: int = 1, sliding: bool = True, tol: float = 1e-6) -> FrameResult:
        """Fit the weights of one frame.

        Parameters
        ----------
        markers_px : (C,M,2) float or None
            Tracked marker pixels per camera; NaN where a marker is not
            tracked. Off-screen pixels are dropped (counted in ``info``).
        bundles : (B,3) float or None
            Bundle positions, scene units; NaN rows are missing.
        curves : list of contours.TrackedCurve or None
            Tracked inner-lip / eyelid curves of this frame.
        previous : FrameResult, optional
            The previous frame: warm start of the weights and initial contour
            correspondence (§4.2).
        iterations : int
            Correspondence / solve alternations after the marker pre-fit (each
            one re-linearises the projective residuals at the current
            estimate). The paper finds one sufficient (§4.2); so do we.
        sliding : bool
            Sliding contours (paper); False keeps the previous correspondence
            (fixed contours, Fig. 6).
        tol : float
            Stop early when the weights change less than this (max abs).

        Returns
        -------
        FrameResult
        """
        t0 = time.perf_counter()
        c0 = time.process_time()
        md, offscreen = self._marker_data(markers_px)
        bd = self._bundle_data(bundles)
        use_curves = bool(curves) and self.loops is not None
        if curves and self.loops is None:
            raise FaceLabError(
                "Tracked curves were given but the solver has no contour loops; build them with "
                "contours.contour_loops(rest_vertices, faces) and pass loops= to BlendshapeSolver."
            )
        if not md and bd is None and not use_curves:
            raise FaceLabError("This frame has no tracked markers, bundles or curves; nothing to fit.")
        w = np.zeros(self.S) if previous is None else np.clip(np.asarray(previous.weights, float), self.lo, self.hi)
        prev_corr = None if previous is None else previous.correspondences
        corr = []
        it_done = 0
        with small_dense_threads(1):
            if use_curves and (md or bd is not None):
                # markers/bundles first: the contour correspondence is then built on a close mesh
                for _ in range(1 if previous is not None else 2):  # 2: re-linearise the depths from the neutral
                    w = self._solve_linear(w, *self._system(w, md, bd, None))
            n_it = max(1, int(iterations)) if use_curves else max(2, int(iterations))  # markers: re-linearise once
            for it in range(n_it):
                if use_curves:
                    from .matching import match_contours

                    Vc = self._partial_vertices(w)
                    # sliding: select and match afresh on the current mesh (a previous loop would win silhouette
                    # ties against the loop closest to the curve); fixed: keep the previous assignment
                    corr = match_contours(Vc, self.faces, self.cameras, curves, self.loops, sliding=sliding,
                                          previous=None if sliding else prev_corr, eyelids=self.eyelids)
                    prev_corr = corr
                w_new = self._solve_linear(w, *self._system(w, md, bd, corr))
                change = float(np.abs(w_new - w).max())
                w = w_new
                it_done = it + 1
                if change < tol and (not use_curves or not sliding):
                    break
            if use_curves and corr and self.contour_huber_px and self.robust_iterations > 0 and (md or bd is not None):
                # Huber IRLS on the lip-contour points (same correspondence): a lip the rig cannot reach (out of
                # its span) loses its pull instead of bending the whole lower face; the corrective fits it
                for _ in range(int(self.robust_iterations)):
                    pw = self._robust_weights(w, corr)
                    w_new = self._solve_linear(w, *self._system(w, md, bd, corr, pw))
                    change = float(np.abs(w_new - w).max())
                    w = w_new
                    if change < tol:
                        break
        info = dict(iterations=it_done, markers_used=int(sum(len(s) for _, s, _ in md)),
                    markers_offscreen=offscreen, bundles_used=0 if bd is None else int(len(bd[0])),
                    contour_points=int(sum(len(c.vertices) for c in corr)))
        info.update(self.residuals(w, markers_px, bundles, corr))
        info["time_s"] = time.perf_counter() - t0
        info["cpu_s"] = time.process_time() - c0
        return FrameResult(weights=w, correspondences=list(corr), info=info)

    def _solve_linear(self, w, J, r):
        """Bounded least squares ``min |J w - r|^2 + ridge |w|^2`` in the bounds, warm-started at ``w``."""
        H = J.T @ J
        ridge = self.regularization * max(float(np.trace(H)) / self.S, 1e-12)
        H[np.diag_indices_from(H)] += ridge
        w_new, _ = box_least_squares(H, J.T @ r, self.lo, self.hi, w)
        return w_new

    def _robust_weights(self, w, corr):
        """Huber factors ``min(1, k / e)`` of the 2D mouth-contour points at ``w`` (list aligned with ``corr``).

        ``e``: a point's reprojection residual (pixels), ``k = contour_huber_px``.
        Eyelid points keep factor 1 (None).
        """
        k = self.contour_huber_px
        out = []
        for cc in corr:
            if cc.name.startswith("mouth") and getattr(cc, "pixels", None) is not None and cc.camera >= 0:
                x0, B = self._edge_model(cc)
                e = np.linalg.norm(self.cameras[cc.camera].project(x0 + B @ w) - np.asarray(cc.pixels, float), axis=1)
                out.append(np.minimum(1.0, k / np.maximum(e, 1e-12)))
            else:
                out.append(None)
        return out

    def _system(self, w, md, bd, corr, point_weights=None):
        """Weighted rows (J, r) of all residuals linearised at ``w``: residual ``J w - r``.

        ``point_weights``: optional list (aligned with ``corr``) of (c,) factors on the contour weight, or None.
        """
        Js, rs = [], []
        for c, sel, px in md:
            x0, B = self._mk["x0"][sel], self._mk["B"][sel]
            J, r = self._proj_rows(c, x0, B, px, x0 + B @ w, self.marker_weight)
            Js.append(J)
            rs.append(r)
        if bd is not None:
            sel, p = bd
            s = np.sqrt(self.bundle_weight)
            Js.append(s * self._bd["B"][sel].reshape(-1, self.S))
            rs.append(s * (p - self._bd["x0"][sel]).reshape(-1))
        for i, cc in enumerate(corr or []):
            x0, B = self._edge_model(cc)
            if getattr(cc, "pixels", None) is not None and cc.camera >= 0:
                cw = self.contour_weight
                if point_weights is not None and point_weights[i] is not None:
                    cw = cw * point_weights[i]
                J, r = self._proj_rows(cc.camera, x0, B, np.asarray(cc.pixels, float), x0 + B @ w, cw)
            elif getattr(cc, "targets", None) is not None:
                s = np.sqrt(self.contour_weight)
                J = s * B.reshape(-1, self.S)
                r = s * (np.asarray(cc.targets, float) - x0).reshape(-1)
            else:
                continue
            Js.append(J)
            rs.append(r)
        J = np.concatenate(Js) if Js else np.zeros((0, self.S))
        r = np.concatenate(rs) if rs else np.zeros(0)
        return J, r

    def linear_system(self, weights, markers_px, bundles=None, correspondences=None):
        """The weighted least-squares system linearised at ``weights``.

        Returns
        -------
        J : (n,S) float64
        r : (n,) float64
            The solve minimises ``|J w - r|^2`` (+ ridge) in the bounds;
            marker and 2D contour rows are in pixels (depth-normalised Eq. 1).
        """
        md, _ = self._marker_data(markers_px)
        return self._system(np.asarray(weights, float), md, self._bundle_data(bundles), correspondences)

    # ------------------------------------------------------------------ metrics
    def residuals(self, w, markers_px, bundles=None, correspondences=None, delta=None) -> dict:
        """RMS reprojection errors of a solution (pixels; bundles in scene units).

        ``delta`` (V,3) adds a corrective. Contour points are measured against
        their matched pixel (the residual the solvers minimise).
        """
        out = {}
        md, _ = self._marker_data(markers_px)
        err = []
        for c, sel, px in md:
            pts = SurfacePoints(self.markers.vertices[sel], self.markers.bary[sel])
            x = self._mk["x0"][sel] + self._mk["B"][sel] @ w
            if delta is not None:
                x = x + pts.evaluate(delta)
            err.append(np.linalg.norm(self.cameras[c].project(x) - px, axis=1))
        out["marker_rms_px"] = float(np.sqrt(np.mean(np.concatenate(err) ** 2))) if err else float("nan")
        e2 = []
        for cc in correspondences or []:
            if getattr(cc, "pixels", None) is None or cc.camera < 0:
                continue
            x0, B = self._edge_model(cc)
            x = x0 + B @ w
            if delta is not None:
                x = x + np.einsum("ck,ckd->cd", np.asarray(cc.bary, float), delta[np.asarray(cc.vertices)])
            e2.append(np.linalg.norm(self.cameras[cc.camera].project(x) - np.asarray(cc.pixels, float), axis=1))
        out["contour_rms_px"] = float(np.sqrt(np.mean(np.concatenate(e2) ** 2))) if e2 else float("nan")
        return out


# --------------------------------------------------------------------------- corrective
class OutOfSubspaceCorrective:
    """Per-frame out-of-subspace corrective ``ΔV`` (Bhat et al. 2013, §4.3).

    Minimises ``laplacian_weight |L ΔV|^2`` (cotangent Laplacian of the
    neutral) plus ``damping |ΔV|^2`` plus the marker-ray, bundle, contour and
    eyelid 3D terms on ``V_blend + ΔV``, with ``ΔV = 0`` on ``boundary``.
    Factored once here; per-frame solves reuse the factor and the cached
    Woodbury columns.

    Units: ``L`` has dimensionless cotangent weights, so ``|L ΔV|``, the
    ray / plane distances and ``|ΔV|`` are all scene-unit lengths and the
    weights' balance does not depend on the scene scale (centimetres on
    ICT-FaceKit, metres elsewhere). It does depend on the mesh resolution:
    ``|L ΔV|`` of a smooth displacement shrinks with the edge length squared,
    so ``damping`` (and the data weights) gain relative to the Laplacian on
    denser meshes.

    Parameters
    ----------
    neutral : (V,3) float
    faces : (F,3) int
    cameras : list of Camera
    markers, bundles : SurfacePoints or None
        As for :class:`BlendshapeSolver`.
    boundary : (V,) bool, optional
        Vertices held fixed (``ΔV = 0``). Default: the mesh border plus every
        connected component no marker or bundle lies on.
    marker_weight, bundle_weight, contour_weight, eyelid_weight, laplacian_weight : float
        Energy weights (paper: 1, 1, 0.5, 0.5, 1).
    damping : float
        Weight of ``|ΔV|^2`` (not in the paper, whose energy has only the
        Laplacian): keeps the corrective local. With the Laplacian alone a
        constraint that the rig cannot meet (an eyelid target, a lip
        silhouette) bends the whole free surface, since the 80 or so marker
        rays pin it only sideways; on ICT-FaceKit (benchmark) that doubled
        the error away from the eyes and mouth. 0.01 (default) keeps the
        correction within about a centimetre of its constraints on ICT; 0
        is the paper's energy.
    contour_metric : {'plane', 'ray'}
        How a 2D contour point is tied to its tracked pixel. ``'ray'``: the
        distance to the pixel's camera ray (the paper's Eq. 1 in 3D).
        ``'plane'`` (default): the distance to the plane through the ray and
        the curve's image tangent, i.e. the silhouette residual along the
        curve normal only. That plane is the surface's tangent plane at the
        true occluding contour, so it stays right when the rig's silhouette
        sits on a neighbouring edge ring or at another depth, where pulling
        the rig's ring point onto the ray (from two cameras: onto the rays'
        intersection, off the surface) bends the lip.
        (ICT benchmark: inner-lip error 0.30 mm vs 0.32 with rays.)
    warm_vertices : (k,) int, optional
        Vertices whose Woodbury columns are computed up front (e.g. all
        candidate contour-loop vertices), so the first frames are not slower.
    pixel_units : bool
        False (default, the paper's form): 2D marker / contour terms are
        scene-unit distances to the camera rays; with the dimensionless
        cotangent Laplacian the balance does not depend on the scene scale.
        True: the distances are converted to pixels (times ``f / depth``),
        which weights the 2D terms ~(f/depth)^2 more: tighter contours, but
        the corrective then also fits the marker noise.
    """

    def __init__(self, neutral, faces, cameras, markers: SurfacePoints | None, bundles: SurfacePoints | None, *,
                 boundary=None, marker_weight: float = 1.0, bundle_weight: float = 1.0,
                 contour_weight: float = 0.5, eyelid_weight: float = 0.5, laplacian_weight: float = 1.0,
                 warm_vertices=None, pixel_units: bool = False, damping: float = 0.01,
                 contour_metric: str = "plane"):
        V0, F = validate_mesh(neutral, faces, name="neutral mesh")
        self.neutral, self.faces = V0, F
        self.cameras = _check_cameras(cameras)
        self.markers, self.bundles = markers, bundles
        self.marker_weight = float(marker_weight)
        self.bundle_weight = float(bundle_weight)
        self.contour_weight = float(contour_weight)
        self.eyelid_weight = float(eyelid_weight)
        self.pixel_units = bool(pixel_units)
        if contour_metric not in ("plane", "ray"):
            raise FaceLabError(f"contour_metric must be 'plane' or 'ray', got {contour_metric!r}.")
        self.contour_metric = contour_metric
        n = len(V0)
        if boundary is None:
            boundary = self.default_boundary(V0, F, markers, bundles)
        boundary = np.asarray(boundary, bool)
        if boundary.shape != (n,):
            raise FaceLabError(f"The boundary mask must have one entry per vertex ({n}), got {boundary.shape}.")
        self.boundary = boundary
        L = cotangent_laplacian(V0, F)
        t0 = time.perf_counter()
        self.damping = float(damping)
        self.deformer = LaplacianDeformer(L, lambda_reg=float(laplacian_weight), pos_weights=self.damping,
                                          pinned=boundary)
        self.factor_time_s = time.perf_counter() - t0
        if warm_vertices is not None:
            wv = np.unique(np.asarray(warm_vertices, np.int64))
            wv = wv[~boundary[wv]]
            if len(wv):
                self.deformer.solve(V0, constraints=PointConstraints.points(wv, V0[wv], 1e-3))

    @staticmethod
    def default_boundary(vertices, faces, markers=None, bundles=None) -> np.ndarray:
        """(V,) bool: mesh-border vertices plus components no marker/bundle touches."""
        from scipy.sparse.csgraph import connected_components

        n = len(vertices)
        edges, ef = edge_faces(faces)
        b = np.zeros(n, bool)
        b[edges[(ef < 0).any(axis=1)].ravel()] = True
        _, lab = connected_components(vertex_adjacency(faces, n), directed=False)
        used = np.zeros(n, bool)
        for p in (markers, bundles):
            if p is not None and len(p):
                used[p.vertices[p.bound].ravel()] = True
        keep = np.isin(lab, np.unique(lab[used])) if used.any() else np.ones(n, bool)
        return b | ~keep

    def _px_scale(self, cam, X):
        """(n,) squared pixels per squared scene unit at points X, or 1 without ``pixel_units``."""
        if not self.pixel_units:
            return 1.0
        z = np.maximum(cam.depth(X), 1e-12)
        f = 0.5 * (cam.K[0, 0] + cam.K[1, 1])
        return (f / z) ** 2

    def constraints(self, vertices_blend, markers_px, bundles, correspondences) -> PointConstraints | None:
        """The frame's point constraints (marker rays, bundles, contour rays, eyelid points)."""
        Vb = np.asarray(vertices_blend, float)
        items = []
        if self.markers is not None and markers_px is not None:
            mp = np.asarray(markers_px, float)
            if mp.ndim == 2:
                mp = mp[None]
            ok = self.markers.bound
            for c, cam in enumerate(self.cameras):
                sel = np.flatnonzero(np.isfinite(mp[c]).all(axis=1) & cam.in_frame(mp[c]) & ok)
                if len(sel):
                    o, d = cam.rays(mp[c, sel])
                    s = self.marker_weight * self._px_scale(cam, self.markers.subset(sel).evaluate(Vb))
                    items.append(PointConstraints.rays(self.markers.vertices[sel], o, d, s,
                                                       bary=self.markers.bary[sel]))
        if self.bundles is not None and bundles is not None:
            b = np.asarray(bundles, float).reshape(-1, 3)
            sel = np.flatnonzero(np.isfinite(b).all(axis=1) & self.bundles.bound)
            if len(sel):
                items.append(PointConstraints.points(self.bundles.vertices[sel], b[sel], self.bundle_weight,
                                                     bary=self.bundles.bary[sel]))
        for cc in correspondences or []:
            v = np.asarray(cc.vertices, np.int64)
            bb = np.asarray(cc.bary, float)
            if getattr(cc, "pixels", None) is not None and cc.camera >= 0:
                cam = self.cameras[cc.camera]
                o, d = cam.rays(np.asarray(cc.pixels, float))
                s = self.contour_weight * self._px_scale(cam, np.einsum("ck,ckd->cd", bb, Vb[v]))
                if self.contour_metric == "plane" and len(v) >= 2:
                    items.append(PointConstraints(v, bb, o, _contour_planes(d), s))
                else:
                    items.append(PointConstraints.rays(v, o, d, s, bary=bb))
            elif getattr(cc, "targets", None) is not None:
                items.append(PointConstraints.points(v, np.asarray(cc.targets, float), self.eyelid_weight, bary=bb))
        return PointConstraints.concat(items)

    def solve(self, vertices_blend, markers_px, bundles=None, correspondences=None) -> np.ndarray:
        """The corrective ``ΔV`` (V,3), scene units (zero on the boundary)."""
        Vb = np.asarray(vertices_blend, dtype=np.float64)
        if Vb.shape != self.neutral.shape:
            raise FaceLabError(f"Expected {len(self.neutral)} vertices, got {Vb.shape}; the topology changed.")
        C = self.constraints(Vb, markers_px, bundles, correspondences)
        if C is None:
            return np.zeros_like(Vb)
        with small_dense_threads(1):
            X = self.deformer.solve(Vb, Vb, C)
        return X - Vb


def _contour_planes(d):
    """(c,3,3) metrics ``n n^T`` of the planes through a curve's camera rays and the curve tangent.

    ``d`` (c,3): the rays' directions, in curve order. The plane through the
    camera centre that contains the ray of a curve pixel and the curve's
    image tangent there is the surface's tangent plane at the true occluding
    contour point (the ray grazes the surface along the contour), so a
    nearby surface point belongs on it to second order, whichever edge ring
    the silhouette is on and whatever the depth along the ray: the distance
    to this plane is the silhouette residual along the curve normal.
    """
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    tan = np.empty_like(d)
    tan[1:-1] = d[2:] - d[:-2]
    tan[0] = d[1] - d[0]
    tan[-1] = d[-1] - d[-2]
    n = np.cross(d, tan)
    nn = np.linalg.norm(n, axis=1, keepdims=True)
    bad = nn[:, 0] < 1e-12
    n = n / np.maximum(nn, 1e-300)
    P = n[:, :, None] * n[:, None, :]
    if bad.any():  # repeated pixels: fall back to the ray distance there
        P[bad] = np.eye(3)[None] - d[bad, :, None] * d[bad, None, :]
    return P


# --------------------------------------------------------------------------- sequence
def solve_performance(solver: BlendshapeSolver, corrective: OutOfSubspaceCorrective | None, markers_px,
                      bundles=None, curves_per_frame=None, *, progress=None, sliding: bool = True,
                      iterations: int = 1, rematch: bool = True,
                      corrective_iterations: int = 1) -> PerformanceResult:
    """Solve a whole sequence, warm-starting every frame from the previous one.

    Parameters
    ----------
    solver : BlendshapeSolver
    corrective : OutOfSubspaceCorrective or None
    markers_px : (T,C,M,2) float or None
        NaN where a marker is not tracked.
    bundles : (T,B,3) float or None
    curves_per_frame : list (length T) of list of TrackedCurve, or None
    progress : callable(frame_index, n_frames), optional
        Called after each frame.
    sliding, iterations
        See :meth:`BlendshapeSolver.solve_frame`.
    rematch : bool
        Before the corrective, match the contours again on the fitted rig
        mesh (the blendshape fit's correspondences were built on the
        iterate before its last solve), so the corrective's targets (and the
        3D eyelid lifts, which use the lids' current heights) belong to the
        mesh it corrects. A few ms per frame.
    corrective_iterations : int
        Corrective passes; each further pass re-matches the contours on
        ``V_blend + ΔV`` and solves the corrective again (§4.2's alternation
        of correspondence and solve, applied to the corrective).

    Returns
    -------
    PerformanceResult
        Frames with nothing to fit are skipped (NaN weights) and listed in
        ``skipped`` with the reason; the warm start then continues from the
        last solved frame.
    """
    lengths = [len(x) for x in (markers_px, bundles, curves_per_frame) if x is not None]
    if not lengths:
        raise FaceLabError("No tracking data: give marker tracks, bundles or curves to solve the performance.")
    if len(set(lengths)) != 1:
        raise FaceLabError(f"Tracking inputs cover different numbers of frames {lengths}; pass one entry per frame.")
    T = lengths[0]
    V = len(solver.neutral)
    W = np.full((T, solver.S), np.nan)
    D = np.zeros((T, V, 3)) if corrective is not None else None
    skipped, frames, offs, corrs = {}, [], {}, []
    prev = None
    t0 = time.perf_counter()
    for i in range(T):
        mp = None if markers_px is None else markers_px[i]
        bd = None if bundles is None else bundles[i]
        cv = None if curves_per_frame is None else curves_per_frame[i]
        why = solver.has_data(mp, bd, cv)
        if why is not None:
            skipped[i] = why
            frames.append(None)
            corrs.append([])
        else:
            res = solver.solve_frame(mp, bd, cv, previous=prev, iterations=iterations, sliding=sliding)
            W[i] = res.weights
            if res.info.get("markers_offscreen"):
                offs[i] = res.info["markers_offscreen"]
            if corrective is not None:
                t1, c1 = time.perf_counter(), time.process_time()
                Vb = solver.vertices(res.weights)
                cc = res.correspondences
                if rematch and cv:
                    cc = solver.match(res.weights, cv, sliding=sliding, previous=cc)
                D[i] = corrective.solve(Vb, mp, bd, cc)
                for _ in range(max(1, int(corrective_iterations)) - 1):
                    if not cv:
                        break
                    cc = solver.match(res.weights, cv, sliding=sliding, previous=cc, vertices=Vb + D[i])
                    D[i] = corrective.solve(Vb, mp, bd, cc)
                res.info["corrective_contour_points"] = int(sum(len(c.vertices) for c in cc))
                res.info["corrective_time_s"] = time.perf_counter() - t1
                res.info["corrective_cpu_s"] = time.process_time() - c1
            frames.append(res.info)
            corrs.append(res.correspondences if corrective is None else cc)
            prev = res
        if progress is not None:
            progress(i, T)
    return PerformanceResult(weights=W, correctives=D, skipped=skipped,
                             info=dict(frames=frames, time_s=time.perf_counter() - t0, offscreen_markers=offs),
                             correspondences=corrs)
