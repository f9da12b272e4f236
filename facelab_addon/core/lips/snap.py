"""Snap sketched lip strokes to the plate: each point moves along the stroke's normal onto the image edge.

A rough stroke drawn over footage lies within a few pixels of the lip line the plate shows. For every
stroke point :func:`snap_stroke` samples the image's gradient along the stroke's normal (a Gaussian
derivative, read with cubic splines) within ``search_px``. Only edges of one polarity count: told the
mouth's side (``mouth_side``), the edge darker on that side (the mouth's interior; the other lip's edge
of a narrow mouth has the other polarity); else the polarity most points' strongest edge has. On a colour
plate, told the mouth's side, the profile is the gradient in the colour that tells the lip from the
mouth best above the plate's colour noise (the colour gradients at the strongest edges, summed and
whitened by the noise covariance: a matched filter), not the grey level.

An edge is a local peak of that profile standing ``contrast`` times above what the image's noise gives
the gradient (:func:`image_noise`: a robust spread of the finest detail, so the threshold follows the
plate's own noise), prominent on both sides, and no wider than ``SHARP`` sigmas (a defocused edge is
none). The offsets along the stroke are one path through the peaks, chosen by dynamic programming (each
point scores its edge's strength, a change of offset between neighbours costs ``bend`` per pixel: the
hand's wobble is smooth along the stroke); each point on the path takes its peak's subpixel position (a
Gaussian through the three samples around it) and the offsets are smoothed (a second-difference penalty:
one banded solve). Runs of edge shorter than ``min_run_px`` are dropped (a crease crossing the stroke),
gaps up to ``bridge_px`` between edge points move with them, and everywhere else a point is left
exactly where the artist drew it. :func:`snap_lips` snaps both lips of a frame and leaves the points
where the lips touch or overlap (a sealed mouth has no inner-lip edge; the two sides of a narrow dark crease
between touching lips are none either), and moves the lower lip only part of the way near the mouth's corners.

Conventions: pixels as in :mod:`facelab_addon.core.capture.camera` (top-left image corner at
``(0, 0)``, the centre of pixel ``(i, j)`` at ``(i + 0.5, j + 0.5)``, y down); images ``(H, W)`` or
``(H, W, C)`` arrays, row 0 at the top, any numeric range.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import linalg, ndimage

from ..errors import FaceLabError
from ..geometry.polyline import arc_length

__all__ = ["BEND", "BRIDGE_PX", "CREASE_PX", "LOWER_CORNER", "SEARCH_PX", "SHARP", "SnapResult", "grey",
           "image_noise", "prepare", "snap_lips", "snap_stroke", "snap_strokes"]

_STEP = 0.5  # profile sample spacing, pixels
#: How far along the normal an edge is looked for, pixels each side (chosen on the sample plate's frames 2, 5,
#: 8, ...: a hand's 2-4 px wobble strays past 4.5 px; farther, shading next to a lip is taken more often).
SEARCH_PX = 7.5
#: Cost of a 1 px change of the snapped offset between neighbouring stroke points, in edges at the detection
#: level (chosen on the sample plate's frames 2, 5, 8, ...).
BEND = 2.0
#: Longest stretch of a stroke without an edge, between points with one, that moves with them, pixels.
BRIDGE_PX = 8.0
#: Widest edge taken: the Gaussian fitted to a gradient peak has a standard deviation of at most this many
#: ``sigma`` (a defocused edge is wider).
SHARP = 3.0
#: Fraction of the mouth's width, from each corner, over which the lower lip's snap ramps in from nothing (at
#: the corners its inner line runs inside the mouth's shadow, and the edge there is the lit lip's boundary,
#: below the line; chosen on the sample plate's frames 2, 5, 8, ...).
LOWER_CORNER = 0.15
#: Widest gap between the two lips' edges, pixels over three quarters of their common width, that is taken
#: for the two sides of a dark crease where the lips touch (a sealed mouth) rather than an open mouth.
CREASE_PX = 4.0


@dataclass
class SnapResult:
    """One stroke snapped to the plate.

    Attributes
    ----------
    points : (N,2) float64
        The stroke after snapping, pixels; a point without an edge is exactly the input's.
    offsets : (N,) float64
        How far each point moved along its normal, pixels (0 where left alone).
    snapped : (N,) bool
        Points moved onto an edge.
    polarity : int
        +1 / -1: the sign of the image gradient along the stroke's normal (its left-hand normal in
        the image, y down) of the edge snapped to; 0 when no edge was found.
    sealed : (N,) bool or None
        Points left as drawn because the lips touch or overlap there (:func:`snap_lips`); None: not
        checked.
    """

    points: np.ndarray
    offsets: np.ndarray
    snapped: np.ndarray
    polarity: int = 0
    sealed: np.ndarray | None = None

    @property
    def n_sealed(self) -> int:
        """Points left as drawn because the lips touch or overlap there."""
        return 0 if self.sealed is None else int(self.sealed.sum())

    @property
    def n_snapped(self) -> int:
        return int(self.snapped.sum())

    @property
    def n_left(self) -> int:
        """Points left where they were drawn (no edge found)."""
        return int((~self.snapped).sum())


_LUMA = np.array([0.2126, 0.7152, 0.0722])  # Rec. 709


def grey(image) -> np.ndarray:
    """(H,W) float64 luminance of an ``(H,W)`` or ``(H,W,C)`` image (RGB(A): Rec. 709 weights)."""
    im = np.asarray(image, dtype=np.float64)
    if im.ndim == 2:
        return im
    if im.ndim != 3:
        raise FaceLabError(f"The plate must be an (H,W) or (H,W,C) image, got shape {im.shape}; read it as pixels.")
    if im.shape[2] >= 3:
        return im[..., :3] @ _LUMA
    return im[..., 0]


def _normals(P) -> np.ndarray:
    """(N,2) unit normals of a polyline (tangent by central differences, turned +90° in the image)."""
    T = np.gradient(P, axis=0) if len(P) > 1 else np.array([[1.0, 0.0]])
    T /= np.maximum(np.linalg.norm(T, axis=1, keepdims=True), 1e-12)
    return np.c_[-T[:, 1], T[:, 0]]


def _smooth(meas, weight, smooth: float, free=None) -> np.ndarray:
    """Offsets ``d`` minimising ``sum w (d - meas)^2 + smooth sum (d[i+1] - 2 d[i] + d[i-1])^2``, with the
    points of weight 0 held at 0 (left alone) unless ``free`` (N,) bool (then set by their neighbours).
    (N,) float64."""
    n = len(meas)
    held = (weight <= 0) & (True if free is None else ~np.asarray(free, bool))
    if n < 3 or smooth <= 0:
        return np.where(held, 0.0, meas)
    D = np.zeros((n - 2, n))
    i = np.arange(n - 2)
    D[i, i], D[i, i + 1], D[i, i + 2] = 1.0, -2.0, 1.0
    A = smooth * (D.T @ D) + np.diag(np.where(held, 1e6, weight))
    b = np.where(held, 0.0, weight * meas)
    # A is symmetric positive definite and pentadiagonal: banded Cholesky
    ab = np.zeros((3, n))
    for k in range(3):
        ab[2 - k, k:] = np.diagonal(A, k)
    return linalg.solveh_banded(ab, b)


def snap_stroke(image, stroke_px, *, search_px: float = SEARCH_PX, sigma: float = 1.0, contrast: float = 8.0,
                smooth: float = 2.0, polarity: int | None = None, mouth_side=None, noise: float | None = None,
                quantum: float = 1.0 / 255.0, min_run_px: float = 12.0, bend: float = BEND,
                bridge_px: float = BRIDGE_PX, prepared=None) -> SnapResult:
    """Move the points of one stroke along its normal onto the plate's edge.

    Parameters
    ----------
    image : (H,W) or (H,W,C) array_like
        The plate of the stroke's frame (row 0 at the top).
    stroke_px : (N,2) array_like
        The stroke, pixels (top-left corner origin, y down).
    search_px : float
        How far along the normal an edge is looked for, pixels each side.
    sigma : float
        Scale of the Gaussian derivative, pixels (about the blur of the plate's edges).
    contrast : float
        An edge must have a gradient ``contrast`` times what the image's noise gives the gradient (a
        signal-to-noise ratio).
    smooth : float
        Weight of the offsets' second differences along the stroke (0: each point on its own).
    polarity : int, optional
        +1 / -1 to take only edges whose gradient along the left-hand normal has that sign.
    mouth_side : (2,) array_like, optional
        Image direction ``(dx, dy)`` (y down) in which the mouth's interior lies from this stroke
        (``(0, 1)`` for an upper lip, ``(0, -1)`` for a lower one): the edge taken is darker on that side,
        and on a colour image the edge is measured in the colour that tells the lip from the darker
        side (the plate's own lip-to-mouth contrast). Ignored when ``polarity`` is given; without either,
        the polarity most points' strongest edge has.
    noise : float, optional
        The image's noise, standard deviation in its units; default :func:`image_noise` of ``image``.
    quantum : float
        The image's storage step (1/255: 8-bit footage read as 0..1; 0: float footage).
    min_run_px : float
        Edges found along less than this length of the stroke (pixels) are not taken: a lip edge runs
        along the stroke, a shadow or a crease crossing it does not.
    bridge_px : float
        Points without an edge between points with one, along at most this length of the stroke (pixels),
        move with their neighbours (the smoothing sets them); longer stretches are left as drawn.
    bend : float
        Cost of the offset changing by one pixel between neighbouring points, in units of an edge at the
        detection level (the path along the stroke is chosen by dynamic programming over the offsets).
    prepared : dict, optional
        Gradients from :func:`prepare` of the same image and ``sigma`` (:func:`snap_strokes` shares them).

    Returns
    -------
    SnapResult
    """
    P = np.asarray(stroke_px, dtype=np.float64).reshape(-1, 2)
    n = len(P)
    if n == 0:
        return SnapResult(P.copy(), np.zeros(0), np.zeros(0, bool))
    if not (search_px > 0 and sigma > 0 and contrast > 0 and smooth >= 0 and bend >= 0):
        raise FaceLabError("snap_stroke needs search_px, sigma and contrast > 0, smooth and bend >= 0; use the "
                           "defaults.")
    prep = prepared if prepared is not None else prepare(image, sigma)
    N = _normals(P)
    t = np.arange(-search_px, search_px + 1e-9, _STEP)  # (S,) offsets along the normal
    Q = P[:, None, :] + t[None, :, None] * N[:, None, :]  # (N,S,2) pixels
    coords = np.stack([Q[..., 1].ravel() - 0.5, Q[..., 0].ravel() - 0.5])  # (row, col) of the pixel centres
    inside = ((Q[..., 0] >= 0) & (Q[..., 0] <= prep["shape"][1]) & (Q[..., 1] >= 0) & (Q[..., 1] <= prep["shape"][0]))

    def profile(k):  # directional derivative of channel k along the normal, (N,S)
        gy, gx = prep["gy"][k], prep["gx"][k]
        g = (ndimage.map_coordinates(gx, coords, order=3, mode="nearest", prefilter=False) * np.repeat(N[:, 0], len(t))
             + ndimage.map_coordinates(gy, coords, order=3, mode="nearest", prefilter=False)
             * np.repeat(N[:, 1], len(t)))
        return np.where(inside, g.reshape(n, len(t)), 0.0)

    g = profile(0)  # grey
    if noise is None:
        noise = image_noise(prep["grey"], quantum)
    # an edge stands `contrast` noise deviations above the profile on both sides, and above twice a step of
    # one storage level (a banded gradient of 8-bit footage is no edge)
    floor = 2.0 * quantum / (np.sqrt(2 * np.pi) * sigma)
    level = max(contrast * float(noise) * _derivative_gain(sigma), floor, 1e-300)
    if polarity is None and mouth_side is not None:
        side = float(np.mean(N @ np.asarray(mouth_side, dtype=np.float64)))
        polarity = -int(np.sign(side))  # darker towards the mouth: the gradient along the normal falls there
    if polarity is None:
        best = g[np.arange(n), np.abs(g).argmax(1)]
        strong = np.abs(best) > level
        polarity = int(np.sign(best[strong].sum())) if strong.any() else 0
    if polarity == 0:
        return SnapResult(P.copy(), np.zeros(n), np.zeros(n, bool), 0)
    s = polarity * g
    if mouth_side is not None and len(prep["gy"]) > 1:
        # the colour that tells the lip from the mouth best above the plate's noise: the colour gradients at
        # each point's strongest one, signed alike (their principal direction, brightening with luminance: the
        # mouth is the darker side) and summed, whitened by the noise covariance of the colours (a matched
        # filter: the channel of largest edge-to-noise ratio); the profile is then the gradient in that colour
        G = np.stack([profile(k) for k in range(1, len(prep["gy"]))])  # (C,N,S)
        j = np.einsum("cns,cns->ns", G, G).argmax(1)
        v = G[:, np.arange(n), j]  # (C,N)
        e = np.linalg.eigh(v @ v.T)[1][:, -1]
        w = np.linalg.solve(prep["noise_cov"], (v * np.sign(e @ v)).sum(1))
        w /= max(float(np.linalg.norm(w)), 1e-300)
        w *= 1.0 if w @ _LUMA[:len(w)] >= 0 else -1.0
        s = polarity * np.tensordot(w, G, 1)
        level = max(contrast * image_noise(np.tensordot(w, prep["colour"], 1), quantum) * _derivative_gain(sigma),
                    floor * float(np.abs(w).sum()), 1e-300)
    # local maxima above the level, with their subpixel offsets
    peak = np.zeros_like(s, dtype=bool)
    peak[:, 1:-1] = (s[:, 1:-1] > level) & (s[:, 1:-1] >= s[:, :-2]) & (s[:, 1:-1] > s[:, 2:])
    # prominence: the profile must fall by `level` on each side of the peak (soft shading does not)
    for r, c in zip(*np.nonzero(peak)):
        if s[r, c] - max(s[r, :c].min(), s[r, c + 1:].min()) < level:
            peak[r, c] = False
    # width: a Gaussian through the three samples around the peak (a parabola through their logarithms, exact
    # for a blurred step) no wider than `SHARP` sigmas (an edge as sharp as the plate's own, not a defocused one)
    with np.errstate(divide="ignore", invalid="ignore"):
        ls = np.log(np.maximum(s, 1e-300))
        den = np.zeros_like(s)
        den[:, 1:-1] = ls[:, :-2] - 2 * ls[:, 1:-1] + ls[:, 2:]
        peak &= den < -(_STEP / (SHARP * sigma)) ** 2
    # the path of offsets along the stroke: dynamic programming, each point scoring its edge strength (in levels,
    # at most 3) and paying `bend` per pixel the offset changes from the previous point's
    score = np.where(peak, np.minimum(s / level, 3.0), 0.0)
    path = _best_path(score, t, bend)
    rows, cols = np.nonzero(peak)
    b = s[rows, cols]
    # a Gaussian through the three samples (a parabola through their logarithms): exact for a blurred step
    a, c = (np.log(np.maximum(s[rows, cols + k], 1e-12 * b)) for k in (-1, 1))
    lb = np.log(b)
    den = a - 2 * lb + c
    frac = np.where(den < 0, 0.5 * (a - c) / np.where(den < 0, den, -1.0), 0.0)
    pos = t[cols] + _STEP * np.clip(frac, -0.5, 0.5)
    meas = np.zeros(n)
    found = np.zeros(n, bool)
    on_path = np.abs(t[cols] - path[rows]) < 1e-9
    meas[rows[on_path]], found[rows[on_path]] = pos[on_path], True
    # a few points without an edge between points with one (a faint stretch of the same edge): bridged by
    # the smoothing, not left behind as drawn
    s_len = arc_length(P)
    found = _long_runs(s_len, found, min_run_px)
    moved = found | _gaps(s_len, found, bridge_px)
    d = _smooth(meas, found.astype(np.float64), smooth, free=moved & ~found)
    d = np.where(moved, d, 0.0)
    return SnapResult(P + d[:, None] * N, d, moved, polarity if moved.any() else 0)


def _gaps(s, found, max_len) -> np.ndarray:
    """(N,) bool: the points of the runs of False in ``found`` (N,) that have True on both sides and span
    at most ``max_len`` pixels of the stroke between those two True points (``s`` (N,): its arc length)."""
    out = np.zeros(len(found), bool)
    idx = np.flatnonzero(found)
    if len(idx) < 2 or max_len <= 0:
        return out
    for a, b in zip(idx[:-1], idx[1:]):
        if b - a > 1 and s[b] - s[a] <= max_len:
            out[a + 1:b] = True
    return out


def _best_path(score, t, bend) -> np.ndarray:
    """(N,) offsets (values of ``t``) maximising ``sum score[i, k_i] - bend sum |t[k_i] - t[k_(i-1)]|`` over one
    sample ``k_i`` of ``t`` (S,) per point; ``score`` (N,S). Viterbi."""
    n, S = score.shape
    pen = bend * np.abs(t[:, None] - t[None, :])  # (S,S) from -> to
    acc = score[0].copy()
    back = np.zeros((n, S), dtype=np.int64)
    for i in range(1, n):
        m = acc[:, None] - pen
        back[i] = m.argmax(0)
        acc = m[back[i], np.arange(S)] + score[i]
    k = np.zeros(n, dtype=np.int64)
    k[-1] = int(acc.argmax())
    for i in range(n - 1, 0, -1):
        k[i - 1] = back[i, k[i]]
    return t[k]


def _long_runs(s, found, min_len) -> np.ndarray:
    """``found`` (N,) bool with the runs of consecutive True points spanning less than ``min_len`` pixels
    of the stroke (``s`` (N,): its arc length) set False."""
    out = found.copy()
    i, n = 0, len(found)
    while i < n:
        if not found[i]:
            i += 1
            continue
        j = i
        while j + 1 < n and found[j + 1]:
            j += 1
        if s[j] - s[i] < min_len and not (i == 0 and j == n - 1):
            out[i:j + 1] = False
        i = j + 1
    return out


def image_noise(img, quantum: float = 0.0) -> float:
    """Standard deviation of the noise of a grey image (its units), from its finest detail: the robust
    spread (1.4826 x median absolute deviation) of the image minus its 1-pixel Gaussian blur, divided by
    what that filter leaves of white noise. Edges are few pixels of an image, so they barely count. At
    least the rounding noise of the image's storage step ``quantum`` (``quantum / sqrt(12)``: 1/255 for
    8-bit footage read as 0..1, 0 for float footage)."""
    img = np.asarray(img, dtype=np.float64)
    r = img - ndimage.gaussian_filter(img, 1.0)
    mad = 1.4826 * float(np.median(np.abs(r - np.median(r)))) if img.size else 0.0
    return max(mad / _residual_gain(), float(quantum) / np.sqrt(12.0), 1e-300)


def _impulse(n=33):
    z = np.zeros((n, n))
    z[n // 2, n // 2] = 1.0
    return z


def _residual_gain() -> float:
    """Standard deviation of (image - its 1 px Gaussian blur) for unit white noise."""
    z = _impulse()
    return float(np.linalg.norm(z - ndimage.gaussian_filter(z, 1.0)))


def _derivative_gain(sigma: float) -> float:
    """Standard deviation of one Gaussian derivative (scale ``sigma``) of unit white noise."""
    z = _impulse(2 * int(4 * sigma + 4) + 1)
    return float(np.linalg.norm(ndimage.gaussian_filter(z, sigma, order=(0, 1))))


def _gradients(img, sigma):
    """Cubic spline coefficients of the image's Gaussian derivatives ``(d/drow, d/dcol)``."""
    gy = ndimage.gaussian_filter(img, sigma, order=(1, 0))
    gx = ndimage.gaussian_filter(img, sigma, order=(0, 1))
    return ndimage.spline_filter(gy, order=3), ndimage.spline_filter(gx, order=3)


