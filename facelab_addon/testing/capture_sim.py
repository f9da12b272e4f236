"""Synthetic head-mounted capture for the contour solve (tests and benchmark).

Builds the set-up of Bhat et al. 2013 (§3-4) from a blendshape rig with known
ground truth:

* a helmet-like stereo pair: two cameras 15-25 cm in front of the face, left
  and right of the mouth, looking at the face (portrait 1080x1920);
* painted markers: surface points spread over the skin (seeded farthest-point
  sampling of random points in random skin triangles, away from the inner
  mouth and the eyelids, visible from both cameras on the neutral);
* a smooth ground-truth weight sequence of rig expressions (jaw and lip
  activity, brows, blinks; ``weights.spline_weights``), values in [-1, 1];
* optionally an out-of-subspace lip deformation on top of the truth (the
  rig cannot express it; the corrective should), via
  ``synthetic.inject_lip_error`` with a smoothly varying amount;
* the markers projected into both cameras with Gaussian pixel noise, and the
  truth's inner-lip / eyelid occluding contours as tracked curves (through
  ``contours.synthetic_tracked_curves`` when that module is present).

Units: the model's scene units; distances given in centimetres are converted
with ``cm`` (scene units per centimetre, 1 for ICT-FaceKit's default).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..core.capture.camera import Camera
from ..core.capture.markers import SurfacePoints, bind_surface_points
from .weights import spline_weights

__all__ = [
    "SyntheticCapture",
    "helmet_cameras",
    "sample_markers",
    "make_capture",
    "DEFAULT_EXPRESSIONS",
]

#: Expressions animated in the default ground truth (ICT / ARKit names), with weight ranges.
DEFAULT_EXPRESSIONS = {
    "jawOpen": (0.0, 0.55),
    "mouthSmile_L": (0.0, 0.7),
    "mouthSmile_R": (0.0, 0.6),
    "mouthFunnel": (0.0, 0.5),
    "mouthPucker": (0.0, 0.5),
    "mouthLowerDown_L": (0.0, 0.5),
    "mouthLowerDown_R": (0.0, 0.5),
    "mouthUpperUp_L": (0.0, 0.4),
    "mouthUpperUp_R": (0.0, 0.4),
    "mouthRollLower": (0.0, 0.3),
    "jawLeft": (-0.3, 0.3),
    "browInnerUp_L": (0.0, 0.8),
    "browInnerUp_R": (0.0, 0.8),
    "browDown_L": (0.0, 0.5),
    "eyeBlink_L": (0.0, 0.6),
    "eyeBlink_R": (0.0, 0.6),
    "cheekSquint_L": (-0.2, 0.4),
}


@dataclass
class SyntheticCapture:
    """A simulated capture with its ground truth.

    Attributes
    ----------
    cameras : list of Camera
    markers : SurfacePoints
        The markers' true bindings on the neutral (M points).
    names : list of str
        Rig expression names (the solver's S shapes, in order).
    weights : (T,S) float64
        Ground-truth weights.
    truth : (T,V,3) float64
        Ground-truth meshes (rig pose plus any out-of-subspace lip error).
    markers_px : (T,C,M,2) float64
        Noisy marker pixels (NaN: off-screen).
    markers_px_clean : (T,C,M,2) float64
        The same without noise.
    curves : list (T) of list of TrackedCurve, or None
    lip_error : (T,) float64
        Out-of-subspace lip error amount per frame, millimetres.
    """

    cameras: list
    markers: SurfacePoints
    names: list
    weights: np.ndarray
    truth: np.ndarray
    markers_px: np.ndarray
    markers_px_clean: np.ndarray
    curves: list | None = None
    lip_error: np.ndarray = field(default_factory=lambda: np.zeros(0))


def helmet_cameras(center=(0.0, -1.0, 8.0), *, cm: float = 1.0, distance_cm: float = 19.0,
                   offset_cm: float = 6.0, below_cm: float = 3.0, focal_px: float = 1200.0,
                   width: int = 1080, height: int = 1920):
    """Two helmet cameras left and right of the mouth, looking at ``center``.

    Parameters
    ----------
    center : (3,) float
        The point looked at (default: the middle of ICT-FaceKit's face), scene units.
    cm : float
        Scene units per centimetre.
    distance_cm, offset_cm, below_cm : float
        Camera position relative to ``center``: ``distance_cm`` along +z
        (the face looks along +z, Y up), ``±offset_cm`` along x, ``below_cm``
        down along y.
    focal_px : float
        Focal length in pixels.
    width, height : int
        Image size (portrait by default).

    Returns
    -------
    list of Camera
    """
    c = np.asarray(center, float)
    sensor = 36.0
    focal_mm = focal_px / width * sensor
    cams = []
    for s in (-1.0, 1.0):
        eye = c + cm * np.array([s * offset_cm, -below_cm, distance_cm])
        cams.append(Camera.look_at(eye, c, (0.0, 1.0, 0.0), focal_mm, sensor, width, height))
    return cams


def sample_markers(vertices, faces, cameras, face_mask, *, n: int = 80, seed: int = 0, exclude=None,
                   exclude_radius: float = 1.0, min_facing: float = 0.35):
    """Well-spread marker surface points on the skin, visible from every camera.

    Parameters
    ----------
    vertices : (V,3) float
        Neutral mesh, scene units.
    faces : (F,3) int
    cameras : list of Camera
    face_mask : (F,) bool
        Skin triangles markers may be painted on.
    n : int
        Number of markers.
    seed : int
        RNG seed.
    exclude : (k,3) float, optional
        Points (e.g. the inner-lip loop and eyes) no marker may be within
        ``exclude_radius`` (scene units) of.
    min_facing : float
        Minimum cosine between the triangle normal and the direction to each camera.

    Returns
    -------
    SurfacePoints
        ``n`` markers (farthest-point order).
    """
    from scipy.spatial import cKDTree

    V = np.asarray(vertices, float)
    F = np.asarray(faces, np.int64)
    rng = np.random.default_rng(seed)
    tri = np.flatnonzero(np.asarray(face_mask, bool))
    cand = rng.choice(tri, size=min(len(tri), 30 * n), replace=False)
    b = rng.dirichlet(np.ones(3), size=len(cand))
    X = np.einsum("ck,ckd->cd", b, V[F[cand]])
    nrm = np.cross(V[F[cand, 1]] - V[F[cand, 0]], V[F[cand, 2]] - V[F[cand, 0]])
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    ok = np.ones(len(cand), bool)
    for cam in cameras:
        d = cam.center[None] - X
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        ok &= (nrm * d).sum(1) > min_facing
        px = cam.project(X)
        ok &= cam.in_frame(px, margin=20)
        pts, hit = bind_surface_points(V, F, cam, px)
        ok &= hit & (np.linalg.norm(pts.evaluate(V) - X, axis=1) < 1e-6 * max(1.0, np.abs(V).max()))
    if exclude is not None and len(exclude):
        dist, _ = cKDTree(np.asarray(exclude, float)).query(X)
        ok &= dist > exclude_radius
    idx = np.flatnonzero(ok)
    if len(idx) < n:
        n = len(idx)
    # farthest-point sampling from a random start
    chosen = [int(idx[0])]
    d = np.linalg.norm(X[idx] - X[chosen[0]], axis=1)
    for _ in range(n - 1):
        k = int(np.argmax(d))
        chosen.append(int(idx[k]))
        d = np.minimum(d, np.linalg.norm(X[idx] - X[idx[k]], axis=1))
    chosen = np.array(chosen)
    return SurfacePoints(F[cand[chosen]], b[chosen])


def make_capture(model, *, names=None, n_frames: int = 30, n_markers: int = 80, noise_px: float = 0.5,
                 seed: int = 0, lip_error_mm: float = 0.0, curves: bool = True, cameras=None,
                 ranges: dict | None = None):
    """Simulate a helmet capture of an ICT-FaceKit performance.

    Parameters
    ----------
    model : ict.ICTModel
        The rig and truth (scene units from ``model.scale``).
    names : list of str, optional
        Rig expressions the solver uses (default: all of ``model.expressions``).
    n_frames : int
    n_markers : int
    noise_px : float
        Standard deviation of the Gaussian marker noise, pixels.
    seed : int
    lip_error_mm : float
        Peak out-of-subspace inner-lip error (``synthetic.inject_lip_error``,
        "gap" when positive, "cross" when negative), varying smoothly over
        the sequence as ``sin``. 0: the truth is inside the rig's span.
    curves : bool
        Also produce the tracked contour curves (needs ``core.solve.contour_loops``).
    cameras : list of Camera, optional
        Default :func:`helmet_cameras` scaled to the model.
    ranges : dict name -> (lo, hi), optional
        Animated expressions and their ranges (default ``DEFAULT_EXPRESSIONS``).

    Returns
    -------
    SyntheticCapture
    """
    from ..core.lips.mouth import find_mouth
    from .synthetic import ICT_MOUTH_LOOP, inject_lip_error

    cm = float(model.scale)
    names = list(model.expressions) if names is None else list(names)
    ranges = DEFAULT_EXPRESSIONS if ranges is None else ranges
    ranges = {k: v for k, v in ranges.items() if k in names}
    V0, F = model.neutral, model.faces
    cams = helmet_cameras(cm=cm, center=np.array([0.0, -1.0, 8.0]) * cm) if cameras is None else list(cameras)
    skin = model.part_face_mask("M_Face")
    eyes = V0[model.part_vertex_mask("M_ScleraLeft", "M_ScleraRight")]
    excl = np.concatenate([V0[ICT_MOUTH_LOOP], eyes])
    markers = sample_markers(V0, F, cams, skin, n=n_markers, seed=seed, exclude=excl, exclude_radius=0.9 * cm)
    W_sub = spline_weights(ranges, n_frames, seed=seed + 1)
    W = np.zeros((n_frames, len(names)))
    for j, k in enumerate(ranges):
        W[:, names.index(k)] = W_sub[:, j]
    D = model.deltas(names)
    truth = V0[None] + np.einsum("ts,svd->tvd", W, D)
    amount = np.zeros(n_frames)
    if lip_error_mm:
        fixed = ~model.part_vertex_mask("M_Face")
        mouth = find_mouth(V0, F, fixed, loop=ICT_MOUTH_LOOP, units_per_mm=0.1 * cm)
        amount = abs(lip_error_mm) * (0.6 + 0.4 * np.sin(np.linspace(0, 2 * np.pi, n_frames)))
        kind = "gap" if lip_error_mm > 0 else "cross"
        for t in range(n_frames):
            truth[t], _ = inject_lip_error(truth[t], F, fixed, kind=kind, amount_mm=float(amount[t]), mouth=mouth)
    rng = np.random.default_rng(seed + 2)
    X = markers.evaluate(truth)  # (T,M,3)
    clean = np.stack([np.stack([c.project(X[t]) for c in cams]) for t in range(n_frames)])
    noisy = clean + rng.normal(0.0, noise_px, clean.shape)
    for ci, c in enumerate(cams):
        for t in range(n_frames):
            bad = ~c.in_frame(clean[t, ci])
            noisy[t, ci, bad] = np.nan
    tracked = None
    if curves:
        from .contour_truth import ict_contour_loops, synthetic_tracked_curves

        loops = ict_contour_loops(model)
        tracked = [synthetic_tracked_curves(truth[t], F, cams, loops) for t in range(n_frames)]
    return SyntheticCapture(cameras=cams, markers=markers, names=names, weights=W, truth=truth,
                            markers_px=noisy, markers_px_clean=clean, curves=tracked, lip_error=amount)
