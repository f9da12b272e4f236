"""Snap sketched lip strokes to the plate: each point moves along the stroke's normal onto the image edge.

A rough stroke drawn over footage lies within a few pixels of the lip line the plate shows. For every
stroke point :func:`snap_stroke` samples the image's gradient along the stroke's normal (a Gaussian
derivative of the grey image, read with cubic splines), takes the edge as the subpixel peak of that
profile (a Gaussian through the three samples around the largest one), and smooths the offsets along
the stroke (a second-difference penalty: one tridiagonal solve, repeated once after picking, at each
point, the edge nearest the smoothed line). Only edges of the stroke's own polarity count (the one
most of its points see: the upper lip's inner edge is light above, dark below), so the other lip's
edge of a sealed mouth is not taken.

Where no edge is found a point is left exactly where the artist drew it: an edge counts when its
gradient stands ``contrast`` times above what the noise of the image around the strokes gives a
gradient (:func:`image_noise`: a robust spread of the image's finest detail, so the threshold follows
the plate's own noise, no absolute level), and lies within ``search_px`` of the stroke.

Conventions: pixels as in :mod:`facelab_addon.core.capture.camera` (top-left image corner at
``(0, 0)``, the centre of pixel ``(i, j)`` at ``(i + 0.5, j + 0.5)``, y down); images ``(H, W)`` or
``(H, W, C)`` arrays, row 0 at the top, any numeric range.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import linalg, ndimage

from ..errors import FaceLabError

__all__ = ["SEARCH_PX", "SnapResult", "grey", "image_noise", "snap_stroke", "snap_strokes"]

_STEP = 0.5  # profile sample spacing, pixels
#: How far along the normal an edge is looked for, pixels each side (chosen on the sample plate's frames 2, 5,
#: 8, ...: farther, the shading next to a lip's edge is taken more often than the edge).
SEARCH_PX = 4.5


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
    """

    points: np.ndarray
    offsets: np.ndarray
    snapped: np.ndarray
    polarity: int = 0

    @property
    def n_snapped(self) -> int:
        return int(self.snapped.sum())

    @property
    def n_left(self) -> int:
        """Points left where they were drawn (no edge found)."""
        return int((~self.snapped).sum())


def grey(image) -> np.ndarray:
    """(H,W) float64 luminance of an ``(H,W)`` or ``(H,W,C)`` image (RGB(A): Rec. 709 weights)."""
    im = np.asarray(image, dtype=np.float64)
    if im.ndim == 2:
        return im
    if im.ndim != 3:
        raise FaceLabError(f"The plate must be an (H,W) or (H,W,C) image, got shape {im.shape}; read it as pixels.")
    if im.shape[2] >= 3:
        return im[..., :3] @ np.array([0.2126, 0.7152, 0.0722])
    return im[..., 0]


def _normals(P) -> np.ndarray:
    """(N,2) unit normals of a polyline (tangent by central differences, turned +90° in the image)."""
    T = np.gradient(P, axis=0) if len(P) > 1 else np.array([[1.0, 0.0]])
    T /= np.maximum(np.linalg.norm(T, axis=1, keepdims=True), 1e-12)
    return np.c_[-T[:, 1], T[:, 0]]


def _smooth(meas, weight, smooth: float) -> np.ndarray:
    """Offsets ``d`` minimising ``sum w (d - meas)^2 + smooth sum (d[i+1] - 2 d[i] + d[i-1])^2``, with the
    points of weight 0 held at 0 (left alone). (N,) float64."""
    n = len(meas)
    held = weight <= 0
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