def prepare(image, sigma: float = 1.0) -> dict:
    """What :func:`snap_stroke` reads of an image, computed once for all its strokes: the grey image
    ``"grey"`` (H,W), the colour channels ``"colour"`` (C,H,W) (RGB; none for a grey image), their noise
    covariance ``"noise_cov"`` (C,C), the cubic spline coefficients of the Gaussian derivatives (scale
    ``sigma`` px) of grey then each colour, ``"gy"`` / ``"gx"`` (1+C,H,W), and ``"shape"`` (H, W)."""
    im = np.asarray(image, dtype=np.float64)
    g = grey(im)
    colour = np.moveaxis(im[..., :3], 2, 0) if im.ndim == 3 and im.shape[2] >= 3 else np.zeros((0,) + g.shape)
    grads = [_gradients(c, sigma) for c in (g, *colour)]
    cov = np.eye(len(colour))
    if len(colour):
        # the colours' noise covariance: of their finest detail (image minus its 1 px blur), the pixels within
        # 4 robust deviations in every channel (edges left out)
        r = np.stack([c - ndimage.gaussian_filter(c, 1.0) for c in colour]).reshape(len(colour), -1)
        dev = np.abs(r - np.median(r, axis=1, keepdims=True))
        ok = np.all(dev <= 4 * 1.4826 * np.median(dev, axis=1, keepdims=True) + 1e-300, axis=0)
        if ok.sum() > 2 * len(colour):
            cov = np.cov(r[:, ok])
        cov = cov + (1e-12 + 1e-6 * np.trace(cov)) * np.eye(len(colour))
    return dict(grey=g, colour=colour, gy=[a for a, _ in grads], gx=[b for _, b in grads], shape=g.shape,
                noise_cov=cov)


