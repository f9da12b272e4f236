"""Per-frame blendshape fit from markers, bundles and contours.

Bhat, Goldenthal, Ye, Mallet, Koperwas 2013, "High fidelity facial animation
capture and retargeting with contours", §4.1-4.3:

* **Constraints (§4.1).** A marker is a surface point ``x = A V`` (see
  ``core.capture.markers``). A tracked 2D marker ``m`` in a camera with
  projection ``Q`` (3x4) gives the residual of Eq. 1, ``(m_x q2ᵀy - q0ᵀy,
  m_y q2ᵀy - q1ᵀy)`` with ``y = (x, 1)``; a 3D bundle ``p`` gives Eq. 2,
  ``x - p``.
* **Contours (§4.2).** Tracked inner-lip and eyelid curves are matched to the
  mesh's occluding contour each frame by :func:`.matching.match_contours`;
  every matched point lies on a mesh edge and is fitted like a 2D marker (or,
  for eyelid curves projected on the cornea, like a 3D bundle).
* **Blendshape fit (§4.3, Eq. 3).** ``min_w sum_i omega_i E_i(w)`` subject to
  ``-1 <= w <= 1`` with marker and contour weights ``omega = 1``: a bounded
  linear least-squares problem (:func:`.bounded_lsq.box_least_squares`,
  warm-started from the previous frame). Correspondence and solve alternate
  (the paper finds one iteration enough).

The out-of-subspace corrective on top of the fit is in :mod:`.corrective`,
the whole-sequence loop in :mod:`.performance`.

Implementation notes (deviations, all documented in docs/solve.md):

* Eq. 1 is the algebraic (DLT) residual: it is the pixel error times the
  point's depth ``q2ᵀy``. We divide each row by the depth at the current
  estimate, so the residual is in pixels and, after the Gauss-Newton style
  re-linearisation of the outer iterations, exactly the reprojection error.
* A tiny ridge (``regularization`` times the mean diagonal of the normal
  matrix) makes the weights of shapes no constraint sees (e.g. eye gaze with
  skin markers only) zero instead of arbitrary.

Conventions: vertices (V,3) float64 scene units; pixels top-left origin,
y down; cameras ``core.capture.camera.Camera`` (OpenCV).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from ..capture.camera import Camera
from ..capture.markers import SurfacePoints
from ..errors import FaceLabError
from ..geometry.linsolve import small_dense_threads
from ..geometry.mesh import grow_region, validate_mesh, vertex_adjacency
from .bounded_lsq import box_least_squares
from .matching import MatchParams, match_contours

__all__ = [
    "SolveParams", "FrameResult", "BlendshapeSolver", "contour_region", "ANCHOR_RINGS_MOUTH", "ANCHOR_EYE_RADIUS",
]

#: Edge rings around the mouth loops (and, plus the number of eyelid loops, around the eyes) left out of the
#: tie to the markers-only fit (``SolveParams.anchor_weight``).
ANCHOR_RINGS_MOUTH = 2
#: Radius, in eye widths, around the eyelid loops left out of that tie (the lids' skin moves with a blink).
ANCHOR_EYE_RADIUS = 0.5


@dataclass(frozen=True)
class SolveParams:
    """Options of the per-frame blendshape fit (:class:`BlendshapeSolver`).

    Weights are dimensionless factors on squared residuals: marker and 2D
    contour residuals are in pixels, bundle and 3D eyelid residuals in scene
    units. The defaults are the paper's except where noted.

    Weight bounds
    -------------
    bounds : (lo, hi)
        Weight bounds (paper: -1, 1); scalars or (S,) arrays (dimensionless).

    Energy weights
    --------------
    marker_weight, contour_weight, bundle_weight : float
        ``omega`` of each energy (paper: 1).
    regularization : float
        Ridge, relative to the mean diagonal of the normal matrix (dimensionless).

    Contours
    --------
    match : MatchParams
        Contour selection and matching (:func:`.matching.match_contours`),
        among them how eyelid curves are fitted (``match.eyelids``): lifted
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
        IRLS re-solves for ``contour_huber_px``.

    Tie to the markers-only fit
    ---------------------------
    anchor_weight : float
        Tie to the markers-only fit away from the contours (not in the
        paper; dimensionless). With markers and curves, the contour solves add
        ``anchor_weight * n * mean_v |s (x_v(w) - x_v(w_m))|^2 / r^2`` over
        the anchored vertices ``v``: ``w_m`` is the frame's markers-only
        fit, ``r`` its marker reprojection RMS (pixels, at least
        ``anchor_noise_floor_px``: how far the markers can be trusted),
        ``n`` the number of marker observations and ``s`` the cameras'
        pixels per scene unit at the markers. The curves then move the lips
        and lids without explaining a lip the rig cannot reach with jaw and
        cheek shapes the markers contradict; the corrective fits the rest.
        Clean markers (small ``r``) hold the face firmly, noisy ones less.
        0: the paper's fit. The default is chosen on the tuning captures
        (docs/solve.md).
    anchor_noise_floor_px : float or None
        Smallest marker misfit ``r`` (pixels) the anchor is scaled by;
        None or 0: no scaling (``r = 1``).

    Raises
    ------
    FaceLabError
        ``anchor_weight`` negative or not finite.
    """

    bounds: tuple = (-1.0, 1.0)
    marker_weight: float = 1.0
    contour_weight: float = 1.0
    bundle_weight: float = 1.0
    regularization: float = 1e-6
    match: MatchParams = MatchParams()
    contour_huber_px: float | None = 1.0
    robust_iterations: int = 2
    anchor_weight: float = 50.0
    anchor_noise_floor_px: float | None = 0.05

    def __post_init__(self):
        w = float(self.anchor_weight)
        if not (np.isfinite(w) and w >= 0):
            raise FaceLabError(f"anchor_weight must be a non-negative number, got {self.anchor_weight!r}; use 0 to "
                               "turn the tie to the markers-only fit off.")


@dataclass
class FrameResult:
    """One solved frame.

    Attributes
    ----------
    weights : (S,) float64
        Blendshape weights, inside the bounds.
    correspondences : list of CurveCorrespondence
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