def snap_stroke(image, stroke_px, *, search_px: float = SEARCH_PX, sigma: float = 1.0, contrast: float = 5.0,
                smooth: float = 2.0, polarity: int | None = None, noise: float | None = None,
                quantum: float = 1.0 / 255.0, min_run_px: float = 12.0, prepared=None) -> SnapResult:
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
        +1 / -1 to take only edges whose gradient along the left-hand normal has that sign; default:
        the sign most points' strongest edge has.
    noise : float, optional
        The image's noise, standard deviation in its units; default :func:`image_noise` of ``image``.
    quantum : float
        The image's storage step (1/255: 8-bit footage read as 0..1; 0: float footage).
    min_run_px : float
        Edges found along less than this length of the stroke (pixels) are not taken: a lip edge runs
        along the stroke, a shadow or a crease crossing it does not.
    prepared : tuple, optional
        ``(gy, gx)`` spline coefficients from an earlier call on the same image and ``sigma``
        (:func:`snap_strokes` shares them; pass ``noise`` with them).

    Returns
    -------
    SnapResult
    """
    P = np.asarray(stroke_px, dtype=np.float64).reshape(-1, 2)
    n = len(P)
    if n == 0:
        return SnapResult(P.copy(), np.zeros(0), np.zeros(0, bool))
    if not (search_px > 0 and sigma > 0 and contrast > 0 and smooth >= 0):
        raise FaceLabError("snap_stroke needs search_px, sigma and contrast > 0 and smooth >= 0; use the defaults.")
    gy, gx = prepared if prepared is not None else _gradients(grey(image), sigma)
    N = _normals(P)
    t = np.arange(-search_px, search_px + 1e-9, _STEP)  # (S,) offsets along the normal
    Q = P[:, None, :] + t[None, :, None] * N[:, None, :]  # (N,S,2) pixels
    coords = np.stack([Q[..., 1].ravel() - 0.5, Q[..., 0].ravel() - 0.5])  # (row, col) of the pixel centres
    g = (ndimage.map_coordinates(gx, coords, order=3, mode="nearest", prefilter=False) * np.repeat(N[:, 0], len(t))
         + ndimage.map_coordinates(gy, coords, order=3, mode="nearest", prefilter=False) * np.repeat(N[:, 1], len(t)))
    g = g.reshape(n, len(t))  # directional derivative along the normal, (N,S)
    inside = ((Q[..., 0] >= 0) & (Q[..., 0] <= gx.shape[1]) & (Q[..., 1] >= 0) & (Q[..., 1] <= gx.shape[0]))
    g = np.where(inside, g, 0.0)
    if noise is None:
        noise = image_noise(grey(image), quantum)
    # an edge stands `contrast` noise deviations above the profile on both sides, and above twice a step of
    # one storage level (a banded gradient of 8-bit footage is no edge)
    level = max(contrast * float(noise) * _derivative_gain(sigma), 2.0 * quantum / (np.sqrt(2 * np.pi) * sigma),
                1e-300)
    if polarity is None:
        best = g[np.arange(n), np.abs(g).argmax(1)]
        strong = np.abs(best) > level
        polarity = int(np.sign(best[strong].sum())) if strong.any() else 0
    if polarity == 0:
        return SnapResult(P.copy(), np.zeros(n), np.zeros(n, bool), 0)
    s = polarity * g
    # local maxima above the level, with their subpixel offsets
    peak = np.zeros_like(s, dtype=bool)
    peak[:, 1:-1] = (s[:, 1:-1] > level) & (s[:, 1:-1] >= s[:, :-2]) & (s[:, 1:-1] > s[:, 2:])
    # prominence: the profile must fall by `level` on each side of the peak (soft shading does not)
    for r, c in zip(*np.nonzero(peak)):
        if s[r, c] - max(s[r, :c].min(), s[r, c + 1:].min()) < level:
            peak[r, c] = False
    rows, cols = np.nonzero(peak)
    b = s[rows, cols]
    # a Gaussian through the three samples (a parabola through their logarithms): exact for a blurred step
    a, c = (np.log(np.maximum(s[rows, cols + k], 1e-12 * b)) for k in (-1, 1))
    lb = np.log(b)
    den = a - 2 * lb + c
    frac = np.where(den < 0, 0.5 * (a - c) / np.where(den < 0, den, -1.0), 0.0)
    pos = t[cols] + _STEP * np.clip(frac, -0.5, 0.5)
    # first pick: the strongest edge of each point; then the one nearest the smoothed line
    meas = np.zeros(n)
    found = np.zeros(n, bool)
    strength = np.full(n, -np.inf)
    for r, p, v in zip(rows, pos, b):
        if v > strength[r]:
            strength[r], meas[r], found[r] = v, p, True
    d = _smooth(meas, found.astype(np.float64), smooth)
    if len(rows):
        meas2 = meas.copy()
        gap = np.full(n, np.inf)
        for r, p in zip(rows, pos):
            e = abs(p - d[r])
            if e < gap[r]:
                gap[r], meas2[r] = e, p
        found &= gap <= 1.0 + 0.25 * search_px  # an edge far off the smoothed line: none for this point
        found = _long_runs(P, found, min_run_px)
        d = _smooth(meas2, found.astype(np.float64), smooth)
    d = np.where(found, d, 0.0)
    return SnapResult(P + d[:, None] * N, d, found, polarity if found.any() else 0)


def _long_runs(P, found, min_len) -> np.ndarray:
    """``found`` (N,) bool with the runs of consecutive True points spanning less than ``min_len`` pixels
    of the polyline ``P`` (N,2) set False."""
    out = found.copy()
    s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(P, axis=0), axis=1))]
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


def snap_strokes(image, strokes, **options) -> list:
    """:func:`snap_stroke` for each stroke of one image (its gradients and noise computed once, on the part
    of the image around the strokes). ``strokes``: list of (N,2) pixel arrays; ``options``: those of
    :func:`snap_stroke`. Returns a list of :class:`SnapResult`, one per
    stroke, in order."""
    options = dict(options)
    quantum = options.setdefault("quantum", 1.0 / 255.0)
    strokes = [np.asarray(p, dtype=np.float64).reshape(-1, 2) for p in strokes]
    img = grey(image)
    H, W = img.shape
    sigma = float(options.get("sigma", 1.0))
    reach = float(options.get("search_px", SEARCH_PX)) + 4 * sigma + 4
    pts = np.vstack([p for p in strokes if len(p)]) if any(len(p) for p in strokes) else np.zeros((0, 2))
    if len(pts) == 0:
        return [snap_stroke(img, p, **options) for p in strokes]
    x0, y0 = (max(int(np.floor(v - reach)), 0) for v in pts.min(0))
    x1, y1 = min(int(np.ceil(pts[:, 0].max() + reach)), W), min(int(np.ceil(pts[:, 1].max() + reach)), H)
    if x1 <= x0 or y1 <= y0:  # the strokes are off the image: nothing to snap to
        return [SnapResult(p.copy(), np.zeros(len(p)), np.zeros(len(p), bool)) for p in strokes]
    crop = img[y0:y1, x0:x1]
    prepared = _gradients(crop, sigma)
    if options.get("noise") is None:
        options = dict(options, noise=image_noise(crop, quantum))
    off = np.array([x0, y0], dtype=np.float64)
    out = []
    for p in strokes:
        r = snap_stroke(crop, p - off, prepared=prepared, **options)
        out.append(SnapResult(r.points + off, r.offsets, r.snapped, r.polarity))
    return out