def snap_strokes(image, strokes, **options) -> list:
    """:func:`snap_stroke` for each stroke of one image (its gradients and noise computed once, on the part
    of the image around the strokes). ``strokes``: list of (N,2) pixel arrays; ``options``: those of
    :func:`snap_stroke`. Returns a list of :class:`SnapResult`, one per
    stroke, in order."""
    options = dict(options)
    quantum = options.setdefault("quantum", 1.0 / 255.0)
    strokes = [np.asarray(p, dtype=np.float64).reshape(-1, 2) for p in strokes]
    image = np.asarray(image)
    if image.ndim not in (2, 3):
        grey(image)  # raises: not an image
    H, W = image.shape[:2]
    sigma = float(options.get("sigma", 1.0))
    reach = float(options.get("search_px", SEARCH_PX)) + 4 * sigma + 4
    pts = np.vstack([p for p in strokes if len(p)]) if any(len(p) for p in strokes) else np.zeros((0, 2))
    if len(pts) == 0:
        return [SnapResult(p.copy(), np.zeros(0), np.zeros(0, bool)) for p in strokes]
    x0, y0 = (max(int(np.floor(v - reach)), 0) for v in pts.min(0))
    x1, y1 = min(int(np.ceil(pts[:, 0].max() + reach)), W), min(int(np.ceil(pts[:, 1].max() + reach)), H)
    if x1 <= x0 or y1 <= y0:  # the strokes are off the image: nothing to snap to
        return [SnapResult(p.copy(), np.zeros(len(p)), np.zeros(len(p), bool)) for p in strokes]
    crop = np.asarray(image[y0:y1, x0:x1], dtype=np.float64)
    prepared = prepare(crop, sigma)
    if options.get("noise") is None:
        options = dict(options, noise=image_noise(prepared["grey"], quantum))
    off = np.array([x0, y0], dtype=np.float64)
    out = []
    for p in strokes:
        r = snap_stroke(crop, p - off, prepared=prepared, **options)
        out.append(SnapResult(r.points + off, r.offsets, r.snapped, r.polarity))
    return out


