"""Inner-lip contours of a face or creature mesh, and the talking portion on them.

Bhat et al. 2013, "High fidelity facial animation capture and retargeting
with contours", §5.1 (lip-sync heuristic, Fig. 8):

* :func:`lip_contours` splits the closed inner-lip edge loop
  (``core.lips.lip_loop.inner_lip_loop`` or an artist's edge-loop selection)
  at the two mouth corners into an upper and a lower contour
  (:class:`LipContours`), both ordered from the left corner to the right one
  (left = smaller coordinate along ``up x forward``; face axes default to
  :mod:`facelab_addon.core.geometry.axes`).
* :func:`contour_points` places surface points (mesh edge and barycentric
  weights) at fractions of a contour's arc length.
* The *talking portion* of the creature's contours (:class:`EndPoints`):
  automatically as long as the actor's lips (:func:`lip_sync_end_points`:
  ``min(creature length, actor length + threshold)``, centred on the middle
  of each contour by arc length, measured on the current frames), or picked
  by an artist (:func:`end_points_from_vertices`).
* :func:`lip_distances` measures the upper-to-lower lip distances of actor
  and creature along it (the quantity the lip-sync heuristic matches).

Units: positions in scene units; end points are fractions of arc length.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import FaceLabError, RegionError
from ..geometry.axes import Y_UP, Z_FORWARD, unit_axis
from ..geometry.polyline import arc_length
from ..lips.lip_loop import inner_lip_loop, order_edge_loop

__all__ = [
    "LipContours",
    "EndPoints",
    "lip_contours",
    "contour_points",
    "lip_sync_end_points",
    "end_points_from_vertices",
    "lip_distances",
]


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


def lip_contours(rest_vertices, faces, loop=None, *, corners=None, up=Y_UP, forward=Z_FORWARD) -> LipContours:
    """Split the inner-lip loop at the mouth corners into upper and lower contours.

    Parameters
    ----------
    rest_vertices : (V,3) array_like
        Rest positions (lips closed or nearly closed), scene units.
    faces : (F,3) int array_like
        Triangles.
    loop : (L,) int array_like, optional
        The closed inner-lip edge loop (any order, for example a Blender
        edge-loop selection). Default: found by ``lip_loop.inner_lip_loop``.
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
    up_, fw = unit_axis(up, "up"), unit_axis(forward, "forward")
    lateral = unit_axis(np.cross(up_, fw), "lateral (up x forward)")
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
    s = arc_length(X[c])
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
        la = arc_length(A[getattr(actor_contours, lip)])[-1]
        lc = arc_length(C[getattr(creature_contours, lip)])[-1]
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
                s = arc_length(C[chain])
                return s[hit[0]] / s[-1]
        raise FaceLabError(
            f"Vertex {v} is not on the creature's inner-lip contours; pick the end points on the inner-lip loop."
        )

    fl, fr = frac(left_vertex), frac(right_vertex)
    if fl > fr:
        fl, fr = fr, fl
    return EndPoints(np.array([fl, fr]), np.array([fl, fr]))


def resolve_end_points(end_points):
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
