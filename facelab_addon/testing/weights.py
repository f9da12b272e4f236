"""Expression-weight curves for synthetic performances (tests, benchmarks, demos).

Every generator is deterministic: the same arguments (and seed) give the same
array. Weights are unitless blendshape weights; rows are frames, columns are
expressions (ICT-FaceKit / ARKit names).

* :func:`speech_weights`: speech-like mouth activity (syllable-rate jaw, sparse
  lip shapes, correlated left/right sides) over :data:`SPEECH_CHANNELS`;
* :func:`spline_weights`: smooth random curves, a clamped cubic spline through
  random keys inside a range per expression;
* :func:`rectified_sine_weights`: half-wave rectified sines of random frequency,
  phase and amplitude, the jaw opening and closing regularly;
* :func:`cyclic_mouth_weights`: a fixed periodic mouth cycle over
  :data:`CYCLIC_MOUTH_CHANNELS`, analytic in the frame number;
* :func:`viseme_weights`: key mouth poses (:data:`VISEME_POSES`) in a sequence,
  joined by a cosine ease-in-out.

:func:`facelab_addon.testing.datasets.animated_weights` (held-out expression
templates, eased) lives with the dataset it draws from.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "SPEECH_CHANNELS",
    "CYCLIC_MOUTH_CHANNELS",
    "VISEME_POSES",
    "VISEME_SEQUENCE",
    "smooth_noise",
    "speech_weights",
    "spline_weights",
    "rectified_sine_weights",
    "cyclic_mouth_weights",
    "viseme_weights",
]

#: The mouth shapes of speech and their maximum weight: the columns of :func:`speech_weights`.
SPEECH_CHANNELS = [
    ("jawOpen", 0.55),
    ("mouthClose", 0.35),
    ("mouthFunnel", 0.6),
    ("mouthPucker", 0.7),
    ("mouthSmile_L", 0.7),
    ("mouthSmile_R", 0.7),
    ("mouthPress_L", 0.6),
    ("mouthPress_R", 0.6),
    ("mouthRollLower", 0.5),
    ("mouthRollUpper", 0.4),
    ("mouthStretch_L", 0.5),
    ("mouthStretch_R", 0.5),
    ("mouthLowerDown_L", 0.4),
    ("mouthLowerDown_R", 0.4),
    ("mouthUpperUp_L", 0.4),
    ("mouthUpperUp_R", 0.4),
]

#: The columns of :func:`cyclic_mouth_weights`.
CYCLIC_MOUTH_CHANNELS = ("jawOpen", "mouthClose", "mouthFunnel", "mouthSmile_L", "mouthSmile_R")

#: Speech-like key poses of :func:`viseme_weights` (name -> {expression: weight}).
VISEME_POSES = {
    "rest": {},
    "open": {"jawOpen": 0.45, "mouthLowerDown_L": 0.3, "mouthLowerDown_R": 0.3},
    "ee": {"jawOpen": 0.15, "mouthStretch_L": 0.45, "mouthStretch_R": 0.45, "mouthSmile_L": 0.3,
           "mouthSmile_R": 0.3},
    "oo": {"jawOpen": 0.2, "mouthFunnel": 0.6, "mouthPucker": 0.4},
    "mm": {"mouthClose": 0.2, "mouthPress_L": 0.4, "mouthPress_R": 0.4, "jawOpen": 0.05},
    "ah": {"jawOpen": 0.6, "mouthUpperUp_L": 0.25, "mouthUpperUp_R": 0.25},
}
#: The default order of the poses of :func:`viseme_weights`.
VISEME_SEQUENCE = ["rest", "open", "ee", "oo", "mm", "ah", "oo", "open", "mm", "ee", "ah", "rest"]


def smooth_noise(rng, n: int, sigma: float):
    """Zero-mean, unit-variance Gaussian-filtered white noise.

    Parameters
    ----------
    rng : numpy.random.Generator
        Drawn from (``n + 8 * int(sigma)`` standard normals).
    n : int
        Number of samples (frames).
    sigma : float
        Standard deviation of the Gaussian filter, frames.

    Returns
    -------
    (n,) float64
    """
    w = rng.standard_normal(n + 8 * int(sigma))
    k = np.exp(-0.5 * (np.arange(-4 * int(sigma), 4 * int(sigma) + 1) / sigma) ** 2)
    s = np.convolve(w, k / k.sum(), mode="valid")[:n]
    return (s - s.mean()) / s.std()


def speech_weights(n_frames: int, seed: int = 7, *, channels=None):
    """Smooth, speech-like mouth weights.

    The jaw opens at syllable rate (a 6-frame period, about 4 Hz at 24 fps)
    under a slowly varying envelope; smile, press, stretch, lower-down and
    upper-up are sparse and correlated between the left and right sides;
    close, funnel, pucker and the lip rolls are sparse. Each channel is scaled
    to its maximum in :data:`SPEECH_CHANNELS` (the 99th percentile maps to the
    maximum), and ``mouthClose`` never exceeds ``jawOpen`` (ARKit convention).

    Parameters
    ----------
    n_frames : int
    seed : int
    channels : sequence of str, optional
        Return only these columns, in this order (names of
        :data:`SPEECH_CHANNELS`); the values do not depend on the selection.

    Returns
    -------
    (n_frames, C) float64
        Weights in ``[0, max]``, columns :data:`SPEECH_CHANNELS` (or ``channels``).
    """
    rng = np.random.default_rng(seed)
    W = {}
    # jaw: syllables at ~4 Hz (24 fps) with a slowly varying envelope, closed between phrases
    phase = np.cumsum(2 * np.pi / 6.0 * (1 + 0.25 * smooth_noise(rng, n_frames, 12)))
    env = np.clip(0.6 + 0.5 * smooth_noise(rng, n_frames, 20), 0, 1)
    W["jawOpen"] = np.clip(0.5 + 0.5 * np.sin(phase), 0, 1) ** 1.5 * env
    for base in ("mouthSmile", "mouthPress", "mouthStretch", "mouthLowerDown", "mouthUpperUp"):
        common = smooth_noise(rng, n_frames, 6)
        for side in ("_L", "_R"):
            x = 0.8 * common + 0.45 * smooth_noise(rng, n_frames, 6)
            W[base + side] = np.clip(x - 0.3, 0, None)
    for name in ("mouthClose", "mouthFunnel", "mouthPucker", "mouthRollLower", "mouthRollUpper"):
        W[name] = np.clip(smooth_noise(rng, n_frames, 5) - 0.4, 0, None)
    out = np.zeros((n_frames, len(SPEECH_CHANNELS)))
    for c, (name, mx) in enumerate(SPEECH_CHANNELS):
        x = W[name]
        if name != "jawOpen":
            x = x / max(np.percentile(x, 99), 1e-9)
        out[:, c] = mx * np.clip(x, 0, 1)
    names = [n for n, _ in SPEECH_CHANNELS]
    jc = names.index("mouthClose")
    out[:, jc] = np.minimum(out[:, jc], out[:, 0])
    if channels is not None:
        out = out[:, [names.index(n) for n in channels]]
    return out


def spline_weights(ranges: dict, n_frames: int, *, seed: int = 0, n_keys: int = 6):
    """Smooth random weight curves: a clamped cubic spline through random keys.

    Each curve has ``n_keys`` keys evenly spread over the frames, uniform in
    [0, 1] (the first in [0, 0.3]); the spline is clipped to [0, 1] and mapped
    to the expression's range.

    Parameters
    ----------
    ranges : dict name -> (lo, hi)
        The animated expressions, in column order, and their weight ranges.
    n_frames : int
    seed : int
    n_keys : int
        Random keys per curve (more: faster motion).

    Returns
    -------
    (n_frames, len(ranges)) float64
        Weights within each range (hence within [-1, 1] for sane ranges).
    """
    from scipy.interpolate import CubicSpline

    rng = np.random.default_rng(seed)
    T = int(n_frames)
    out = np.zeros((T, len(ranges)))
    tk = np.linspace(0, max(T - 1, 1), n_keys)
    t = np.arange(T)
    for j, (lo, hi) in enumerate(ranges.values()):
        k = rng.uniform(0, 1, n_keys)
        k[0] = rng.uniform(0, 0.3)
        u = np.clip(CubicSpline(tk, k, bc_type="clamped")(t), 0, 1)
        out[:, j] = lo + (hi - lo) * u
    return out


def rectified_sine_weights(n_frames: int, n_channels: int, seed: int = 7):
    """Half-wave rectified sines: mouth shapes that come and go, a jaw that opens and closes.

    Column ``j`` is ``max(sin(2 pi f t + phase), 0) * a`` over ``t`` in [0, 1]
    with ``f`` in [1, 3.5] cycles, ``phase`` in [0, 2 pi) and ``a`` in
    [0.15, 0.4] drawn per column; column 0 (the jaw) is then replaced by
    ``0.05 + 0.25 * max(sin(2 pi 2.2 t), 0)``.

    Parameters
    ----------
    n_frames : int
    n_channels : int
        Number of columns (the draws depend on it).
    seed : int

    Returns
    -------
    (n_frames, n_channels) float64
        Weights in [0, 0.4].
    """
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 1, n_frames)
    W = np.zeros((n_frames, n_channels))
    for j in range(n_channels):
        f = rng.uniform(1.0, 3.5)
        ph = rng.uniform(0, 2 * np.pi)
        W[:, j] = np.clip(np.sin(2 * np.pi * f * t + ph), 0, None) * rng.uniform(0.15, 0.4)
    W[:, 0] = 0.05 + 0.25 * np.clip(np.sin(2 * np.pi * 2.2 * t), 0, None)  # jaw opens and closes
    return W


def cyclic_mouth_weights(frames, first: int = 1, last: int = 40):
    """A periodic mouth cycle over :data:`CYCLIC_MOUTH_CHANNELS`, analytic in the frame number.

    With ``t = (frame - first) / (last - first)``: jaw ``0.25 + 0.25 sin(2 pi t)``,
    close ``0.1 + 0.1 cos(3 pi t)``, funnel ``0.3 sin(pi t)^2``, smiles
    ``0.3 max(sin(2 pi t + 1), 0)`` (left) and ``0.3 max(sin(2 pi t + 2), 0)``
    (right).

    Parameters
    ----------
    frames : int or (T,) array_like
        Frame numbers (any, also outside ``[first, last]``).
    first, last : int
        Frames where ``t`` is 0 and 1.

    Returns
    -------
    (T, 5) float64, or (5,) for a single frame
    """
    t = (np.asarray(frames, float) - first) / float(last - first)
    return np.stack([
        0.25 + 0.25 * np.sin(2 * np.pi * t),
        0.1 + 0.1 * np.cos(3 * np.pi * t),
        0.3 * np.sin(np.pi * t) ** 2,
        0.3 * np.clip(np.sin(2 * np.pi * t + 1), 0, None),
        0.3 * np.clip(np.sin(2 * np.pi * t + 2), 0, None),
    ], -1)


def viseme_weights(names, frames_per_pose: int, sequence=None, poses=None):
    """Key mouth poses one after the other, joined by a cosine ease-in-out.

    Parameters
    ----------
    names : sequence of str
        Expression names (the columns); expressions a pose does not name are 0.
    frames_per_pose : int
        Frames from one key pose to the next.
    sequence : sequence of str, optional
        Pose names in order (default :data:`VISEME_SEQUENCE`).
    poses : dict, optional
        Pose name -> {expression: weight} (default :data:`VISEME_POSES`).

    Returns
    -------
    ((len(sequence) - 1) * frames_per_pose + 1, len(names)) float64
        The key poses on frames ``0, frames_per_pose, ...``, eased in between.
    """
    sequence = VISEME_SEQUENCE if sequence is None else sequence
    poses = VISEME_POSES if poses is None else poses
    keys = np.array([[poses[p].get(n, 0.0) for n in names] for p in sequence])
    out = []
    for a, b in zip(keys[:-1], keys[1:]):
        s = 0.5 - 0.5 * np.cos(np.pi * np.arange(frames_per_pose) / frames_per_pose)
        out.append(a[None] + s[:, None] * (b - a)[None])
    out.append(keys[-1:])
    return np.concatenate(out)
