"""Snap to plate, the adapter: the lip strokes read from a sketch, moved onto the edges of the plate its
camera shows on the frame (:func:`facelab_addon.core.lips.snap.snap_strokes`).

A sketch asks for it with the custom property :data:`~facelab_addon.names.SNAP_PROP`;
:func:`.strokes.read_lip_strokes` then returns the snapped strokes (the strokes drawn are never changed)
and writes what snapping did to :data:`~facelab_addon.names.SNAP_REPORT_PROP`. The plate is read with
:func:`.plate.plate_file` / :func:`.plate.plate_pixels` (image sequences, as a Movie Clip or an Image, and
stills).
"""

from __future__ import annotations

import numpy as np

from ..core.capture.camera import Camera
from ..core.lips.snap import snap_lips
from .plate import plate_file, plate_pixels

__all__ = ["snap_to_plate"]


def snap_to_plate(cam_obj, camera: Camera, frame: int, strokes: dict, **options) -> tuple:
    """The lip strokes snapped onto the edges of the plate the sketch's camera shows on ``frame``.

    Parameters
    ----------
    cam_obj : bpy.types.Object or None
        The camera object the sketch was drawn through (its plate is read; None: no plate).
    camera : Camera
        That camera, in pixels of the render (the plate is scaled to them when its size differs).
    frame : int
    strokes : dict
        ``{"upper": [(N,2), ...], "lower": [...]}`` pixels, as :func:`read_lip_strokes` returns them.
    **options
        Of :func:`facelab_addon.core.lips.snap.snap_stroke` (``search_px`` in render pixels).

    Returns
    -------
    (dict, str)
        The snapped strokes (same layout; the input is not changed) and a report: how many points
        moved onto an edge, how many were left as drawn, or why nothing was snapped (no plate).

    Raises
    ------
    PlateError
        The plate is a movie file, or its image for the frame is missing.
    """
    path = None if cam_obj is None else plate_file(cam_obj, frame)
    if path is None:
        return strokes, "not snapped: the camera shows no plate"
    img = plate_pixels(path)
    H, W = img.shape[:2]
    sx, sy = W / camera.width, H / camera.height
    if abs(sx - sy) > 1e-3 * max(sx, sy):
        return strokes, (f"not snapped: the plate ({W}x{H}) has another aspect than the render "
                         f"({camera.width}x{camera.height})")
    opts = dict(options)
    if "search_px" in opts:
        opts["search_px"] = opts["search_px"] * sx
    scaled = {lab: [np.asarray(p) * [sx, sy] for p in strokes[lab]] for lab in ("upper", "lower")}
    snapped = dict(zip(("upper", "lower"), snap_lips(img, scaled["upper"], scaled["lower"], **opts)))
    out, moved, left = {}, 0, 0
    for lab, res in snapped.items():
        out[lab] = [r.points / [sx, sy] for r in res]
        moved += sum(r.n_snapped for r in res)
        left += sum(r.n_left for r in res)
    report = f"snapped {moved} of {moved + left} points to the plate"
    if left:
        report += f"; {left} left as drawn (no sharp lip edge within reach, or the lips touch there)"
    return out, report
