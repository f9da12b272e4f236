"""Snap to plate, the adapter: the lip strokes read from a sketch, moved onto the edges of the plate its
camera shows on the frame (:func:`facelab_addon.core.lips.snap.snap_strokes`).

A sketch asks for it with the custom property :data:`~facelab_addon.names.SNAP_PROP` (all its strokes), a
stroke with the per-curve attribute :data:`~facelab_addon.names.SNAP_ATTR` of its drawing (+1 snapped,
-1 never, 0 as the sketch says: :func:`.strokes.stroke_snap_choices`, :func:`.strokes.set_stroke_snap`);
:func:`.strokes.read_lip_strokes` then returns the snapped strokes (the strokes drawn are never changed)
and writes what snapping did to :data:`~facelab_addon.names.SNAP_REPORT_PROP`. The plate is read with
:func:`plate_image`: image sequences (as a Movie Clip or an Image) and stills by
:func:`.plate.plate_file` / :func:`.plate.plate_pixels`, a movie file loaded as a Movie Clip by decoding its
frame with Blender's FFmpeg (:func:`movie_frame_pixels`).
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import bpy
import numpy as np

from ..core.capture.camera import Camera
from ..core.lips.snap import snap_lips
from .plate import PlateError, plate_file, plate_pixels, shown_footage

__all__ = ["movie_frame_pixels", "plate_image", "snap_to_plate"]


def snap_to_plate(cam_obj, camera: Camera, frame: int, strokes: dict, only=None, **options) -> tuple:
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
    only : dict, optional
        ``{"upper": [bool, ...], "lower": [...]}``: the strokes to snap (default all); the others are
        returned as drawn (they still tell where the other lip is).
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
        The plate has no image for the frame, or Blender cannot read it.
    """
    img = None if cam_obj is None else plate_image(cam_obj, frame)
    if img is None:
        return strokes, "not snapped: the camera shows no plate"
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
    out, moved, left, sealed = {}, 0, 0, 0
    for lab, res in snapped.items():
        use = [True] * len(res) if only is None else [bool(u) for u in only[lab]]
        out[lab] = [r.points / [sx, sy] if u else np.asarray(p) for r, p, u in zip(res, strokes[lab], use)]
        moved += sum(r.n_snapped for r, u in zip(res, use) if u)
        left += sum(r.n_left for r, u in zip(res, use) if u)
        sealed += sum(r.n_sealed for r, u in zip(res, use) if u)
    report = f"snapped {moved} of {moved + left} points to the plate"
    if left - sealed:
        report += f"; {left - sealed} left as drawn (no sharp lip edge within reach)"
    if sealed:
        report += f"; {sealed} left as drawn where the lips touch or overlap (sealed: no inner-lip edge)"
    return out, report


def _movie_clip(cam_obj):
    """The Movie Clip of a movie file the camera's plate shows (its first shown background image), or None."""
    shown = shown_footage(cam_obj)
    if shown is None:
        return None
    bg, footage = shown
    return footage if bg.source == "MOVIE_CLIP" and footage.source == "MOVIE" else None


def plate_image(cam_obj, frame: int):
    """(H,W,C) float32 pixels of the plate the camera shows on scene ``frame`` (row 0 at the top, 0..1 for
    8-bit footage), or None when it shows none. A movie file loaded as a Movie Clip is decoded at the clip's
    frame (its Start Frame and Frame Offset); image sequences and stills as :func:`.plate.plate_file` finds
    them.

    Raises
    ------
    PlateError
        The frame is outside the footage, or Blender cannot read it.
    """
    clip = _movie_clip(cam_obj)
    if clip is None:
        path = plate_file(cam_obj, frame)
        return None if path is None else plate_pixels(path)
    n = int(frame) - int(clip.frame_start) + 1 + int(clip.frame_offset)
    if not 1 <= n <= int(clip.frame_duration):
        raise PlateError(f"The plate {Path(clip.filepath).name!r} has no frame for scene frame {frame} (it has "
                         f"{int(clip.frame_duration)}); check the clip's Start Frame and Frame Offset.")
    return movie_frame_pixels(bpy.path.abspath(clip.filepath), n)


_MOVIE_CACHE = {}


def movie_frame_pixels(path, number: int) -> np.ndarray:
    """(H,W,C) float32 pixels of frame ``number`` (1 = the first) of a movie file, row 0 at the top, as
    stored (0..1; no view transform), decoded by Blender's FFmpeg through a temporary scene's Video
    Sequencer (removed again). The last frame read is kept.

    Raises
    ------
    PlateError
        Blender cannot decode the movie (a build without FFmpeg, or a broken file).
    """
    path = Path(path)
    key = (str(path), path.stat().st_mtime_ns if path.exists() else 0, int(number))
    if key in _MOVIE_CACHE:
        return _MOVIE_CACHE[key]
    if not path.exists():
        raise PlateError(f"The plate {path.name!r} is missing; load the footage again (Load Plate).")
    sc = bpy.data.scenes.new("FL_tmp_movie_frame")
    tmp = tempfile.mkdtemp(prefix="facelab-frame-")
    out = os.path.join(tmp, "frame.png")
    try:
        seq = sc.sequence_editor_create()
        strips = seq.strips if hasattr(seq, "strips") else seq.sequences
        try:
            strip = strips.new_movie("plate", str(path), 1, 1)
        except RuntimeError as e:
            raise PlateError(f"Blender could not decode the movie {path.name!r} ({e}); export it as PNG/JPEG images "
                             "(a numbered sequence) and load that as the plate.") from None
        W, H = int(strip.elements[0].orig_width), int(strip.elements[0].orig_height)
        if W < 1 or H < 1:
            raise PlateError(f"Blender could not decode the movie {path.name!r}; export it as PNG/JPEG images (a "
                             "numbered sequence) and load that as the plate.")
        r = sc.render
        r.resolution_x, r.resolution_y, r.resolution_percentage = W, H, 100
        r.use_sequencer = True
        r.image_settings.file_format = "PNG"
        r.filepath = out
        sc.view_settings.view_transform = "Standard"
        sc.view_settings.look = "None"
        sc.frame_start = sc.frame_end = sc.frame_current = int(number)
        with bpy.context.temp_override(scene=sc):
            bpy.ops.render.render(write_still=True, scene=sc.name)
        img = bpy.data.images.load(out, check_existing=False)
        try:
            ch = int(img.channels)
            px = np.empty(W * H * ch, np.float32)
            img.pixels.foreach_get(px)
        finally:
            bpy.data.images.remove(img)
    finally:
        bpy.data.scenes.remove(sc)
        if os.path.exists(out):
            os.remove(out)
        os.rmdir(tmp) if os.path.isdir(tmp) and not os.listdir(tmp) else None
    px = px.reshape(H, W, ch)[::-1].copy()
    _MOVIE_CACHE.clear()
    _MOVIE_CACHE[key] = px
    return px
