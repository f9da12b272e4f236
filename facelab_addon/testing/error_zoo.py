"""An error zoo for Refine Lips: capture failures as Dinev et al. 2018 list them, on several faces and cameras.

Refine Lips (:mod:`facelab_addon.core.lips.sketch`) is judged on a frame with a known truth: a face model posed
with its own expression shapes (the truth), the truth plus a smooth capture error confined to the lips (the
capture), and the truth's inner-lip silhouettes sketched through a camera as a hand draws them (the sketch).
Everything here is NumPy/SciPy on the face model's arrays (no ``bpy``); nothing is found with the code under test:
the lips' contact line, the side of each vertex and the mouth corners come from
:mod:`facelab_addon.testing.lip_truth` (the jaw-opening expression), the lip band Refine may move is Auto Regions'
``FL_lips`` (as the artist's route has it).

Error families (:data:`FAMILIES`), split into :data:`TUNING` (Refine's defaults are chosen on these) and
:data:`HELD_OUT` (reported), each varied by its reach across the lip (2-10 mm), size, a depth component (along the
face's forward axis), left-right asymmetry, the truth's expression and a head nod (:class:`ZooCase`,
:func:`sample_cases`):

* ``gap`` (tuning): the lips held apart where they should seal (the truth's lips touch: pose ``sealed``);
* ``cross`` (held out): the lips passing through each other;
* ``corners`` (tuning): the mouth corners losing their fleshiness (pulled in along the mouth and sunk back);
* ``roll`` (tuning): the lips' red part rolled into the mouth (back and toward its own side);
* ``bulge`` (held out): a missed bulge: the lip band flattened along its own normals, most in the middle of the
  band, not at the contact;
* ``sticky`` (held out): sticky lips parting too early: a gap where the truth's lips still touch, largest between
  the middle and the corners.

Sketches (:func:`hand_sketch`): the truth's silhouettes (:func:`truth_sketch`, each lip's envelope: the edge of
the mouth opening), drawn on one line where they lie within :data:`ONE_LINE_PX` of each other (the README's
convention for sealed lips), then with a hand's noise: a smooth 1-2 px jitter
(:func:`facelab_addon.testing.route.jitter_stroke`), ends that stop short or overshoot, strokes in several pieces.

Measures: :func:`lip_band` (the skin within 6 mm of the contact line, as ``testing.route``), :func:`rms_mm`,
:func:`best_possible_cut_pct` (the most any correction confined to ``FL_lips`` with its border held can cut: the
error on the band outside its inside stays), :func:`contact_gap` (the lips' 3D distance along the contact).

Faces: any ICT-like face model (:func:`zoo_face`); :func:`makehuman_zoo_face` is MakeHuman's head, which is not
ICT's topology (its expressions transferred from ICT's).

Units: positions in the face model's units; ``ZooFace.unit_mm`` converts millimetres. Pixels: top-left origin,
y down.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from ..core.capture.camera import Camera
from ..core.geometry.mesh import vertex_normals
from ..core.geometry.silhouette import lip_side, silhouette_edges
from .lip_truth import lip_labels, truth_line
from .route import jitter_stroke

__all__ = ["FAMILIES", "TUNING", "HELD_OUT", "POSES", "ONE_LINE_PX", "ZooFace", "ZooCase", "zoo_face",
           "sample_cases", "make_case", "truth_sketch", "hand_sketch", "lip_band", "rms_mm", "best_possible_cut_pct",
           "contact_gap", "free_inside", "makehuman_zoo_face"]

FAMILIES = {
    "gap": "the lips held apart where they should seal (upper lip up, lower lip down), the truth's lips touching",
    "cross": "the lips passing through each other (upper lip down, lower lip up)",
    "corners": "the mouth corners losing their fleshiness: pulled in along the mouth and sunk back",
    "roll": "the lips' red part rolled into the mouth: back along the face's forward axis and 30 degrees toward "
            "its own side",
    "bulge": "a missed bulge: the lip band pushed in along its own normals, most in the middle of the band",
    "sticky": "sticky lips parting too early: a gap where the truth's lips touch, largest between the middle and "
              "the corners",
}
#: Families Refine's defaults are chosen on.
TUNING = ("gap", "corners", "roll")
#: Families only reported.
HELD_OUT = ("cross", "bulge", "sticky")
#: The truth's expression, ``name: {expression: weight}`` (the face model's own expression shapes).
POSES = {
    "sealed": {"mouthPress_L": 0.3, "mouthPress_R": 0.3},
    "neutral": {},
    "open": {"jawOpen": 0.12, "mouthLowerDown_L": 0.2, "mouthLowerDown_R": 0.2},
    "smile": {"mouthSmile_L": 0.4, "mouthSmile_R": 0.4, "mouthPress_L": 0.2, "mouthPress_R": 0.2},
    "pucker": {"mouthPucker": 0.4, "mouthPress_L": 0.15, "mouthPress_R": 0.15},
    "funnel": {"mouthFunnel": 0.3, "jawOpen": 0.08},
}
#: Poses whose lips touch (the gap and sticky families use these).
SEALED_POSES = ("sealed", "smile", "pucker")
#: The artist draws both contours on one line where the truth's silhouettes are this close (pixels).
ONE_LINE_PX = 1.5
#: The lip band measured: skin within this many millimetres of the contact line (as ``testing.route``).
BAND_MM = 6.0


@dataclass
class ZooFace:
    """A face model prepared for the zoo (positions in its units, Y up and Z forward as ICT-FaceKit).

    Attributes
    ----------
    name : str
    neutral : (V,3) float
        Rest positions (with the actor's identity).
    faces : (F,3) int
    expressions : dict of (V,3)
        Expression targets (absolute positions).
    skin : (V,) bool
        The skin that may carry the error (``M_Face``).
    fixed : (V,) bool
        Hidden vertices (everything but the skin; the route's ``FL_fixed``).
    lips : (V,) bool
        Auto Regions' ``FL_lips`` on the rest pose.
    unit_mm : float
        Model units per millimetre.
    side : (V,) float
        +1 upper lip, -1 lower lip, 0 corners / cut off (:func:`~facelab_addon.testing.lip_truth.lip_labels`).
    upper, lower, corners : int arrays
        The truth's contact line (:class:`~facelab_addon.testing.lip_truth.TruthLine`).
    """

    name: str
    neutral: np.ndarray
    faces: np.ndarray
    expressions: dict
    skin: np.ndarray
    fixed: np.ndarray
    lips: np.ndarray
    unit_mm: float
    side: np.ndarray
    upper: np.ndarray
    lower: np.ndarray
    corners: np.ndarray
    up: np.ndarray = field(default_factory=lambda: np.array([0.0, 1.0, 0.0]))
    forward: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))

    @property
    def loop(self) -> np.ndarray:
        return np.r_[self.upper, self.lower[-2:0:-1]].astype(np.int64)

    def pose(self, weights: dict) -> np.ndarray:
        """(V,3) the neutral plus the weighted expression offsets."""
        X = self.neutral.copy()
        for n, w in weights.items():
            if n in self.expressions:
                X += w * (self.expressions[n] - self.neutral)
        return X


def zoo_face(face, name: str, identity_offset=None, unit_mm: float | None = None) -> ZooFace:
    """A :class:`ZooFace` of an ICT-like face model (``neutral``, ``faces``, ``expressions``, ``part_vertex_mask``).

    Parameters
    ----------
    face : ICTModel or RemeshedFace
    name : str
    identity_offset : (V,3) float, optional
        Added to the neutral and every expression (another actor: ICT's linear identity model).
    unit_mm : float, optional
        Model units per millimetre (default ``0.1 * face.scale``: centimetres).
    """
    from ..core.lips.regions import auto_regions

    off = 0.0 if identity_offset is None else np.asarray(identity_offset, dtype=np.float64)
    V = np.asarray(face.neutral, dtype=np.float64) + off
    F = np.asarray(face.faces, dtype=np.int64)
    line = truth_line(face)  # the same vertices for any actor (ICT's identity model keeps the topology)
    skin = np.asarray(face.part_vertex_mask("M_Face"), bool)
    _, lips = auto_regions(V, F)
    return ZooFace(name=name, neutral=V, faces=F,
                   expressions={n: np.asarray(face.expressions[n], dtype=np.float64) + off for n in face.expression_names},
                   skin=skin, fixed=~skin, lips=lips,
                   unit_mm=float(unit_mm) if unit_mm else 0.1 * float(getattr(face, "scale", 1.0)),
                   side=lip_labels(V, F, line), upper=line.upper, lower=line.lower, corners=line.corners)


def _pose_names():
    return sorted({n for p in POSES.values() for n in p} | {"jawOpen"})


def makehuman_zoo_face(ict=None) -> ZooFace:
    """MakeHuman's CC0 head (:func:`facelab_addon.testing.makehuman.makehuman_head`) as a zoo face.

    Its expressions are ICT-FaceKit's, carried over by deformation transfer: those of
    :data:`~facelab_addon.testing.makehuman.EXPRESSIONS` and every one :data:`POSES` uses, so the zoo's poses are
    made of the same shapes as on ICT. Centimetres (``unit_mm`` 0.1); the whole head is skin (nothing hidden).

    Raises
    ------
    FileNotFoundError
        Without the mesh (``FACELAB_MAKEHUMAN_OBJ``; the message says how to get it).
    """
    from .makehuman import EXPRESSIONS, makehuman_head

    names = tuple(EXPRESSIONS) + tuple(n for n in _pose_names() if n not in EXPRESSIONS)
    return zoo_face(makehuman_head(ict=ict, expressions=names), "MakeHuman (CC0, ICT shapes by DT)")


@dataclass
class ZooCase:
    """One zoo case: a capture error on a posed face, seen by one or two cameras, sketched by hand.

    Sizes in millimetres and degrees. ``second_elev`` is the second camera's elevation above the mouth (negative:
    below; 20-35 degrees either way), at the main camera's azimuth.
    """

    family: str
    pose: str
    reach_mm: float
    amount_mm: float
    depth: float
    asym: float
    head_pitch: float
    azim: float
    elev: float
    lens_mm: float
    distance_cm: float
    second_elev: float
    noise_px: float
    end_px: tuple
    pieces: int
    seed: int

    @property
    def split(self) -> str:
        return "tuning" if self.family in TUNING else "held_out"


def sample_cases(families, per_family: int, seed: int = 0) -> list:
    """``per_family`` random :class:`ZooCase` of each family (deterministic in ``seed``)."""
    rng = np.random.default_rng(seed)
    out = []
    for fam in families:
        for k in range(per_family):
            sealed = fam in ("gap", "sticky")
            pose = SEALED_POSES[k % len(SEALED_POSES)] if sealed else list(POSES)[(k + len(fam)) % len(POSES)]
            out.append(ZooCase(
                family=fam, pose=pose,
                reach_mm=float(rng.uniform(2.0, 10.0)),
                amount_mm=float(rng.uniform(0.8, 2.0)),
                depth=float(rng.uniform(-0.6, 0.6)),
                asym=float(rng.uniform(-0.5, 0.5)),
                head_pitch=float(rng.choice([0.0, -8.0, 8.0])),
                azim=float(rng.uniform(-15.0, 15.0)),
                elev=float(rng.uniform(-15.0, 15.0)),
                lens_mm=float(rng.choice([35.0, 50.0, 85.0])),
                distance_cm=float(rng.uniform(30.0, 50.0)),
                second_elev=float(rng.choice([-1.0, 1.0]) * rng.uniform(20.0, 35.0)),
                noise_px=float(rng.uniform(1.0, 2.0)),
                end_px=tuple(float(x) for x in rng.uniform(-12.0, 8.0, size=4)),
                pieces=int(rng.integers(1, 4)),
                seed=int(rng.integers(1 << 30)),
            ))
    return out


def _bump(d, r):
    """(1 - (d / r)^2)^2 inside ``r``, 0 outside (C1)."""
    return np.clip(1.0 - (np.asarray(d) / r) ** 2, 0.0, 1.0) ** 2


def error_field(zf: ZooFace, T, case: ZooCase) -> np.ndarray:
    """(V,3) the capture error of ``case`` on the truth ``T`` (V,3), model units (before any head nod)."""
    mm = zf.unit_mm
    up, fwd = zf.up, zf.forward
    lat_axis = np.cross(up, fwd)
    loop = zf.loop
    d, _ = cKDTree(T[loop]).query(T)
    cl, cr = T[zf.corners[0]], T[zf.corners[1]]
    mid = 0.5 * (cl + cr)
    half = max(0.5 * abs((cr - cl) @ lat_axis), 1e-12)
    t = ((T - mid) @ lat_axis) / half  # -1..1 between the corners
    along = np.clip(1.0 - np.abs(t) ** 4, 0.0, 1.0)
    asym = np.clip(1.0 + case.asym * t, 0.0, None)  # one side larger
    skin = zf.skin.astype(np.float64)
    side = zf.side
    R = case.reach_mm * mm
    a = case.amount_mm * mm
    w = _bump(d, R) * skin * asym
    fam = case.family
    if fam in ("gap", "cross", "sticky"):
        s = 1.0 if fam != "cross" else -1.0
        prof = along if fam != "sticky" else np.exp(-((np.abs(t) - 0.55) / 0.25) ** 2) * along
        wv = w * prof * np.abs(side)
        dirs = s * side[:, None] * up[None] + case.depth * fwd[None]
        return (a * wv)[:, None] * dirs
    if fam == "corners":
        c = np.minimum(np.linalg.norm(T - cl, axis=1), np.linalg.norm(T - cr, axis=1))
        wc = _bump(c, R) * skin * np.where(t < 0, 1.0 - case.asym, 1.0 + case.asym)
        inward = -np.sign(t)
        return (a * wc)[:, None] * (inward[:, None] * lat_axis[None] - (0.5 + case.depth) * fwd[None])
    if fam == "roll":
        ang = np.radians(30.0)
        wv = w * along * np.abs(side)
        # the depth share scales the part along the forward axis
        dirs = -(1.0 + case.depth) * np.cos(ang) * fwd[None] + np.sin(ang) * side[:, None] * up[None]
        return (a * wv)[:, None] * dirs
    if fam == "bulge":
        # most in the middle of the band (a ring around the contact), pushed in along the lip's normals
        wb = (np.clip(d / (0.5 * R), 0.0, 1.0) ** 2) * w * along * np.abs(side)
        n = vertex_normals(T, zf.faces)
        n = n + case.depth * fwd[None]
        return -(a * wb)[:, None] * n
    raise ValueError(f"family must be one of {list(FAMILIES)}, not {fam!r}")


def _rot_x(deg):
    a = np.radians(deg)
    return np.array([[1.0, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])


def zoo_camera(zf: ZooFace, center, azim, elev, lens_mm, distance_cm) -> Camera:
    """A 1920x1080 camera (36 mm sensor) ``distance_cm`` from ``center``, ``azim`` / ``elev`` degrees off the front."""
    up, fwd = zf.up, zf.forward
    lat = np.cross(up, fwd)
    a, e = np.radians(azim), np.radians(elev)
    d = np.cos(e) * (np.cos(a) * fwd + np.sin(a) * lat) + np.sin(e) * up
    eye = np.asarray(center) + distance_cm * 10.0 * zf.unit_mm * d
    return Camera.look_at(eye, center, up, lens_mm, 36.0, 1920, 1080)


@dataclass
class MadeCase:
    """A built case: truth, capture, rest, cameras (main first) and the drawn strokes per camera."""

    case: ZooCase
    truth: np.ndarray
    capture: np.ndarray
    rest: np.ndarray
    cameras: list
    strokes: list  # per camera: (upper pieces, lower pieces)
    one_line_px: list  # per camera: how many pixels of the sketch are drawn on one line
    head: np.ndarray = None  # (3,3) the head's nod (rotation about the mouth)

    def basis(self, zf: ZooFace, exclude=()) -> np.ndarray:
        """(K,V,3) the face's expression offsets as the nodded head carries them (``exclude``: names left out)."""
        names = [n for n in zf.expressions if n not in exclude]
        return np.stack([(zf.expressions[n] - zf.neutral) @ self.head.T for n in names])


def make_case(zf: ZooFace, case: ZooCase) -> MadeCase:
    """Pose the truth, add the error, nod the head, place the cameras and draw the sketches (see the module)."""
    T0 = zf.pose(POSES[case.pose])
    C0 = T0 + error_field(zf, T0, case)
    c = T0[zf.loop].mean(axis=0)
    R = _rot_x(case.head_pitch)
    T = (T0 - c) @ R.T + c
    C = (C0 - c) @ R.T + c
    cams = [zoo_camera(zf, c, case.azim, case.elev, case.lens_mm, case.distance_cm),
            zoo_camera(zf, c, case.azim, case.second_elev, case.lens_mm, case.distance_cm)]
    rng = np.random.default_rng(case.seed)
    strokes, one = [], []
    for cam in cams:
        up, lo, n1 = truth_sketch(zf, T, cam)
        strokes.append(hand_sketch(up, lo, case, rng))
        one.append(n1)
    return MadeCase(case=case, truth=T, capture=C, rest=zf.neutral, cameras=cams, strokes=strokes, one_line_px=one,
                    head=R)


def _envelope(xs, a, b, upper):
    x0, x1 = np.minimum(a[:, 0], b[:, 0]), np.maximum(a[:, 0], b[:, 0])
    dx = b[:, 0] - a[:, 0]
    t = (xs[None, :] - a[:, 0:1]) / np.where(np.abs(dx) < 1e-12, 1e-12, dx)[:, None]
    inside = (xs[None, :] >= x0[:, None]) & (xs[None, :] <= x1[:, None])
    y = a[:, 1:2] + np.clip(t, 0, 1) * (b[:, 1] - a[:, 1])[:, None]
    if upper:
        return np.where(inside, y, -np.inf).max(axis=0)
    return np.where(inside, y, np.inf).min(axis=0)


def truth_sketch(zf: ZooFace, T, cam, band_mm: float = 4.0):
    """The truth's inner-lip contours through ``cam``, as an artist draws them.

    Each lip's envelope of its silhouette edges within ``band_mm`` of the contact line (the lowest upper-lip and the
    highest lower-lip silhouette at each pixel column, 1 px apart); where the two lie within :data:`ONE_LINE_PX` of
    each other, both are drawn on their mid-line (the lips touch: one line); where the lower lip's lies farther above
    the upper lip's (lips overlapping in the image), they are drawn crossing, as they are (Refine's ``"follow"``).

    Returns
    -------
    upper, lower : (N,2), (M,2) float
        Pixels, left to right.
    one_line : int
        Columns drawn on one line.
    """
    d, _ = cKDTree(T[zf.loop]).query(T)
    near = (d <= band_mm * zf.unit_mm) & zf.skin
    E = silhouette_edges(T, zf.faces, cam)
    E = E[near[E].all(axis=1)]
    ls = lip_side(T, zf.faces, cam, E.ravel()).reshape(-1, 2)
    px = cam.project(T)
    env = []
    for s in (1, -1):
        Es = E[((ls == s) & (zf.side[E] == s)).all(axis=1)]
        if len(Es) == 0:
            raise ValueError(f"no {'upper' if s > 0 else 'lower'}-lip silhouette in this view")
        a, b = px[Es[:, 0]], px[Es[:, 1]]
        env.append((a, b))
    lo_x = max(min(a[:, 0].min(), b[:, 0].min()) for a, b in env)
    hi_x = min(max(a[:, 0].max(), b[:, 0].max()) for a, b in env)
    xs = np.arange(np.ceil(lo_x), np.floor(hi_x) + 1.0)
    yu = _envelope(xs, *env[0], upper=True)
    yl = _envelope(xs, *env[1], upper=False)
    ok = np.isfinite(yu) & np.isfinite(yl)
    xs, yu, yl = xs[ok], yu[ok], yl[ok]
    one = np.abs(yl - yu) <= ONE_LINE_PX
    m = 0.5 * (yu + yl)
    yu, yl = np.where(one, m, yu), np.where(one, m, yl)
    return np.c_[xs, yu], np.c_[xs, yl], int(one.sum())


def _trim_extend(P, start_px, end_px):
    """A polyline with ``start_px`` / ``end_px`` added at its ends (negative: stopped that far short)."""
    P = np.asarray(P, dtype=np.float64)
    for first, amount in ((True, start_px), (False, end_px)):
        if len(P) < 6:
            break
        if amount < 0:
            s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(P, axis=0), axis=1))]
            keep = s >= -amount if first else s <= s[-1] + amount
            if keep.sum() >= 6:
                P = P[keep]
        else:
            e, q = (P[0], P[3]) if first else (P[-1], P[-4])
            u = (e - q) / max(np.linalg.norm(e - q), 1e-12)
            ext = e + np.outer(np.arange(1.0, amount + 1.0), u)
            P = np.r_[ext[::-1], P] if first else np.r_[P, ext]
    return P


