"""Facial shape datasets for local geometric indexing, generated from ICT-FaceKit.

Cong, Lan and Fedkiw 2019, §3: the dataset holds captured extreme poses,
augmented with *nonlinear* in-betweens and combinations (made with muscle
simulation in the paper, because linear in-betweens "suffer from well-known
linear blendshape artifacts such as volume loss" and add nothing a linear
blend does not already have). We have no simulator, so FaceLab generates its
test, demo and benchmark data from the ICT-FaceKit expressions with a small,
documented *nonlinear face model* (:class:`ICTShapeGenerator`):

``x(w) = T_jaw(theta(w)) ( x0 + sum_k w_k b*_k
                          + kappa_i sum_k sin(pi w_k) |b*_k| n
                          + kappa_c sum_{k<l} w_k w_l sqrt(|b*_k| |b*_l|) n )``

* ``b*_k`` is ICT expression ``k``'s delta with the jaw motion removed (Eq. 2);
  ``T_jaw`` is linear blend skinning with a jaw hinge fitted to ``jawOpen``
  on the lower teeth (:func:`fit_ict_jaw`, a 25.3 degree rotation about a
  left-right axis), and ``theta(w)`` is linear in the jaw weights
  (``jawOpen`` rotates, ``jawForward/Left/Right`` translate). So jaw
  in-betweens follow arcs, not chords.
* The ``sin(pi w)`` term bulges the skin along the neutral normal ``n`` in
  the middle of a motion (zero at 0 and 1): skin bunching of an in-between.
* The ``w_k w_l`` term bulges the skin where two expressions overlap, the
  volume-preserving correction a FACS corrective shape would add.
* Bulges act on the skin (``M_Face``) only; ``kappa_i = 0.15``,
  ``kappa_c = 0.25`` by default (a 3 mm bulge for a 2 cm motion).

With all weights 0 or 1 and a single expression, ``x(w)`` is the ICT target
exactly, so the dataset contains the 57 ICT expressions unchanged.

:func:`ict_dataset` returns those 57 expressions, in-betweens of the
largest expressions (``jawOpen`` at 0.25, 0.5, 0.75; 20 others at 0.5) and
``n_combinations`` FACS-style expression templates (``EXPRESSION_TEMPLATES``,
e.g. the sneer + upper-lip raiser + brow lowerer of the paper's Fig. 7) at
full weight: 109 shapes by default. :func:`held_out_weights` draws
combinations that are *not* in the dataset (template components at random
partial weights, mixtures of two templates); :func:`animated_weights` makes a
smooth performance through such poses. :func:`ict_bundle_layout` places
motion-capture bundles on the face like a painted marker pattern.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..core.geometry.mesh import face_normals, triangulate, vertex_normals
from ..core.geometry.rigid import rigid_fit
from ..core.lgi.jaw import JawRig
from ..core.lgi.natural_neighbor import surface_points

__all__ = [
    "EXPRESSION_TEMPLATES",
    "INBETWEENS",
    "JAW_SHAPES",
    "ict_triangle_uvs",
    "ict_bundle_layout",
    "fit_ict_jaw",
    "ICTShapeGenerator",
    "ICTDataset",
    "ict_dataset",
    "held_out_weights",
    "animated_weights",
    "bundles_for",
]

JAW_SHAPES = ("jawOpen", "jawForward", "jawLeft", "jawRight")


def _lr(base, w=1.0):
    return {f"{base}_L": w, f"{base}_R": w}


#: FACS-style expression templates (name -> {ICT expression: weight}).
EXPRESSION_TEMPLATES = {
    "smile": {**_lr("mouthSmile"), **_lr("cheekSquint", 0.6)},
    "smile_open": {**_lr("mouthSmile"), **_lr("cheekSquint", 0.5), "jawOpen": 0.4},
    "smirk_L": {"mouthSmile_L": 1.0, "mouthLeft": 0.3, "cheekSquint_L": 0.5},
    "smirk_R": {"mouthSmile_R": 1.0, "mouthRight": 0.3, "cheekSquint_R": 0.5},
    "anger": {**_lr("noseSneer"), **_lr("mouthUpperUp"), **_lr("browDown")},  # Fig. 7
    "snarl_L": {"noseSneer_L": 1.0, "mouthUpperUp_L": 1.0, "cheekRaiser_L": 0.6},
    "snarl_R": {"noseSneer_R": 1.0, "mouthUpperUp_R": 1.0, "cheekRaiser_R": 0.6},
    "yell": {"jawOpen": 0.7, **_lr("browDown"), **_lr("noseSneer", 0.6), **_lr("mouthUpperUp", 0.5)},
    "sad": {**_lr("browInnerUp"), **_lr("mouthFrown"), "mouthShrugLower": 0.5},
    "surprise": {**_lr("browInnerUp"), **_lr("browOuterUp"), **_lr("eyeWide"), "jawOpen": 0.5},
    "fear": {**_lr("browInnerUp"), **_lr("eyeWide"), **_lr("mouthStretch"), "jawOpen": 0.3},
    "disgust": {**_lr("noseSneer"), "mouthShrugUpper": 0.7, **_lr("mouthFrown", 0.4)},
    "kiss": {"mouthPucker": 1.0, **_lr("cheekSquint", 0.3)},
    "ooh": {"mouthFunnel": 1.0, "jawOpen": 0.3},
    "aah": {"jawOpen": 0.8, **_lr("mouthStretch", 0.4)},
    "eee": {**_lr("mouthStretch"), **_lr("mouthSmile", 0.4)},
    "mmm": {**_lr("mouthPress"), "mouthRollLower": 0.4, "mouthRollUpper": 0.4},
    "puff": {**_lr("cheekPuff"), "mouthClose": 0.2},
    "yawn": {"jawOpen": 1.0, **_lr("eyeSquint", 0.6), **_lr("browInnerUp", 0.4)},
    "wink_L": {"eyeBlink_L": 1.0, "cheekSquint_L": 0.7, "mouthSmile_L": 0.4},
    "wink_R": {"eyeBlink_R": 1.0, "cheekSquint_R": 0.7, "mouthSmile_R": 0.4},
    "squint": {**_lr("eyeSquint"), **_lr("cheekSquint"), **_lr("browDown", 0.4)},
    "pout": {"mouthShrugLower": 1.0, "mouthShrugUpper": 0.5, **_lr("mouthFrown", 0.5)},
    "grimace": {**_lr("mouthStretch"), **_lr("mouthLowerDown"), **_lr("mouthUpperUp", 0.6)},
    "dimple": {**_lr("mouthDimple"), **_lr("mouthPress", 0.5)},
    "jaw_side_L": {"jawLeft": 1.0, "mouthLeft": 0.5},
    "jaw_side_R": {"jawRight": 1.0, "mouthRight": 0.5},
    "jaw_forward": {"jawForward": 1.0, "mouthShrugLower": 0.4},
    "brows_up": {**_lr("browInnerUp"), **_lr("browOuterUp")},
    "concern": {**_lr("browInnerUp"), **_lr("browDown", 0.5), **_lr("mouthPress", 0.4)},
    "roll_lips": {"mouthRollLower": 1.0, "mouthRollUpper": 1.0},
    "talk_o": {"jawOpen": 0.35, "mouthFunnel": 0.6, "mouthPucker": 0.3},
}

#: In-betweens added to the dataset: (expression, weight).
INBETWEENS = [("jawOpen", 0.25), ("jawOpen", 0.5), ("jawOpen", 0.75)] + [
    (n, 0.5)
    for n in (
        "mouthSmile_L", "mouthSmile_R", "mouthPucker", "mouthFunnel", "mouthClose", "mouthLeft", "mouthRight",
        "mouthStretch_L", "mouthStretch_R", "mouthRollLower", "mouthRollUpper", "cheekPuff_L", "cheekPuff_R",
        "eyeBlink_L", "eyeBlink_R", "browInnerUp_L", "browInnerUp_R", "browOuterUp_L", "browOuterUp_R",
        "mouthShrugLower",
    )
]


def ict_triangle_uvs(ict):
    """(F,3,2) UVs of every triangle corner of ``ict.faces`` (same fan triangulation)."""
    tuv, _ = triangulate(ict.poly_uv, ict.poly_offsets)
    return ict.uvs[tuv]


def ict_bundle_layout(ict, n: int = 100, seed: int = 0):
    """Motion-capture bundles spread over the ICT face like a painted marker pattern.

    Farthest-point sampling over the front of the skin (``M_Face`` triangles
    facing forward, away from the eyelids, the inner lips and the ears), each
    bundle at a random point of its triangle.

    Parameters
    ----------
    ict : ICTModel
    n : int
        Number of bundles.
    seed : int

    Returns
    -------
    bundle_faces : (n,) int64 ndarray
    bundle_bary : (n,3) float64 ndarray
    """
    rng = np.random.default_rng(seed)
    X, F = ict.neutral, ict.faces
    s = 1.0 / ict.scale  # work in centimetres
    fn = face_normals(X, F)
    cen = X[F].mean(axis=1) * s
    ok = ict.part_face_mask("M_Face") & (fn[:, 2] > 0.35)
    ok &= (np.abs(cen[:, 0]) < 6.0) & (cen[:, 1] > -8.5) & (cen[:, 1] < 8.5) & (cen[:, 2] > 5.5)
    for name in ("eyeBlink_L", "eyeBlink_R"):
        if name in ict.expressions:
            mv = np.linalg.norm(ict.expressions[name] - X, axis=1) * s
            ok &= mv[F].max(axis=1) < 0.15
    if "mouthRollLower" in ict.expressions:  # inner lips curl in: keep to the outer lip
        vn = vertex_normals(X, F)
        ok &= vn[F][:, :, 2].min(axis=1) > 0.2
    cand = np.flatnonzero(ok)
    C = cen[cand]
    start = int(np.argmax(C[:, 2]))  # nose tip
    chosen = [start]
    d = np.linalg.norm(C - C[start], axis=1)
    for _ in range(n - 1):
        k = int(np.argmax(d))
        chosen.append(k)
        d = np.minimum(d, np.linalg.norm(C - C[k], axis=1))
    faces = cand[np.array(chosen)]
    bary = rng.dirichlet([4.0, 4.0, 4.0], size=n)
    return faces.astype(np.int64), bary


def fit_ict_jaw(ict):
    """A jaw rig for ICT-FaceKit from its ``jaw*`` expressions.

    The hinge is the rigid motion of the lower teeth in ``jawOpen``
    (Kabsch fit; on ICT-FaceKit a 25.3 degree rotation about the left-right
    axis through (0, -0.55, 1.82) cm, 0.2 mm residual). The skinning weight
    of a vertex is the fraction of the rigid jaw motion its ``jawOpen``
    displacement follows (least squares, clipped to [0, 1]). ``jawForward``,
    ``jawLeft`` and ``jawRight`` are translations (the lower teeth's mean
    displacement).

    Parameters
    ----------
    ict : ICTModel

    Returns
    -------
    jaw : JawRig
    unit_params : dict str -> (4,) float64
        Jaw parameters ``(angle rad, tx, ty, tz)`` of each ``jaw*``
        expression at weight 1.
    """
    X = ict.neutral
    teeth = ict.part_vertex_mask("M_Teeth")
    d = ict.expressions["jawOpen"] - X
    n = np.linalg.norm(d, axis=1)
    lower = teeth & (n > 0.5 * n[teeth].max())
    R, t = rigid_fit(X[lower], ict.expressions["jawOpen"][lower])
    angle = float(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1)))
    axis = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    axis /= np.linalg.norm(axis)
    pivot = np.linalg.lstsq(np.eye(3) - R, t, rcond=None)[0]
    rig_full = JawRig(pivot, axis, np.ones(len(X)))
    full = rig_full.skin(X, (angle, 0, 0, 0)) - X
    ff = (full * full).sum(1)
    w = np.where(ff > 1e-8 * ff.max(), (d * full).sum(1) / np.maximum(ff, 1e-300), 0.0)
    jaw = JawRig(pivot, axis, np.clip(w, 0, 1))
    unit = {"jawOpen": np.array([angle, 0.0, 0.0, 0.0])}
    for name in ("jawForward", "jawLeft", "jawRight"):
        if name in ict.expressions:
            tt = (ict.expressions[name] - X)[lower].mean(axis=0)
            unit[name] = np.r_[0.0, tt]
    return jaw, unit


class ICTShapeGenerator:
    """The nonlinear ICT face model of this module's docstring.

    Parameters
    ----------
    ict : ICTModel
    inbetween_bulge : float
        ``kappa_i``, unitless.
    combination_bulge : float
        ``kappa_c``, unitless.

    Attributes
    ----------
    jaw : JawRig
    jaw_units : dict str -> (4,) float64
    names : list of str
        The ICT expression names.
    """

    def __init__(self, ict, *, inbetween_bulge: float = 0.15, combination_bulge: float = 0.25):
        self.ict = ict
        self.x0 = ict.neutral
        self.names = list(ict.expressions)
        self.jaw, self.jaw_units = fit_ict_jaw(ict)
        self.normals = vertex_normals(ict.neutral, ict.faces)
        skin = ict.part_vertex_mask("M_Face").astype(np.float64)
        self.kappa_i = float(inbetween_bulge)
        self.kappa_c = float(combination_bulge)
        self.bstar, self.mag = {}, {}
        for n in self.names:
            th = self.jaw_units.get(n)
            if th is not None:
                b = self.jaw.unskin_shape(ict.expressions[n], self.x0, th)
            else:
                b = ict.expressions[n] - self.x0
            self.bstar[n] = b
            self.mag[n] = np.linalg.norm(b, axis=1) * skin

    def jaw_parameters(self, weights: dict):
        """(4,) jaw parameters ``(angle rad, tx, ty, tz)`` of a weight dict."""
        th = np.zeros(4)
        for n, w in weights.items():
            if n in self.jaw_units:
                th += float(w) * self.jaw_units[n]
        return th

    def __call__(self, weights: dict):
        """(V,3) face for ICT expression weights ``{name: weight}``, scene units."""
        u = self.x0.copy()
        bulge = np.zeros(len(u))
        items = [(n, float(w)) for n, w in weights.items() if float(w) != 0.0]
        for n, w in items:
            if n not in self.bstar:
                raise KeyError(f"unknown ICT expression {n!r}")
            u += w * self.bstar[n]
            bulge += self.kappa_i * np.sin(np.pi * w) * self.mag[n]
        for a in range(len(items)):
            for b in range(a + 1, len(items)):
                (na, wa), (nb, wb) = items[a], items[b]
                bulge += self.kappa_c * wa * wb * np.sqrt(self.mag[na] * self.mag[nb])
        u += bulge[:, None] * self.normals
        return self.jaw.skin(u, self.jaw_parameters(weights))


@dataclass
class ICTDataset:
    """A generated dataset.

    Attributes
    ----------
    names : list of str
    shapes : (S,V,3) float64
        Positions, scene units.
    weights : list of dict
        ICT expression weights of every shape.
    jaw : (S,4) float64
        Jaw parameters of every shape (for :class:`GeometricIndexer`'s ``shape_jaw``).
    generator : ICTShapeGenerator
    """

    names: list
    shapes: np.ndarray
    weights: list
    jaw: np.ndarray
    generator: ICTShapeGenerator

    def __iter__(self):  # ``names, shapes = ict_dataset(ict)``
        return iter((self.names, self.shapes))


def ict_dataset(ict, n_combinations: int = 30, *, inbetweens=None, seed: int = 0, generator=None) -> ICTDataset:
    """ICT expressions plus generated in-betweens and combinations (module docstring).

    Parameters
    ----------
    ict : ICTModel
    n_combinations : int
        How many of ``EXPRESSION_TEMPLATES`` (drawn with ``seed``) are added
        at full weight.
    inbetweens : list of (str, float), optional
        Default ``INBETWEENS`` (23 in-betweens).
    seed : int
    generator : ICTShapeGenerator, optional

    Returns
    -------
    ICTDataset
        Unpacks as ``names, shapes``.
    """
    gen = generator or ICTShapeGenerator(ict)
    rng = np.random.default_rng(seed)
    weights, names = [], []
    for n in gen.names:
        weights.append({n: 1.0})
        names.append(n)
    for n, w in INBETWEENS if inbetweens is None else inbetweens:
        weights.append({n: float(w)})
        names.append(f"{n}@{w:g}")
    keys = list(EXPRESSION_TEMPLATES)
    pick = rng.permutation(len(keys))[: int(n_combinations)]
    for k in sorted(pick):
        weights.append(dict(EXPRESSION_TEMPLATES[keys[k]]))
        names.append(keys[k])
    shapes = np.stack([gen(w) for w in weights])
    jaw = np.stack([gen.jaw_parameters(w) for w in weights])
    return ICTDataset(names=names, shapes=shapes, weights=weights, jaw=jaw, generator=gen)


def held_out_weights(n: int, seed: int = 1, *, low: float = 0.3, high: float = 0.9, mix: float = 0.5):
    """Expression weights of held-out poses (combinations not in the dataset).

    Each pose takes a random template and scales each component by its own
    factor in ``[low, high]``; with probability ``mix`` a second template is
    added at ``[0.2, 0.5]`` of its weights. Weights are clipped to [0, 1].

    Parameters
    ----------
    n : int
    seed : int
    low, high, mix : float

    Returns
    -------
    list of dict str -> float
    """
    rng = np.random.default_rng(seed)
    keys = list(EXPRESSION_TEMPLATES)
    out = []
    for _ in range(int(n)):
        t = EXPRESSION_TEMPLATES[keys[rng.integers(len(keys))]]
        w = {k: v * rng.uniform(low, high) for k, v in t.items()}
        if rng.random() < mix:
            t2 = EXPRESSION_TEMPLATES[keys[rng.integers(len(keys))]]
            s = rng.uniform(0.2, 0.5)
            for k, v in t2.items():
                w[k] = w.get(k, 0.0) + s * v
        out.append({k: float(np.clip(v, 0.0, 1.0)) for k, v in w.items()})
    return out


def animated_weights(n_frames: int, seed: int = 2, *, hold: int = 12):
    """A smooth performance: held-out poses every ``hold`` frames, eased in between.

    Parameters
    ----------
    n_frames : int
    seed : int
    hold : int
        Frames between key poses (the neutral is one pose in four).

    Returns
    -------
    list of dict str -> float
        One weight dict per frame.
    """
    n_keys = int(np.ceil(n_frames / hold)) + 2
    keys = held_out_weights(n_keys, seed)
    rng = np.random.default_rng(seed + 100)
    for i in range(n_keys):
        if rng.random() < 0.25:
            keys[i] = {}
    out = []
    for f in range(int(n_frames)):
        k, r = divmod(f, hold)
        s = r / hold
        s = s * s * (3 - 2 * s)
        a, b = keys[k], keys[k + 1]
        w = {n: (1 - s) * a.get(n, 0.0) + s * b.get(n, 0.0) for n in set(a) | set(b)}
        out.append({n: v for n, v in w.items() if v > 0})
    return out


def bundles_for(shapes, faces, bundle_faces, bundle_bary):
    """Bundle positions on shapes: (..., B, 3) for shapes (..., V, 3), scene units."""
    return surface_points(shapes, faces, bundle_faces, bundle_bary)
