"""Solving a whole performance: the blendshape fit and corrective, frame after frame.

Bhat et al. 2013, "High fidelity facial animation capture and retargeting
with contours", §4: every frame is fitted by a
:class:`~facelab_addon.core.solve.blendshape_solve.BlendshapeSolver`
warm-started from the previous frame (weights and contour correspondence),
then optionally corrected by an
:class:`~facelab_addon.core.solve.corrective.OutOfSubspaceCorrective`, with
the contours matched again on the fitted rig before the corrective. Frames
with nothing to fit are skipped and reported.

Conventions: vertices (V,3) float64 scene units; pixels top-left origin,
y down; time in seconds.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ..errors import FaceLabError
from .blendshape_solve import BlendshapeSolver
from .corrective import OutOfSubspaceCorrective

__all__ = ["PerformanceParams", "PerformanceResult", "solve_performance"]


@dataclass(frozen=True)
class PerformanceParams:
    """How :func:`solve_performance` alternates contour matching, the blendshape fit and the corrective.

    Counts are passes per frame; thresholds are in pixels.

    Blendshape fit
    --------------
    sliding : bool
        Sliding contours (paper): match the contours afresh every frame;
        False keeps the previous frame's correspondence (fixed contours,
        Fig. 6). See :meth:`BlendshapeSolver.solve_frame`.
    iterations : int
        Correspondence / solve alternations of the fit
        (:meth:`BlendshapeSolver.solve_frame`).

    Corrective
    ----------
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
    lip_passes : int
        After the corrective: match the contours again on ``V_blend + ΔV``
        and solve the corrective again inside its lip band
        (:meth:`OutOfSubspaceCorrective.lip_band_solve`, the rest of the face
        held), this many times. On a steep view the rig's occluding contour
        can sit several edge rings from the truth's; the corrected mesh's is
        nearer; ``CorrectiveParams.lip_contour_weight`` and ``lip_damping``
        take the rim onto the line. Needs a corrective built with a
        ``lip_band`` (skipped without one: a whole-surface re-solve is
        ``corrective_iterations``); each pass costs a contour match and a
        solve on the band's vertices only. The default is chosen on the
        tuning cases.

    Lip line pass
    -------------
    lip_line_pass : bool
        After the corrective and the lip passes, re-match the contours on
        ``V_blend + ΔV`` and run :meth:`OutOfSubspaceCorrective.lip_line_pass`
        on the contour points still more than ``lip_line_threshold_px`` from
        their curve (on frames where a curve is more than
        ``lip_line_curve_px`` RMS off): a tighter visible lip line at some
        cost in the hidden inner-lip band (measured in docs/solve.md).
        About one more corrective solve and contour match per frame.
    lip_line_threshold_px, lip_line_curve_px : float
        Pixels; see ``lip_line_pass``.
    """

    sliding: bool = True
    iterations: int = 1
    rematch: bool = True
    corrective_iterations: int = 1
    lip_passes: int = 2
    lip_line_pass: bool = False
    lip_line_threshold_px: float = 0.5
    lip_line_curve_px: float = 0.0


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
        again on the fitted rig, see ``PerformanceParams.rematch``); empty lists
        without curves or for skipped frames.
    """

    weights: np.ndarray
    correctives: np.ndarray | None
    skipped: dict
    info: dict
    correspondences: list = field(default_factory=list)


def solve_performance(solver: BlendshapeSolver, corrective: OutOfSubspaceCorrective | None, markers_px,
                      bundles=None, curves_per_frame=None, *, params: PerformanceParams = PerformanceParams(),
                      progress=None, corrective_sink=None) -> PerformanceResult:
    """Solve a whole sequence, warm-starting every frame from the previous one.

    Parameters
    ----------
    solver : BlendshapeSolver
    corrective : OutOfSubspaceCorrective or None
    markers_px : (T,C,M,2) float or None
        Pixels; NaN where a marker is not tracked.
    bundles : (T,B,3) float or None
        Scene units; NaN rows are missing.
    curves_per_frame : list (length T) of list of TrackedCurve, or None
    params : PerformanceParams
        Passes of contour matching, fit and corrective per frame.
    progress : callable(frame_index, n_frames), optional
        Called after each frame.
    corrective_sink : callable(frame_index, dV), optional
        Each solved frame's corrective ``dV`` (V,3) is handed to it (in frame
        order) instead of being kept: ``correctives`` is then None and memory
        does not grow with frames times vertices.

    Returns
    -------
    PerformanceResult
        Frames with nothing to fit are skipped (NaN weights) and listed in
        ``skipped`` with the reason; the warm start then continues from the
        last solved frame.
    """
    p = params
    lengths = [len(x) for x in (markers_px, bundles, curves_per_frame) if x is not None]
    if not lengths:
        raise FaceLabError("No tracking data: give marker tracks, bundles or curves to solve the performance.")
    if len(set(lengths)) != 1:
        raise FaceLabError(f"Tracking inputs cover different numbers of frames {lengths}; pass one entry per frame.")
    T = lengths[0]
    V = len(solver.neutral)
    W = np.full((T, solver.S), np.nan)
    keep = corrective is not None and corrective_sink is None
    D = np.zeros((T, V, 3)) if keep else None
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
            res = solver.solve_frame(mp, bd, cv, previous=prev, iterations=p.iterations, sliding=p.sliding)
            W[i] = res.weights
            if res.info.get("markers_offscreen"):
                offs[i] = res.info["markers_offscreen"]
            if corrective is not None:
                t1, c1 = time.perf_counter(), time.process_time()
                Vb = solver.vertices(res.weights)
                cc = res.correspondences
                if p.rematch and cv:
                    cc = solver.match(res.weights, cv, sliding=p.sliding, previous=cc)
                d = corrective.solve(Vb, mp, bd, cc)
                for _ in range(max(1, int(p.corrective_iterations)) - 1):
                    if not cv:
                        break
                    cc = solver.match(res.weights, cv, sliding=p.sliding, previous=cc, vertices=Vb + d)
                    d = corrective.solve(Vb, mp, bd, cc)
                for _ in range(max(0, int(p.lip_passes))):
                    if not cv or corrective.band_deformer is None:
                        break
                    cc = solver.match(res.weights, cv, sliding=p.sliding, previous=cc, vertices=Vb + d)
                    d = corrective.lip_band_solve(Vb, d, mp, bd, cc)
                if p.lip_line_pass and cv and corrective.off_the_line(Vb + d, cc, cv, p.lip_line_curve_px):
                    cc = solver.match(res.weights, cv, sliding=p.sliding, previous=cc, vertices=Vb + d)
                    d = corrective.lip_line_pass(Vb, d, mp, bd, cc, cv, threshold_px=p.lip_line_threshold_px,
                                                 curve_threshold_px=p.lip_line_curve_px)
                if keep:
                    D[i] = d
                else:
                    corrective_sink(i, d)
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