def hand_sketch(upper, lower, case: ZooCase, rng):
    """The strokes a hand draws over the truth's contours: jitter, ends short / over, pieces.

    On the stretch drawn on one line (equal upper and lower y) the lower stroke keeps the upper stroke's jitter
    (one line, drawn twice). Returns ``(upper_pieces, lower_pieces)``: lists of (k,2) pixel polylines.
    """
    same = np.isclose(upper[:, 1], lower[:, 1]) if len(upper) == len(lower) else np.zeros(len(lower), bool)
    ju = jitter_stroke(upper, case.noise_px, rng)
    jl = jitter_stroke(lower, case.noise_px, rng)
    if same.any():
        jl[same] = ju[same]
    out = []
    for P, (s, e) in ((ju, case.end_px[:2]), (jl, case.end_px[2:])):
        P = _trim_extend(P, s, e)
        pieces = []
        cuts = np.sort(rng.uniform(0.2, 0.8, size=case.pieces - 1)) if case.pieces > 1 else []
        idx = [0] + [int(c * len(P)) for c in cuts] + [len(P)]
        for i0, i1 in zip(idx[:-1], idx[1:]):
            gap = int(rng.integers(-2, 4))  # overlap a little, or leave a few pixels out
            a, b = max(i0 - max(-gap, 0), 0), i1
            if i1 < len(P):
                b = max(i1 - max(gap, 0), a + 3)
            if b - a >= 3:
                pieces.append(P[a:b])
        out.append(pieces)
    return out[0], out[1]