def snap_lips(image, upper, lower, *, min_gap_px: float = 1.0, max_crossed: float = 0.5,
              lower_corner: float = LOWER_CORNER, crease_px: float = CREASE_PX, **options) -> tuple:
    """Snap the strokes of both inner lips of one image: :func:`snap_strokes` with the mouth below the
    upper strokes and above the lower ones, then the mouth checked open where a point moved.

    A point stays snapped only where, at its image column, the other lip's line (its points as snapped,
    or as drawn where they were left) lies on the mouth's side by more than ``min_gap_px`` pixels: where
    the lips touch or overlap (a sealed mouth: no interior between the lips, so no inner-lip edge to find),
    the points are left as drawn, in both strokes. Where the strokes as drawn cross (the upper one below the
    lower) along more than ``max_crossed`` of their common width, the artist drew overlapping lips: every
    point is left as drawn; so is every point when the lips' snapped edges are at most ``crease_px`` apart
    along three quarters of their common width (the two sides of a dark crease where the lips touch). Near
    the mouth's corners (the extreme columns of all the strokes) the lower lip's
    points move only part of the way: from nothing at a corner to all of it ``lower_corner`` of the mouth's
    width in (there the lower lip's inner line runs inside the mouth's shadow and the visible edge is the lit
    lip's boundary, below the line).

    Parameters
    ----------
    image : (H,W) or (H,W,C) array_like
    upper, lower : list of (N,2) array_like
        The strokes of each lip, pixels (top-left corner origin, y down).
    min_gap_px : float
        How far apart the lips must be to count as open, pixels.
    max_crossed : float
        Largest fraction of their common width along which the drawn strokes may cross.
    crease_px : float
        Widest gap, pixels, between the lips' edges (over three quarters of their common width) taken for a
        crease between touching lips.
    lower_corner : float
        Fraction of the mouth's width from each corner over which the lower lip's snap ramps in (0: none).
    **options
        Of :func:`snap_stroke` (not ``mouth_side``).

    Returns
    -------
    (list of SnapResult, list of SnapResult)
        Upper and lower, one per stroke, in order.
    """
    drawn = {lab: [np.asarray(p, dtype=np.float64).reshape(-1, 2) for p in strokes]
             for lab, strokes in (("upper", upper), ("lower", lower))}
    res = {lab: snap_strokes(image, drawn[lab], mouth_side=side, **options)
           for lab, side in (("upper", (0.0, 1.0)), ("lower", (0.0, -1.0)))}

    def line(results):  # (x sorted, y) of all the points of one lip's strokes as snapped
        pts = np.vstack([r.points for r in results if len(r.points)]) if any(len(r.points) for r in results) \
            else np.zeros((0, 2))
        return pts[np.argsort(pts[:, 0])]

    lines = {lab: line(res[lab]) for lab in res}
    # drawn crossing over most of their common width: the lips overlap (a sealed mouth drawn as the lips'
    # silhouettes), whatever edges the strokes found
    up0, lo0 = (line([SnapResult(p, np.zeros(len(p)), np.zeros(len(p), bool)) for p in drawn[lab]])
                for lab in ("upper", "lower"))
    crossed = False
    if len(up0) >= 2 and len(lo0) >= 2:
        w = (up0[:, 0] >= lo0[0, 0]) & (up0[:, 0] <= lo0[-1, 0])
        crossed = bool(w.any()) and float(np.mean(np.interp(up0[w, 0], lo0[:, 0], lo0[:, 1]) - up0[w, 1] <= 0)) \
            > max_crossed
    # both lips' edges a narrow band apart along their common width: the two sides of a dark crease where the
    # lips touch, not an open mouth
    up1, lo1 = (np.vstack([np.zeros((0, 2))] + [r.points[r.snapped] for r in res[lab]]) for lab in ("upper", "lower"))
    up1, lo1 = up1[np.argsort(up1[:, 0])], lo1[np.argsort(lo1[:, 0])]
    if len(up1) >= 2 and len(lo1) >= 2:
        w = (up1[:, 0] >= lo1[0, 0]) & (up1[:, 0] <= lo1[-1, 0])
        if w.sum() >= 2:
            crossed |= float(np.percentile(np.interp(up1[w, 0], lo1[:, 0], lo1[:, 1]) - up1[w, 1], 75)) <= crease_px
    allpts = [p for ps in drawn.values() for p in ps if len(p)]
    xa = min(float(p[:, 0].min()) for p in allpts) if allpts else 0.0
    xb = max(float(p[:, 0].max()) for p in allpts) if allpts else 0.0
    ramp = max(lower_corner * (xb - xa), 0.0)
    out = {}
    for lab, other, sign in (("upper", "lower", 1.0), ("lower", "upper", -1.0)):
        kept = []
        for r, P0 in zip(res[lab], drawn[lab]):
            snapped = r.snapped.copy()
            o = lines[other]
            if crossed:
                snapped[:] = False
            elif len(o) >= 2 and snapped.any():
                x, y = r.points[:, 0], r.points[:, 1]
                within = (x >= o[0, 0]) & (x <= o[-1, 0])
                gap = sign * (np.interp(x, o[:, 0], o[:, 1]) - y)  # towards the mouth, pixels
                snapped &= ~(within & (gap <= min_gap_px))
            sealed = r.snapped & ~snapped
            share = np.ones(len(P0))
            if lab == "lower" and ramp > 0 and len(P0):
                share = np.clip(np.minimum(P0[:, 0] - xa, xb - P0[:, 0]) / ramp, 0.0, 1.0)
            snapped &= share > 0
            d = np.where(snapped, share * r.offsets, 0.0)
            P = np.where(snapped[:, None], P0 + share[:, None] * (r.points - P0), P0)
            kept.append(SnapResult(P, d, snapped, r.polarity if snapped.any() else 0, sealed))
        out[lab] = kept
    return out["upper"], out["lower"]
