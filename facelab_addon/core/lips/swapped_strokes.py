"""Lip strokes drawn on each other's layer: the upper-lip contour on the lower lip's layer and back.

An open mouth's inner contours bound a lens in the image: the upper one arches up, the lower one sags down,
and the upper lies above the lower. Strokes on swapped layers turn that lens over while the captured face's
lips are apart; Refine Lips would then pull each lip onto the other's contour (the lips several times worse
than the capture). :func:`check_swapped_strokes` refuses such a sketch; pixels throughout (image y down).

Correct strokes cross too: sealed or pressed lips seen from well above or below (a helmet camera), or a pucker,
overlap in the image along the whole mouth, so their inner contours cross in a band of nearly even width, while
the capture being corrected may hold the lips apart there. Such a band is no upside-down lens: the swapped lens
closes at the mouth corners, so its crossing is deepest in the middle by about its whole depth
(:data:`LENS_CLOSING`), where the even band's hardly changes. A shallow lens (its depth under :data:`SURE_DEPTH`
of the mouth's width) is no proof either way: lips overlapping a little in the middle of the mouth and meeting
at the corners (seen from above or below) draw it too, so it is refined as drawn with a warning.
"""

from __future__ import annotations

import numpy as np

from ..errors import SketchError
from ..geometry.polyline import y_at

__all__ = ["LENS_CLOSING", "SURE_DEPTH", "SWAP_SHARE", "check_swapped_strokes"]


def _sag(P) -> float:
    """How far (pixels, image y down) a stroke's middle column lies below the line between its two ends."""
    ends = P[[int(np.argmin(P[:, 0])), int(np.argmax(P[:, 0]))]]
    return float(y_at(np.array([ends[:, 0].mean()]), P)[0] - ends[:, 1].mean())


#: Share of the mouth's width over which the upper stroke must lie below the lower one (by at least a quarter of
#: the captured lips' gap there) for :func:`check_swapped_strokes` to call the layers swapped.
SWAP_SHARE = 0.6

#: How much of the crossing's depth (its 90th percentile over the columns, pixels) the strokes' upside-down lens must
#: close by toward their ends (the upper stroke's sag below its ends minus the lower one's) for
#: :func:`check_swapped_strokes` to call the layers swapped: strokes of an open mouth drawn on swapped layers meet
#: at the corners (about 1), lips overlapping in the image along the whole mouth cross in an even band (about 0).
LENS_CLOSING = 0.7

#: Share of the mouth's width (the strokes' span) the swapped-looking lens must be deep (the crossing's 90th
#: percentile) for :func:`check_swapped_strokes` to refuse the sketch; a shallower one only warns (the lips may
#: overlap that much in the image).
SURE_DEPTH = 0.05


def check_swapped_strokes(upper, lower, yu, yl, x, where: str = "") -> str:
    """Refuse a sketch whose upper and lower strokes look drawn on each other's layer; warn when it may be.

    Parameters
    ----------
    upper, lower : (N,2), (M,2) float
        The strokes as drawn (resampled), pixels (image y down).
    yu, yl : (K,) float
        The captured upper lip's lowest and lower lip's highest silhouette at columns ``x`` (K,)
        (``core.lips.views``), NaN where none.
    x : (K,) float
        Image columns across the span both strokes cover.
    where : str
        Names the view in messages.

    Returns
    -------
    str
        Empty, or a warning when the sketch looks swapped but its lens is shallower than :data:`SURE_DEPTH` of the
        mouth's width (the lips may overlap that much in this view): the sketch is then read as drawn.

    Raises
    ------
    SketchError
        When, over at least :data:`SWAP_SHARE` of the columns, the upper stroke lies below the lower one by
        more than a quarter of the captured lips' gap (and 2 px), the captured lips are apart there (not
        overlapping in this view, where a crossing drawing may be a real overlap), and the strokes lie
        less than half as far (median) from the other lip's silhouette as from their own, and the two strokes
        bound an upside-down lens (the upper stroke's middle sags below its ends more than the lower one's,
        by a quarter of the gap and by :data:`LENS_CLOSING` of the crossing's depth: an open mouth's upper inner
        contour arches up, the lower sags down, and the two meet at the corners): what a sketch on swapped layers
        looks like. A crossing drawn on purpose (one lip in front of the other) keeps the lens's orientation, and
        lips overlapping in the image along the whole mouth (sealed lips seen from well above or below) cross in
        a band of even width that closes toward neither corner: both are read as drawn. A lens shallower than
        :data:`SURE_DEPTH` of the mouth's width only warns.
    """
    su, sl = y_at(x, upper), y_at(x, lower)
    ok = np.isfinite(su) & np.isfinite(sl) & np.isfinite(yu) & np.isfinite(yl)
    if ok.sum() < 10:
        return ""
    su, sl, yu, yl = su[ok], sl[ok], yu[ok], yl[ok]
    gap = yl - yu  # > 0: the captured lips are apart in the image
    cross = su - sl  # > 0: the upper stroke below the lower one
    if not np.median(gap) > 0:
        return ""
    crossed = cross > np.maximum(2.0, 0.25 * gap)
    as_drawn = np.median(np.abs(su - yu) + np.abs(sl - yl))
    swapped = np.median(np.abs(su - yl) + np.abs(sl - yu))
    # an open mouth's inner contours bound a lens: the upper arches up, the lower sags down (image y down)
    # ... which, upside down, closes toward the corners by about the crossing's whole depth (an even band does not)
    lens = _sag(lower) - _sag(upper)
    depth = float(np.percentile(cross, 90))
    if (crossed.mean() >= SWAP_SHARE and swapped < 0.5 * as_drawn
            and lens < -max(2.0, 0.25 * np.median(gap), LENS_CLOSING * depth)):
        width = float(np.ptp(np.concatenate([upper[:, 0], lower[:, 0]])))
        said = (f"The upper-lip stroke{where} lies below the lower-lip stroke over {100 * crossed.mean():.0f} % of "
                "the mouth, while the face's lips are apart there")
        if depth < SURE_DEPTH * width:
            return (f"{said}, by up to {depth:.0f} px: the lips overlap there in this view, or the strokes are on "
                    "swapped layers (the upper lip on 'Lower lip'). Refined as drawn; if swapped, undo, move each "
                    "stroke to its layer and refine again.")
        raise SketchError(
            f"{said}: the strokes look drawn on swapped layers (the upper lip on 'Lower lip'). Move each stroke to "
            "its layer (or swap the two layers' names) and refine again."
        )
    return ""