def contour_region(vertices, faces, loops) -> np.ndarray:
    """(V,) bool: where tracked curves inform the face: around the mouth loops and the eyes.

    The mouth loops (lip weld to lip fronts) grown by :data:`ANCHOR_RINGS_MOUTH`
    edge rings, and every vertex within :data:`ANCHOR_EYE_RADIUS` eye widths
    (corner to corner) of an eye's lid loops and eyeball (the lids' skin moves
    with a blink well beyond the lid loops).

    Parameters
    ----------
    vertices : (V,3) float
        Rest mesh, scene units.
    faces : (F,3) int
    loops : ContourLoops
    """
    V = np.asarray(vertices, float)
    n = len(V)
    mouth = np.zeros(n, bool)
    for v in loops.mouth:
        mouth[np.asarray(v, np.int64).ravel()] = True
    region = grow_region(mouth, vertex_adjacency(faces, n), ANCHOR_RINGS_MOUTH)
    for side, lp in loops.eyes.items():
        ids = np.unique(np.concatenate([np.asarray(v, np.int64).ravel() for v in lp]
                                       + [np.asarray(loops.eyeballs.get(side, []), np.int64)]))
        P = V[ids]
        width = float(np.linalg.norm(P.max(axis=0) - P.min(axis=0)))
        d, _ = cKDTree(P).query(V, distance_upper_bound=ANCHOR_EYE_RADIUS * width)
        region |= np.isfinite(d)
    return region


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