def lip_band(zf: ZooFace, T) -> np.ndarray:
    """(V,) bool: the measured lip band: skin within :data:`BAND_MM` of the truth's contact line."""
    d, _ = cKDTree(T[zf.loop]).query(T)
    return (d < BAND_MM * zf.unit_mm) & zf.skin


def rms_mm(X, T, mask, unit_mm) -> float:
    """RMS 3D distance (millimetres) of ``X`` to ``T`` over ``mask``."""
    e = np.linalg.norm(np.asarray(X)[mask] - np.asarray(T)[mask], axis=1) / unit_mm
    return float(np.sqrt(np.mean(e * e)))


def free_inside(lips, faces) -> np.ndarray:
    """(V,) bool: the inside of a lip region: vertices of its triangles, its border (shared with others) left out."""
    F = np.asarray(faces)
    lips = np.asarray(lips, bool)
    inside = lips[F].all(axis=1)
    free = np.zeros(len(lips), bool)
    free[F[inside].ravel()] = True
    free[F[~inside].ravel()] = False
    return free


def best_possible_cut_pct(C, T, band, lips, faces) -> float:
    """The most (percent of the band's RMS error) any correction of ``C`` moving only the inside of ``lips`` can cut.

    Its held border and everything outside keep the capture's error (``benchmarks/any_face.py``'s
    ``best_possible_cut_pct``, per frame).
    """
    e2 = np.sum((np.asarray(C) - np.asarray(T)) ** 2, axis=1)[band]
    held = e2[~free_inside(lips, faces)[band]].sum() / max(e2.sum(), 1e-300)
    return 100.0 * (1.0 - float(np.sqrt(held)))


def contact_pairs_of(zf: ZooFace, T, inner: float = 0.8):
    """(P,2) pairs (upper, lower) of contact-line vertices facing each other, away from the corners.

    Each upper-chain vertex (between the corners, within ``inner`` of the half-width of the middle) with the
    lower-chain vertex nearest to it in ``T``.
    """
    U, L = zf.upper[1:-1], zf.lower[1:-1]
    j = cKDTree(T[L]).query(T[U])[1]
    lat = np.cross(zf.up, zf.forward)
    cl, cr = T[zf.corners[0]], T[zf.corners[1]]
    half = 0.5 * abs((cr - cl) @ lat)
    t = ((T[U] - 0.5 * (cl + cr)) @ lat) / max(half, 1e-12)
    ok = np.abs(t) <= inner
    return np.c_[U[ok], L[j[ok]]]


def contact_gap(X, pairs) -> float:
    """Mean 3D distance between the paired upper and lower contact vertices of ``X`` (model units)."""
    X = np.asarray(X)
    return float(np.mean(np.linalg.norm(X[pairs[:, 0]] - X[pairs[:, 1]], axis=1)))
