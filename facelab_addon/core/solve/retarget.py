"""Retargeting a solved performance to a creature, with the lip-sync heuristic.

Bhat et al. 2013, "High fidelity facial animation capture and retargeting
with contours", §5.1 and Fig. 8/10:

1. the actor's blendshapes are carried to the creature by deformation
   transfer (``core.solve.deformation_transfer``), giving parallel rigs; the solved
   weights are copied and the per-frame correctives are transferred too;
2. on a creature whose mouth is much wider than the actor's, the inner-lip
   shape is no longer lip-readable, because the semantic correspondence
   along the lips is lost. The *lip-sync heuristic* picks a *talking portion*
   of the creature's inner-lip contours whose length approximately matches
   the actor's lips (a distance threshold sets how much longer it may be, and
   artists may override the end points on any frame), associates its new end
   points with the actor's lip corners, pairs the interior points of the
   upper and lower contours by arc length (as §4.2 does for tracked curves),
   and solves the out-of-subspace deformation (§4.3, the shared
   ``core.geometry.deform.LaplacianDeformer``) on top of the deformation-transferred
   frame with two extra constraint sets:

   * along the talking portion, the vector between corresponding points on
     the creature's upper and lower lip equals the actor's (so the
     upper-to-lower lip distances match the actor's);
   * between each original corner and its new end point, corresponding upper
     and lower points are at zero distance (the paper's "zero length": the
     creature's lips are sealed there and the end points become the mouth
     corners that talk).

Interpretation choices (the paper gives no formulas): the talking portion is
centred on the middle (by arc length) of each contour and its length is
``min(creature length, actor length + threshold)``, measured on the current
frames of actor and creature; the distance constraints are vector constraints
(linear, so the solver stays one factorisation); the sealed pairs are matched
by the same fraction of arc length from the corner on both lips.

Smooth corners: the automatically found inner-lip loops (ICT) zigzag near the
corners (a few vertices of a neighbouring edge row), so pairs of actor and
creature points at equal arc fractions land at different places of the
detours and the raw vector targets jump by millimetres between neighbouring
pairs. The change each talking-portion pair asks for is therefore low-passed
along the mouth (Gaussian, ``smooth``), and the constraints are soft
(``strength`` 10, ``seal_strength`` 100 against the Laplacian term): strong (1000) constraints on the
raw targets tore the creature's lips at the new corners.

Inner-lip contours: the closed inner-lip edge loop (``core.lips.regions.inner_lip_loop``
or an artist's edge-loop selection), split at the two mouth corners into an
upper and a lower contour, both ordered from the left corner to the right one
(left = smaller coordinate along ``up x forward``).

Units: positions in scene units; end points are fractions of arc length.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import FaceLabError, RegionError
from ..geometry.deform import LaplacianDeformer, PointConstraints
from ..geometry.geodesic import geodesic_distance
from ..geometry.laplacian import cotangent_laplacian
from ..geometry.linsolve import small_dense_threads
from ..lips.lip_loop import inner_lip_loop, order_edge_loop
from .deformation_transfer import DeformationTransfer

__all__ = [
    "LipContours",
    "EndPoints",
    "lip_contours",
    "contour_points",
    "lip_sync_end_points",
    "end_points_from_vertices",
    "lip_distances",
    "LipSync",
    "Retargeter",
    "RetargetResult",
    "retarget_performance",
    "widen_mouth",
]

ICT_UP = (0.0, 1.0, 0.0)
ICT_FORWARD = (0.0, 0.0, 1.0)


# --------------------------------------------------------------------------
# Contours
# --------------------------------------------------------------------------


@dataclass
class LipContours:
    """Upper and lower inner-lip contours of one mesh.

    Attributes
    ----------
    upper, lower : (a,), (b,) int64 ndarray
        Vertex ids in order from the left mouth corner to the right one, both
        corners included (``upper[0] == lower[0]``, ``upper[-1] == lower[-1]``).
    """

    upper: np.ndarray
    lower: np.ndarray

    def __post_init__(self):
        self.upper = np.asarray(self.upper, dtype=np.int64).ravel()
        self.lower = np.asarray(self.lower, dtype=np.int64).ravel()
        if len(self.upper) < 2 or len(self.lower) < 2:
            raise RegionError("Each inner-lip contour needs at least 2 vertices; select the whole inner-lip edge loop.")
        if self.upper[0] != self.lower[0] or self.upper[-1] != self.lower[-1]:
            raise RegionError(
                "The upper and lower inner-lip contours must start at the same left corner and end at the same "
                "right corner; rebuild them with lip_contours()."
            )

    @property
    def corners(self) -> np.ndarray:
        """(2,) int64: left and right mouth-corner vertex ids."""
        return np.array([self.upper[0], self.upper[-1]])

    @property
    def vertices(self) -> np.ndarray:
        """(n,) int64: every contour vertex once."""
        return np.unique(np.r_[self.upper, self.lower])


def _unit(v):
    v = np.asarray(v, dtype=np.float64).reshape(3)
    n = np.linalg.norm(v)
    if n < 1e-12:
        raise FaceLabError("An axis vector is zero; pass non-zero 'up' and 'forward' directions.")
    return v / n


def lip_contours(rest_vertices, faces, loop=None, *, corners=None, up=ICT_UP, forward=ICT_FORWARD) -> LipContours:
    """Split the inner-lip loop at the mouth corners into upper and lower contours.

    Parameters
    ----------
    rest_vertices : (V,3) array_like
        Rest positions (lips closed or nearly closed), scene units.
    faces : (F,3) int array_like
        Triangles.
    loop : (L,) int array_like, optional
        The closed inner-lip edge loop (any order, for example a Blender
        edge-loop selection). Default: found by ``regions.inner_lip_loop``.
    corners : (2,) int array_like, optional
        The two mouth-corner vertices (on the loop); default: the loop's
        extremes along ``up x forward``.
    up, forward : (3,) float
        Face up direction and the direction the face looks (ICT: +Y, +Z).

    Returns
    -------
    LipContours

    Raises
    ------
    RegionError
        When the loop is not one closed edge loop or the corners are not on it.
    """
    V = np.asarray(rest_vertices, dtype=np.float64)
    F = np.asarray(faces, dtype=np.int64)
    lp = inner_lip_loop(V, F) if loop is None else order_edge_loop(F, loop, len(V))
    up_, fw = _unit(up), _unit(forward)
    lateral = _unit(np.cross(up_, fw))
    if corners is None:
        lat = V[lp] @ lateral
        ci = [int(np.argmin(lat)), int(np.argmax(lat))]
    else:
        c = np.asarray(corners, dtype=np.int64).ravel()
        if c.size != 2 or not np.isin(c, lp).all() or c[0] == c[1]:
            raise RegionError("The two mouth corners must be two different vertices of the inner-lip loop; reselect them.")
        ci = [int(np.flatnonzero(lp == c[0])[0]), int(np.flatnonzero(lp == c[1])[0])]
        if V[c[0]] @ lateral > V[c[1]] @ lateral:
            ci = ci[::-1]
    n = len(lp)
    i, j = ci
    a = lp[np.arange(i, i + ((j - i) % n) + 1) % n]  # left -> right one way round
    b = lp[np.arange(i, i - ((i - j) % n) - 1, -1) % n]  # left -> right the other way
    if len(a) < 3 or len(b) < 3:
        raise RegionError("The mouth corners split the inner-lip loop into a lip with no interior vertex; check the corners.")
    ha = V[a[1:-1]] @ up_
    hb = V[b[1:-1]] @ up_
    upper, lower = (a, b) if ha.mean() >= hb.mean() else (b, a)
    return LipContours(upper, lower)


def _arc(X, chain):
    seg = np.linalg.norm(np.diff(X[chain], axis=0), axis=1)
    return np.r_[0.0, np.cumsum(seg)]


def contour_points(vertices, chain, fractions):
    """Surface points at fractions of arc length along a contour.

    Parameters
    ----------
    vertices : (V,3) array_like
        Positions, scene units.
    chain : (n,) int array_like
        Contour vertex ids in order.
    fractions : (m,) float array_like
        Positions as fractions 0..1 of the contour's arc length.

    Returns
    -------
    edge : (m,2) int64 ndarray
        End vertices of the contour edge holding each point.
    bary : (m,2) float64 ndarray
        Weights of the two end vertices.
    points : (m,3) float64 ndarray
        The points, scene units.
    """
    X = np.asarray(vertices, dtype=np.float64)
    c = np.asarray(chain, dtype=np.int64)
    s = _arc(X, c)
    total = s[-1]
    f = np.clip(np.asarray(fractions, dtype=np.float64).ravel(), 0.0, 1.0) * total
    k = np.clip(np.searchsorted(s, f, side="right") - 1, 0, len(c) - 2)
    seg = s[k + 1] - s[k]
    t = np.divide(f - s[k], seg, out=np.zeros_like(f), where=seg > 0)
    t = np.clip(t, 0.0, 1.0)
    edge = np.stack([c[k], c[k + 1]], axis=1)
    bary = np.stack([1.0 - t, t], axis=1)
    pts = bary[:, :1] * X[edge[:, 0]] + bary[:, 1:] * X[edge[:, 1]]
    return edge, bary, pts


@dataclass
class EndPoints:
    """Ends of the talking portion of the creature's inner-lip contours.

    Attributes
    ----------
    upper, lower : (2,) float64 ndarray
        Left and right end point as fractions 0..1 of each contour's arc
        length, from the left corner. ``(0, 1)`` is the whole contour (the
        original corners, no sealing).
    """

    upper: np.ndarray = field(default_factory=lambda: np.array([0.0, 1.0]))
    lower: np.ndarray = field(default_factory=lambda: np.array([0.0, 1.0]))

    def __post_init__(self):
        for name in ("upper", "lower"):
            v = np.asarray(getattr(self, name), dtype=np.float64).ravel()
            if v.shape != (2,) or not np.isfinite(v).all() or not (0.0 <= v[0] < v[1] <= 1.0):
                raise FaceLabError(
                    f"The {name} lip end points must be two fractions 0 <= left < right <= 1 of the contour "
                    f"length, got {v.tolist()}; move the end points so the talking portion is not empty."
                )
            setattr(self, name, v)

    @classmethod
    def symmetric(cls, left: float, right: float | None = None) -> "EndPoints":
        """Same fractions on both lips; ``right`` defaults to ``1 - left``."""
        r = 1.0 - left if right is None else right
        return cls(np.array([left, r]), np.array([left, r]))


def lip_sync_end_points(actor_vertices, actor_contours: LipContours, creature_vertices,
                        creature_contours: LipContours, *, threshold: float = 0.0) -> EndPoints:
    """Automatic end points: a talking portion as long as the actor's lips.

    For each lip, the talking length is ``min(L_creature, L_actor + threshold)``
    (arc lengths on the given frames), centred on the middle of the creature's
    contour. The creature's contour is only shortened when it is longer than
    the actor's by more than ``threshold``.

    Parameters
    ----------
    actor_vertices : (V,3) array_like
        Actor frame, scene units.
    actor_contours : LipContours
    creature_vertices : (W,3) array_like
        Creature frame (deformation-transferred), scene units.
    creature_contours : LipContours
    threshold : float
        How much longer than the actor's lips the talking portion may be,
        scene units (0: the same length).

    Returns
    -------
    EndPoints
    """
    A = np.asarray(actor_vertices, dtype=np.float64)
    C = np.asarray(creature_vertices, dtype=np.float64)
    if threshold < 0 or not np.isfinite(threshold):
        raise FaceLabError(f"The lip-sync distance threshold must be >= 0 scene units, got {threshold}.")
    out = []
    for lip in ("upper", "lower"):
        la = _arc(A, getattr(actor_contours, lip))[-1]
        lc = _arc(C, getattr(creature_contours, lip))[-1]
        if lc <= 0:
            raise FaceLabError(f"The creature's {lip} inner-lip contour has zero length on this frame; check the mesh.")
        talk = min(lc, la + float(threshold))
        e = 0.5 * (lc - talk) / lc
        out.append(np.array([e, 1.0 - e]))
    return EndPoints(*out)


def end_points_from_vertices(creature_vertices, creature_contours: LipContours, left_vertex: int,
                             right_vertex: int) -> EndPoints:
    """End points an artist picked as two contour vertices (Bhat §5.1: "adjust the end points").

    Each vertex gives the fraction of arc length of its position on the
    contour it lies on (from that side's corner); the other lip gets the same
    fraction of its own length.

    Parameters
    ----------
    creature_vertices : (W,3) array_like
        Creature frame, scene units.
    creature_contours : LipContours
    left_vertex, right_vertex : int
        Vertices of the upper or lower contour.

    Returns
    -------
    EndPoints
    """
    C = np.asarray(creature_vertices, dtype=np.float64)

    def frac(v):
        for chain in (creature_contours.upper, creature_contours.lower):
            hit = np.flatnonzero(chain == int(v))
            if len(hit):
                s = _arc(C, chain)
                return s[hit[0]] / s[-1]
        raise FaceLabError(
            f"Vertex {v} is not on the creature's inner-lip contours; pick the end points on the inner-lip loop."
        )

    fl, fr = frac(left_vertex), frac(right_vertex)
    if fl > fr:
        fl, fr = fr, fl
    return EndPoints(np.array([fl, fr]), np.array([fl, fr]))


def _resolve_end_points(end_points):
    if end_points is None or isinstance(end_points, EndPoints):
        return end_points
    v = np.asarray(end_points, dtype=np.float64).ravel()
    if v.size == 2:
        return EndPoints(v, v)
    if v.size == 4:
        return EndPoints(v[:2], v[2:])
    raise FaceLabError(
        "End points must be an EndPoints, (left, right) fractions for both lips, or (upper_l, upper_r, lower_l, "
        f"lower_r); got {v.size} numbers."
    )


def lip_distances(actor_vertices, actor_contours: LipContours, creature_vertices, creature_contours: LipContours,
                  end_points: EndPoints, samples: int = 64, *, reference=None) -> dict:
    """Upper-to-lower lip distances of actor and creature along the talking portion.

    Parameters
    ----------
    actor_vertices : (V,3) array_like
        Actor frame, scene units.
    actor_contours : LipContours
    creature_vertices : (W,3) array_like
        Creature frame, scene units.
    creature_contours : LipContours
    end_points : EndPoints
        Talking portion of the creature's contours.
    samples : int
        Points along the talking portion (uniform in arc length).
    reference : (W,3) array_like, optional
        Creature frame on which the points are placed by arc length (the
        deformation-transferred frame the lip-sync constraints were built on);
        they are evaluated on ``creature_vertices``. Default:
        ``creature_vertices``.

    Returns
    -------
    dict
        ``actor`` and ``creature`` (samples,) distances, ``abs_diff`` their
        absolute difference, ``sealed`` (k,) creature distances between the
        corresponding upper and lower points from each original corner to its
        end point (empty without sealing); all scene units.
    """
    A = np.asarray(actor_vertices, dtype=np.float64)
    C = np.asarray(creature_vertices, dtype=np.float64)
    R = C if reference is None else np.asarray(reference, dtype=np.float64)

    def at(chain, f):
        e, b, _ = contour_points(R, chain, f)
        return b[:, :1] * C[e[:, 0]] + b[:, 1:] * C[e[:, 1]]

    u = np.linspace(0.0, 1.0, int(samples))
    _, _, au = contour_points(A, actor_contours.upper, u)
    _, _, al = contour_points(A, actor_contours.lower, u)
    ep = end_points
    cu = at(creature_contours.upper, ep.upper[0] + u * (ep.upper[1] - ep.upper[0]))
    cl = at(creature_contours.lower, ep.lower[0] + u * (ep.lower[1] - ep.lower[0]))
    da = np.linalg.norm(au - al, axis=1)
    dc = np.linalg.norm(cu - cl, axis=1)
    sealed = []
    for side in (0, 1):
        fu = ep.upper[0] if side == 0 else 1.0 - ep.upper[1]
        fl = ep.lower[0] if side == 0 else 1.0 - ep.lower[1]
        if max(fu, fl) <= 0:
            continue
        v = np.linspace(0.0, 1.0, max(2, int(samples * max(fu, fl) / max(ep.upper[1] - ep.upper[0], 1e-9))))[1:]
        pu = v * fu if side == 0 else 1.0 - v * fu
        pl = v * fl if side == 0 else 1.0 - v * fl
        su = at(creature_contours.upper, pu)
        sl = at(creature_contours.lower, pl)
        sealed.append(np.linalg.norm(su - sl, axis=1))
    sealed = np.concatenate(sealed) if sealed else np.zeros(0)
    return {"actor": da, "creature": dc, "abs_diff": np.abs(dc - da), "sealed": sealed}


# --------------------------------------------------------------------------
# Lip-sync solve
# --------------------------------------------------------------------------


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
    radius : float, optional
        Vertices within this geodesic distance (along edges, scene units) of
        the creature's contours may move; the rest is held. Default: 0.8 x
        the creature's corner-to-corner mouth width.
    strength : float
        Weight of the talking-portion constraints against the
        cotangent-Laplacian term (weight ``lambda_reg``); unitless (both terms
        are squared lengths). Soft by default (10): the pairs over-determine
        the lips, and the former 1000 on the raw targets tore the creature's
        lip corners (operator demo frame 3: 1.49 -> 0.76 mm largest umbrella
        roughness, mean lip-distance error 1.08 -> 0.70 mm; the benchmark
        fits its clean case 0.04 -> 0.13 mm less closely).
    seal_strength : float
        Weight of the sealing (zero-distance) constraints between each
        original corner and its new end point; unitless.
    lambda_reg : float
        Weight of the Laplacian term.
    smooth : float
        Width (standard deviation, fraction of the creature's upper-lip arc
        length) of the Gaussian that low-passes the change the talking-portion
        pairs ask for along the mouth (see ``_smooth_targets``); 0 turns it
        off. Sealed pairs are never smoothed (they close exactly).
    backend : str
        ``SPDFactor`` backend.
    """

    def __init__(self, creature_rest, creature_faces, creature_contours: LipContours, actor_contours: LipContours, *,
                 radius=None, strength: float = 10.0, lambda_reg: float = 1.0, smooth: float = 0.02,
                 seal_strength: float = 100.0, backend: str = "auto"):
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
        self.radius = 0.8 * width if radius is None else float(radius)
        dist = geodesic_distance(V, F, cv, limit=self.radius, exact=False)
        self.free = np.isfinite(dist)
        self.strength = float(strength)
        self.smooth = float(smooth)
        self.seal_strength = float(seal_strength)
        L = cotangent_laplacian(V, F)
        self.deformer = LaplacianDeformer(L, lambda_reg=lambda_reg, pos_weights=1e-6, pinned=~self.free,
                                          backend=backend)

    def end_points(self, actor_frame, creature_frame, *, end_points=None, threshold: float = 0.0) -> EndPoints:
        """The artist's end points if given, else :func:`lip_sync_end_points`."""
        ep = _resolve_end_points(end_points)
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
        fu_all = _arc(C, cc.upper)
        fu_all = fu_all / fu_all[-1]  # arc fraction of every upper-contour vertex
        fl_all = _arc(C, cc.lower)
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
        s = _arc(C, cc.upper)
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


# --------------------------------------------------------------------------
# Whole performance
# --------------------------------------------------------------------------


@dataclass
class RetargetResult:
    """A performance carried to the creature.

    Attributes
    ----------
    deltas : (S,W,3) float64
        Creature blendshape deltas (the transferred actor shapes), scene units.
    weights : (T,S) float64
        Weights copied from the actor's solve.
    correctives : (T,W,3) float32
        Per-frame creature correctives on top of ``rest + weights @ deltas``:
        the transferred actor corrective plus the lip-sync offset, scene units.
    end_points : list of EndPoints or None
        Talking portion used on each frame (``None`` without lip sync).
    info : dict
        Timings (seconds) and counts.
    """

    deltas: np.ndarray
    weights: np.ndarray
    correctives: np.ndarray
    end_points: list
    info: dict


class Retargeter:
    """Parallel creature rig plus per-frame retargeting (Bhat §5.1).

    Parameters
    ----------
    actor_rest : (V,3) array_like
        Actor neutral, scene units.
    actor_faces : (F,3) int array_like
    actor_deltas : (S,V,3) array_like
        Actor blendshape deltas, scene units.
    creature_rest : (W,3) array_like
        Creature neutral, scene units.
    creature_faces : (F_t,3) int array_like
    correspondence : (F_t,) int array_like, optional
        Source triangle per creature triangle; default: shared topology.
    lip_sync : bool
        Build the lip-sync deformer.
    actor_loop, creature_loop : (L,) int array_like, optional
        Inner-lip edge loops; default: detected (``regions.inner_lip_loop``)
        on the actor, and the same vertex ids on a creature of the same
        topology (detected on the creature otherwise).
    actor_contours, creature_contours : LipContours, optional
        Give the split contours directly instead of loops.
    threshold : float
        Default lip-sync distance threshold, scene units.
    up, forward : (3,) float
        Face axes for the corner and upper/lower detection.
    radius, strength, smooth, seal_strength : float
        Passed to :class:`LipSync`.
    """

    def __init__(self, actor_rest, actor_faces, actor_deltas, creature_rest, creature_faces, *, correspondence=None,
                 lip_sync: bool = True, actor_loop=None, creature_loop=None, actor_contours=None,
                 creature_contours=None, threshold: float = 0.0, up=ICT_UP, forward=ICT_FORWARD, radius=None,
                 strength: float = 10.0, smooth: float = 0.02, seal_strength: float = 100.0):
        import time

        t0 = time.perf_counter()
        self.transfer = DeformationTransfer(actor_rest, actor_faces, creature_rest, creature_faces, correspondence)
        t1 = time.perf_counter()
        D = np.asarray(actor_deltas, dtype=np.float64)
        if D.ndim == 2:
            D = D[None]
        if D.ndim != 3 or D.shape[1:] != self.transfer.source_rest.shape:
            raise FaceLabError(
                f"The actor's shape deltas have shape {np.shape(actor_deltas)}, expected (S, {len(actor_rest)}, 3); "
                "the rig must have shape keys on the actor mesh."
            )
        if len(D) == 0:
            raise FaceLabError("The actor rig has no shape keys; add blendshapes (shape keys) to the actor first.")
        self.actor_deltas = D
        self.creature_deltas = self.transfer.transfer_deltas(D)
        t2 = time.perf_counter()
        self.threshold = float(threshold)
        self.lip_sync = None
        if lip_sync:
            Va, Fa = self.transfer.source_rest, self.transfer.source_faces
            Vc, Fc = self.transfer.target_rest, self.transfer.target_faces
            ac = actor_contours or lip_contours(Va, Fa, actor_loop, up=up, forward=forward)
            if creature_contours is not None:
                cc = creature_contours
            elif creature_loop is None and self.transfer.same_topology:
                cc = lip_contours(Vc, Fc, np.r_[ac.upper, ac.lower[1:-1][::-1]], corners=ac.corners, up=up,
                                  forward=forward)
            else:
                cc = lip_contours(Vc, Fc, creature_loop, up=up, forward=forward)
            self.lip_sync = LipSync(Vc, Fc, cc, ac, radius=radius, strength=strength, smooth=smooth,
                                    seal_strength=seal_strength)
        t3 = time.perf_counter()
        self.info = {"factor_s": t1 - t0, "transfer_shapes_s": t2 - t1, "lip_sync_setup_s": t3 - t2}

    @property
    def creature_rest(self):
        return self.transfer.target_rest

    def frame(self, weights, corrective=None, *, end_points=None, lip_sync: bool | None = None,
              threshold: float | None = None):
        """Retarget one frame.

        Parameters
        ----------
        weights : (S,) array_like
            Actor weights of this frame (copied to the creature).
        corrective : (V,3) array_like, optional
            Actor's out-of-subspace corrective of this frame, scene units.
        end_points : EndPoints or fractions, optional
            Artist override of the talking portion on this frame.
        lip_sync : bool, optional
            Apply the lip-sync heuristic (default: when it was built).
        threshold : float, optional
            Distance threshold (default: the one given at construction).

        Returns
        -------
        corrective : (W,3) float64 ndarray
            Creature corrective on top of ``creature_rest + weights @ creature_deltas``,
            scene units.
        info : dict
            ``end_points`` (or None) and ``constraints``.
        """
        w = np.asarray(weights, dtype=np.float64).ravel()
        if w.shape != (len(self.actor_deltas),) or not np.isfinite(w).all():
            raise FaceLabError(
                f"Expected {len(self.actor_deltas)} finite weights for this frame, got {w.shape}; solve the frame first."
            )
        blend_a = np.tensordot(w, self.actor_deltas, axes=1)
        blend_c = np.tensordot(w, self.creature_deltas, axes=1)
        if corrective is not None:
            dv = np.asarray(corrective, dtype=np.float64)
            corr_c = self.transfer.transfer_correctives(dv, base=blend_a)
        else:
            dv = 0.0
            corr_c = np.zeros_like(blend_c)
        info = {"end_points": None, "constraints": 0}
        use = self.lip_sync is not None if lip_sync is None else bool(lip_sync)
        if use:
            if self.lip_sync is None:
                raise FaceLabError("Lip sync was not set up for this creature; build the Retargeter with lip_sync=True.")
            actor = self.transfer.source_rest + blend_a + dv
            creature = self.creature_rest + blend_c + corr_c
            th = self.threshold if threshold is None else float(threshold)
            X, info = self.lip_sync.solve(actor, creature, end_points=end_points, threshold=th)
            corr_c = X - self.creature_rest - blend_c
        return corr_c, info


def retarget_performance(actor_rest, actor_faces, actor_deltas, weights, creature_rest, creature_faces, *,
                         correctives=None, correspondence=None, lip_sync: bool = True, threshold: float = 0.0,
                         end_points: dict | None = None, actor_loop=None, creature_loop=None, progress=None,
                         **kwargs) -> RetargetResult:
    """Retarget a solved performance to a creature (Bhat §5.1).

    Parameters
    ----------
    actor_rest : (V,3) array_like
        Actor neutral, scene units.
    actor_faces : (F,3) int array_like
    actor_deltas : (S,V,3) array_like
        Actor blendshape deltas.
    weights : (T,S) array_like
        Solved weights per frame.
    creature_rest : (W,3) array_like
    creature_faces : (F_t,3) int array_like
    correctives : (T,V,3) array_like, optional
        Actor correctives per frame, scene units.
    correspondence : (F_t,) int array_like, optional
        Default: shared topology.
    lip_sync : bool
        Apply the lip-sync heuristic.
    threshold : float
        Lip-sync distance threshold, scene units.
    end_points : dict frame index -> EndPoints or fractions, optional
        Artist overrides on some frames.
    actor_loop, creature_loop : (L,) int array_like, optional
        Inner-lip edge loops (default detected).
    progress : callable(done, total), optional
    **kwargs
        Passed to :class:`Retargeter` (``radius``, ``strength``, ``up``,
        ``forward``, ``actor_contours``, ``creature_contours``).

    Returns
    -------
    RetargetResult
    """
    import time

    W = np.asarray(weights, dtype=np.float64)
    if W.ndim != 2:
        raise FaceLabError(f"Weights must be (frames, shapes), got shape {W.shape}.")
    rt = Retargeter(actor_rest, actor_faces, actor_deltas, creature_rest, creature_faces,
                    correspondence=correspondence, lip_sync=lip_sync, actor_loop=actor_loop,
                    creature_loop=creature_loop, threshold=threshold, **kwargs)
    T = len(W)
    C = None if correctives is None else np.asarray(correctives)
    if C is not None and C.shape != (T,) + rt.transfer.source_rest.shape:
        raise FaceLabError(
            f"Correctives have shape {C.shape}, expected ({T}, {len(rt.transfer.source_rest)}, 3): one per frame."
        )
    out = np.zeros((T,) + rt.creature_rest.shape, dtype=np.float32)
    eps = []
    overrides = end_points or {}
    t0 = time.perf_counter()
    for t in range(T):
        corr, info = rt.frame(W[t], None if C is None else C[t], end_points=overrides.get(t))
        out[t] = corr
        eps.append(info["end_points"])
        if progress is not None:
            progress(t + 1, T)
    info = dict(rt.info)
    info["frames_s"] = time.perf_counter() - t0
    return RetargetResult(deltas=rt.creature_deltas, weights=W.copy(), correctives=out, end_points=eps, info=info)


# --------------------------------------------------------------------------
# Test / benchmark creature
# --------------------------------------------------------------------------


def widen_mouth(vertices, center, *, factor: float = 1.6, sigma=(0.022, 0.015, 0.02), lateral=(1.0, 0.0, 0.0)):
    """A creature made from a face by a smooth warp that widens the mouth.

    ``x' = x + (factor - 1) * g(x) * ((x - c) . l) l`` with the Gaussian falloff
    ``g = exp(-1/2 sum_k ((x - c)_k / sigma_k)^2)`` around the mouth centre
    ``c``: points near the mouth move apart along ``l`` (the mouth's width
    axis), far points do not move. The warp is one-to-one for
    ``factor < 1 + e^1.5 / 2`` (about 3.2).

    Parameters
    ----------
    vertices : (V,3) array_like
        Face positions, scene units.
    center : (3,) array_like
        Mouth centre, scene units.
    factor : float
        Stretch at the centre (1.6: the mouth corners move out by roughly a
        third of the mouth width on ICT in metres with the default sigma).
    sigma : (3,) float
        Falloff radii along x, y, z, scene units (defaults for ICT in metres).
    lateral : (3,) float
        Width axis of the mouth (ICT: +X).

    Returns
    -------
    (V,3) float64 ndarray
    """
    X = np.asarray(vertices, dtype=np.float64)
    c = np.asarray(center, dtype=np.float64).reshape(3)
    l = _unit(lateral)
    d = X - c
    g = np.exp(-0.5 * ((d / np.asarray(sigma, dtype=np.float64)) ** 2).sum(axis=1))
    return X + (float(factor) - 1.0) * (g * (d @ l))[:, None] * l[None, :]