def check_cameras(cameras):
    cams = list(cameras or [])
    for i, c in enumerate(cams):
        if not isinstance(c, Camera):
            raise FaceLabError(
                f"Camera {i} has no calibration (got {type(c).__name__}); give every tracking camera its "
                "intrinsics and pose (solve the camera in the Movie Clip editor or set the lens)."
            )
    return cams


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
    loops : ContourLoops or None
        Candidate contour loops (needed to use tracked curves).
    params : SolveParams
        Bounds, term weights, contour and anchor options.
    anchor_mask : (V,) bool, optional
        The anchored vertices of ``params.anchor_weight``. Default: every
        vertex the rig moves except the mouth loops grown by
        :data:`ANCHOR_RINGS_MOUTH` rings and everything within
        :data:`ANCHOR_EYE_RADIUS` eye widths of the eyelid loops and
        eyeballs (:func:`contour_region`).
    """

    def __init__(self, neutral, deltas, faces, cameras, markers: SurfacePoints | None, bundles: SurfacePoints | None,
                 loops=None, *, params: SolveParams = SolveParams(), anchor_mask=None):
        V0, F = validate_mesh(neutral, faces, name="neutral mesh")
        self.params = params
        self.anchor_weight = float(params.anchor_weight)
        self.anchor_noise_floor_px = float(params.anchor_noise_floor_px or 0.0)
        self.contour_huber_px = None if not params.contour_huber_px else float(params.contour_huber_px)
        self.robust_iterations = int(params.robust_iterations)
        self.match_params = params.match
        D = np.asarray(deltas, dtype=np.float64)
        if D.ndim != 3 or D.shape[1:] != V0.shape or D.shape[0] == 0:
            raise FaceLabError(
                f"The rig has no usable shape keys (deltas shape {D.shape}, mesh {V0.shape}); add blendshape "
                "shape keys to the face (with the same vertex count as the Basis)."
            )
        self.neutral, self.faces, self.deltas = V0, F, D
        self.S = D.shape[0]
        self.cameras = check_cameras(cameras)
        self.loops = loops
        lo, hi = params.bounds
        self.lo = np.broadcast_to(np.asarray(lo, float), (self.S,)).copy()
        self.hi = np.broadcast_to(np.asarray(hi, float), (self.S,)).copy()
        if np.isnan(self.lo).any() or np.isnan(self.hi).any():
            raise FaceLabError("The weight bounds contain NaN; give numbers such as (-1, 1).")
        if (self.lo > self.hi).any():
            raise FaceLabError("Lower weight bounds exceed the upper ones; check the bounds.")
        self.marker_weight = float(params.marker_weight)
        self.contour_weight = float(params.contour_weight)
        self.bundle_weight = float(params.bundle_weight)
        self.regularization = float(params.regularization)
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
        self._anchor_G, self.anchor_vertices = None, np.zeros(0, np.int64)
        if loops is not None and self.anchor_weight > 0 and markers is not None and len(markers):
            self._anchor_G, self.anchor_vertices = self._anchor_matrix(loops, anchor_mask)

    # ------------------------------------------------------------------ model
    def _bind(self, pts: SurfacePoints | None):
        if pts is None or len(pts) == 0:
            return None
        ok = pts.bound
        vid = np.maximum(pts.vertices, 0)
        x0 = np.einsum("mk,mkd->md", pts.bary, self.neutral[vid])
        B = np.einsum("mk,smkd->mds", pts.bary, self.deltas[:, vid])  # (m,3,S)
        return dict(ok=ok, x0=x0, B=B)

    def _anchor_matrix(self, loops, anchor_mask):
        """``G`` (S,S): ``w^T G w`` is the mean squared pixel-equivalent motion of the anchored vertices.

        Anchored vertices: ``anchor_mask`` or, by default, every vertex the
        rig moves outside :func:`contour_region`. Motions are converted to pixels
        with the cameras' focal length over the markers' mean depth.
        """
        n = len(self.neutral)
        if anchor_mask is None:
            moving = (np.abs(self.deltas).max(axis=(0, 2)) > 1e-9 * max(1.0, float(np.abs(self.neutral).max())))
            mask = moving & ~contour_region(self.neutral, self.faces, loops)
        else:
            mask = np.asarray(anchor_mask, bool)
            if mask.shape != (n,):
                raise FaceLabError(f"anchor_mask must have one entry per vertex ({n}), got {mask.shape}.")
        idx = np.flatnonzero(mask)
        if len(idx) == 0:
            return None, idx
        X = self._mk["x0"][self._mk["ok"]] if self._mk is not None else self.neutral[idx]
        scale2 = []
        for c in self.cameras:
            z = np.maximum(c.depth(X), 1e-12)
            scale2.append(np.mean((0.5 * (c.K[0, 0] + c.K[1, 1]) / z) ** 2))
        Dm = self.deltas[:, idx].reshape(self.S, -1)
        G = (Dm @ Dm.T) * (float(np.mean(scale2)) / len(idx))
        return G, idx

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
        curves : list of TrackedCurve
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
        if not curves:
            return []
        if self.loops is None:
            raise FaceLabError(
                "Tracked curves were given but the solver has no contour loops; build them with "
                "contour_loops(rest_vertices, faces) and pass loops= to BlendshapeSolver."
            )
        V = self._partial_vertices(np.asarray(weights, float)) if vertices is None else np.asarray(vertices, float)
        return match_contours(V, self.faces, self.cameras, curves, self.loops, self.match_params,
                              previous=None if sliding else previous, sliding=sliding)

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
        curves : list of TrackedCurve or None
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
                "contour_loops(rest_vertices, faces) and pass loops= to BlendshapeSolver."
            )
        if not md and bd is None and not use_curves:
            raise FaceLabError("This frame has no tracked markers, bundles or curves; nothing to fit.")
        w = np.zeros(self.S) if previous is None else np.clip(np.asarray(previous.weights, float), self.lo, self.hi)
        prev_corr = None if previous is None else previous.correspondences
        corr = []
        it_done = 0
        anchor = None
        with small_dense_threads(1):
            if use_curves and (md or bd is not None):
                # markers/bundles first: the contour correspondence is then built on a close mesh
                for _ in range(1 if previous is not None else 2):  # 2: re-linearise the depths from the neutral
                    w = self._solve_linear(w, *self._system(w, md, bd, None))
                if self._anchor_G is not None and md:
                    # tie to the markers-only fit away from the contours: the contours may move the lips and lids,
                    # not explain an out-of-span lip with jaw and cheek shapes the markers do not see
                    n_obs = sum(len(sel) for _, sel, _ in md)
                    k = self.anchor_weight * n_obs
                    if self.anchor_noise_floor_px > 0:  # in units of the markers' own misfit (noise level)
                        res_px = self.residuals(w, markers_px)["marker_rms_px"]
                        k /= max(res_px, self.anchor_noise_floor_px) ** 2
                    anchor = (k * self._anchor_G, w.copy())
            n_it = max(1, int(iterations)) if use_curves else max(2, int(iterations))  # markers: re-linearise once
            for it in range(n_it):
                if use_curves:
                    Vc = self._partial_vertices(w)
                    # sliding: select and match afresh on the current mesh (a previous loop would win silhouette
                    # ties against the loop closest to the curve); fixed: keep the previous assignment
                    corr = match_contours(Vc, self.faces, self.cameras, curves, self.loops, self.match_params,
                                          previous=None if sliding else prev_corr, sliding=sliding)
                    prev_corr = corr
                w_new = self._solve_linear(w, *self._system(w, md, bd, corr), anchor=anchor if corr else None)
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
                    w_new = self._solve_linear(w, *self._system(w, md, bd, corr, pw), anchor=anchor)
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

    def _solve_linear(self, w, J, r, anchor=None):
        """Bounded least squares ``min |J w - r|^2 + ridge |w|^2`` in the bounds, warm-started at ``w``.

        ``anchor``: optional ``(A (S,S), w_a (S,))`` adding ``(w - w_a)^T A (w - w_a)``.
        """
        H = J.T @ J
        g = J.T @ r
        ridge = self.regularization * max(float(np.trace(H)) / self.S, 1e-12)
        if anchor is not None:
            A, wa = anchor
            H = H + A
            g = g + A @ wa
        H[np.diag_indices_from(H)] += ridge
        w_new, _ = box_least_squares(H, g, self.lo, self.hi, w)
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
