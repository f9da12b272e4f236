"""The lip-sync heuristic: a creature's lips talk like the actor's (Bhat et al. 2013, §5.1, Fig. 8c/10).

"High fidelity facial animation capture and retargeting with contours": on a
creature whose mouth is much wider than the actor's, the inner-lip shape is
no longer lip-readable, because the semantic correspondence along the lips
is lost. The heuristic picks a *talking portion* of the creature's inner-lip
contours whose length approximately matches the actor's lips
(:mod:`.lip_contours`; artists may override its end points on any frame),
associates its new end points with the actor's lip corners, pairs the
interior points of the upper and lower contours by arc length (as §4.2 does
for tracked curves), and solves the out-of-subspace deformation (§4.3, the
shared ``core.geometry.deform.LaplacianDeformer``) on top of the
deformation-transferred frame with two extra constraint sets:

* along the talking portion, the vector between corresponding points on the
  creature's upper and lower lip equals the actor's (so the upper-to-lower
  lip distances match the actor's);
* between each original corner and its new end point, corresponding upper
  and lower points are at zero distance (the paper's "zero length": the
  creature's lips are sealed there and the end points become the mouth
  corners that talk).

Interpretation choices (the paper gives no formulas): the distance
constraints are vector constraints (linear, so the solver stays one
factorisation); the sealed pairs are matched by the same fraction of arc
length from the corner on both lips.

Smooth corners: the automatically found inner-lip loops (ICT) zigzag near the
corners (a few vertices of a neighbouring edge row), so pairs of actor and
creature points at equal arc fractions land at different places of the
detours and the raw vector targets jump by millimetres between neighbouring
pairs. The change each talking-portion pair asks for is therefore low-passed
along the mouth (Gaussian, ``LipSyncParams.smooth``), and the constraints are
soft (``strength`` and ``seal_strength`` against the Laplacian term): near-hard
constraints on the raw targets tear the creature's lips at the new corners.

Units: positions in scene units; end points are fractions of arc length.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import FaceLabError, RegionError
from ..geometry.deform import LaplacianDeformer, PointConstraints
from ..geometry.geodesic import geodesic_distance
from ..geometry.laplacian import cotangent_laplacian
from ..geometry.linsolve import small_dense_threads
from ..geometry.polyline import arc_length
from .lip_contours import (
    EndPoints,
    LipContours,
    resolve_end_points,
    contour_points,
    lip_sync_end_points,
)

__all__ = ["LipSyncParams", "LipSync"]


@dataclass(frozen=True)
class LipSyncParams:
    """Options of the lip-sync deformer (:class:`LipSync`).

    The weights are dimensionless: every term is a squared scene-unit length.

    Attributes
    ----------
    radius : float or None
        Vertices within this geodesic distance (along edges, scene units) of
        the creature's contours may move; the rest is held. None: 0.8 x the
        creature's corner-to-corner mouth width.
    strength : float
        Weight of the talking-portion constraints against the
        cotangent-Laplacian term (weight ``lambda_reg``). Soft by default:
        the pairs over-determine the lips, and near-hard constraints on the
        raw targets tear the creature's lip corners where the contours zigzag.
    seal_strength : float
        Weight of the sealing (zero-distance) constraints between each
        original corner and its new end point.
    lambda_reg : float
        Weight of the Laplacian term.
    smooth : float
        Width (standard deviation, fraction of the creature's upper-lip arc
        length, dimensionless) of the Gaussian that low-passes the change the
        talking-portion pairs ask for along the mouth; 0 turns it off. Sealed
        pairs are never smoothed (they close exactly).
    """

    radius: float | None = None
    strength: float = 10.0
    seal_strength: float = 100.0
    lambda_reg: float = 1.0
    smooth: float = 0.02


class LipSync:
    """Factor-once lip-sync deformer for one creature (Bhat §5.1, Fig. 8c).

    Parameters
    ----------
    creature_rest : (W,3) array_like
        Creature rest positions, scene units.
    creature_faces : (F,3) int array_like
        Creature triangles.
    creature_contours : LipContours
        The creature's inner-lip contours.
    actor_contours : LipContours
        The actor's inner-lip contours (vertex ids of the actor mesh).
    params : LipSyncParams
        Reach, constraint weights and smoothing.
    backend : str
        ``SPDFactor`` backend.
    """

    def __init__(self, creature_rest, creature_faces, creature_contours: LipContours, actor_contours: LipContours, *,
                 params: LipSyncParams = LipSyncParams(), backend: str = "auto"):
        V = np.asarray(creature_rest, dtype=np.float64)
        F = np.asarray(creature_faces, dtype=np.int64)
        self.creature_rest = V
        self.faces = F
        self.creature_contours = creature_contours
        self.actor_contours = actor_contours
        cv = creature_contours.vertices
        if cv.max() >= len(V):
            raise RegionError(
                f"The creature's lip contours refer to vertex {int(cv.max())} but it has {len(V)} vertices; "
                "rebuild the contours on the creature mesh."
            )
        width = float(np.linalg.norm(V[creature_contours.corners[0]] - V[creature_contours.corners[1]]))
        self.params = params
        self.radius = 0.8 * width if params.radius is None else float(params.radius)
        dist = geodesic_distance(V, F, cv, limit=self.radius, exact=False)
        self.free = np.isfinite(dist)
        self.strength = float(params.strength)
        self.smooth = float(params.smooth)
        self.seal_strength = float(params.seal_strength)
        L = cotangent_laplacian(V, F)
        self.deformer = LaplacianDeformer(L, lambda_reg=params.lambda_reg, pos_weights=1e-6, pinned=~self.free,
                                          backend=backend)

    def end_points(self, actor_frame, creature_frame, *, end_points=None, threshold: float = 0.0) -> EndPoints:
        """The artist's end points if given, else :func:`lip_sync_end_points`."""
        ep = resolve_end_points(end_points)
        if ep is None:
            ep = lip_sync_end_points(actor_frame, self.actor_contours, creature_frame, self.creature_contours,
                                     threshold=threshold)
        return ep

    def constraints(self, actor_frame, creature_frame, end_points: EndPoints) -> PointConstraints:
        """Lip-distance and sealing constraints for one frame.

        Parameters
        ----------
        actor_frame : (V,3) array_like
            Actor positions (blendshapes + corrective), scene units.
        creature_frame : (W,3) array_like
            Deformation-transferred creature positions, scene units (arc
            lengths are measured on it).
        end_points : EndPoints

        Returns
        -------
        PointConstraints
            Four-vertex constraints ``x_upper - x_lower = d`` (edge points
            with barycentric weights ``b`` and ``-b``).
        """
        A = np.asarray(actor_frame, dtype=np.float64)
        C = np.asarray(creature_frame, dtype=np.float64)
        ep = end_points
        ac, cc = self.actor_contours, self.creature_contours
        fu_all = arc_length(C[cc.upper])
        fu_all = fu_all / fu_all[-1]  # arc fraction of every upper-contour vertex
        fl_all = arc_length(C[cc.lower])
        fl_all = fl_all / fl_all[-1]

        def params(lo_u, hi_u, lo_l, hi_l):
            """Normalised positions in [0,1] of both lips' vertices inside the given spans, and the span ends.

            Between consecutive positions both lips are straight, so the pairs are controlled along the whole
            contour. (The pairs over-determine the lips by one point per coordinate, since moving both lips
            together changes no distance; least squares spreads that, about 0.3 mm on ICT with a 22 mm jaw
            opening, instead of leaving a span unconstrained.)
            """
            p = [np.array([0.0, 1.0])]
            if hi_u > lo_u:
                q = (fu_all - lo_u) / (hi_u - lo_u)
                p.append(q[(q > 0) & (q < 1)])
            if hi_l > lo_l:
                q = (fl_all - lo_l) / (hi_l - lo_l)
                p.append(q[(q > 0) & (q < 1)])
            return np.unique(np.round(np.concatenate(p), 12))

        # talking portion: the creature's span [e_l, e_r] maps onto the actor's whole contour
        u = params(ep.upper[0], ep.upper[1], ep.lower[0], ep.lower[1])
        _, _, au = contour_points(A, ac.upper, u)
        _, _, al = contour_points(A, ac.lower, u)
        eu, bu, _ = contour_points(C, cc.upper, ep.upper[0] + u * (ep.upper[1] - ep.upper[0]))
        el, bl, _ = contour_points(C, cc.lower, ep.lower[0] + u * (ep.lower[1] - ep.lower[0]))
        verts = [np.concatenate([eu, el], axis=1)]
        bary = [np.concatenate([bu, -bl], axis=1)]
        targets = [au - al]
        # sealed parts: original corner -> new end point, same fraction on both lips, zero distance
        for side in (0, 1):
            fu = ep.upper[0] if side == 0 else 1.0 - ep.upper[1]
            fl = ep.lower[0] if side == 0 else 1.0 - ep.lower[1]
            if max(fu, fl) <= 1e-9:
                continue
            if side == 0:
                v = params(0.0, fu, 0.0, fl)
            else:
                v = 1.0 - params(ep.upper[1], 1.0, ep.lower[1], 1.0)
            v = v[(v > 0) & (v < 1)]  # v=0: the corner itself, v=1: the talking portion's end
            if len(v) == 0:
                continue
            pu = v * fu if side == 0 else 1.0 - v * fu
            pl = v * fl if side == 0 else 1.0 - v * fl
            e1, b1, _ = contour_points(C, cc.upper, pu)
            e2, b2, _ = contour_points(C, cc.lower, pl)
            verts.append(np.concatenate([e1, e2], axis=1))
            bary.append(np.concatenate([b1, -b2], axis=1))
            targets.append(np.zeros((len(v), 3)))
        V4 = np.concatenate(verts)
        B4 = np.concatenate(bary)
        T = np.concatenate(targets)
        if self.smooth > 0:
            n_talk = len(targets[0])
            talk = np.zeros(len(V4), bool)
            talk[:n_talk] = True
            T, g = self._smooth_targets(C, V4, B4, T, talk)
        st = np.full(len(V4), self.seal_strength)
        n_talk = len(targets[0])
        if self.smooth > 0:  # the new corners hold like the seal, easing to the soft talking strength inside
            st[:n_talk] = self.strength + (1.0 - g[:n_talk]) * (self.seal_strength - self.strength)
        else:
            st[:n_talk] = self.strength
        return PointConstraints(V4, B4, T, np.broadcast_to(np.eye(3), (len(V4), 3, 3)), st)

    def _smooth_targets(self, C, V4, B4, T, talk):
        """Low-pass the requested change of the lip vectors along the mouth (Gaussian, ``self.smooth``).

        The automatically found inner-lip loops zigzag near the corners (a few vertices of the next edge row), so
        the paired points of actor and creature do not sit at matching places of the detours: the raw targets jump
        by millimetres between neighbouring pairs, and strong constraints tear the lips there. The change each pair
        asks for, ``target - (x_upper - x_lower)`` on the current creature frame, is smoothed along the creature's
        upper lip (arc fraction of each pair's upper point); the targets become the current vectors plus the
        smoothed change, so every pair moves like its neighbours and the detours are carried along.
        """
        cc = self.creature_contours
        cur = np.einsum("ck,ckd->cd", B4, C[V4])  # current x_upper - x_lower of every pair (B4 holds b and -b)
        s = arc_length(C[cc.upper])
        s = s / s[-1]
        pos = np.empty(len(V4))
        for k in range(len(V4)):  # arc fraction of the upper point (first two entries: the upper edge)
            i0, i1 = V4[k, 0], V4[k, 1]
            j0 = np.flatnonzero(cc.upper == i0)
            j1 = np.flatnonzero(cc.upper == i1)
            pos[k] = B4[k, 0] * s[j0[0]] + B4[k, 1] * s[j1[0]]
        change = T - cur
        w = np.exp(-0.5 * ((pos[:, None] - pos[None, :]) / self.smooth) ** 2)
        w /= w.sum(axis=1, keepdims=True)
        # keep the talking portion's two end pairs (the new corners: the actor's corners, zero vector) exact, easing
        # into the smoothed change over one smoothing width
        u = np.clip(np.minimum(pos - pos[talk].min(), pos[talk].max() - pos) / self.smooth, 0.0, 1.0)
        g = np.where(talk, 0.5 - 0.5 * np.cos(np.pi * u), 0.0)[:, None]
        return cur + change + g * (w @ change - change), g[:, 0]

    def solve(self, actor_frame, creature_frame, *, end_points=None, threshold: float = 0.0):
        """Lip-sync shape of one frame.

        Parameters
        ----------
        actor_frame : (V,3) array_like
            Actor positions, scene units.
        creature_frame : (W,3) array_like
            Deformation-transferred creature positions (blendshapes with copied
            weights plus the transferred corrective), scene units.
        end_points : EndPoints or (2,) / (4,) fractions, optional
            Artist override for this frame; default automatic.
        threshold : float
            Distance threshold of :func:`lip_sync_end_points`, scene units.

        Returns
        -------
        positions : (W,3) float64 ndarray
            Creature positions with the lip-sync constraints, scene units.
        info : dict
            ``end_points`` (EndPoints) and ``constraints`` (count).
        """
        A = np.asarray(actor_frame, dtype=np.float64)
        C = np.asarray(creature_frame, dtype=np.float64)
        if C.shape != self.creature_rest.shape:
            raise FaceLabError(
                f"The creature frame has {C.shape[0]} vertices, the creature mesh {len(self.creature_rest)}; "
                "use frames of the creature the lip-sync was built for."
            )
        if not (np.isfinite(A).all() and np.isfinite(C).all()):
            raise FaceLabError("The actor or creature frame has NaN coordinates; fix the solve of this frame first.")
        ep = self.end_points(A, C, end_points=end_points, threshold=threshold)
        cons = self.constraints(A, C, ep)
        with small_dense_threads(1):
            X = self.deformer.solve(C, C, cons)
        return X, {"end_points": ep, "constraints": len(cons)}
