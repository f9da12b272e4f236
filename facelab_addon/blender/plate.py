"""Camera plates: footage as a Movie Clip behind the scene camera, and the scene matched to it.

What an artist does by hand before sketching over real footage, as adapters:

* :func:`check_footage` -- is the file (a movie, or one image of a numbered sequence) there and in
  a format Blender reads; a folder means its first image;
* :func:`load_clip` -- load it as a Movie Clip and check Blender could decode it
  (:func:`loaded_clip`: the clip of that file already in the scene, with its tracking data);
* :func:`add_clip_background` -- add the clip as a *new* background image of a camera (camera
  view), keeping the backgrounds already there;
* :func:`match_scene_to_clip` -- the scene's frame range, frame rate and render resolution from the
  clip;
* :func:`clip_lens_is_set` / :func:`lens_from_clip` -- the lens, sensor, principal point (shift) and
  pixel aspect from the clip's tracking camera, the way Blender's *Setup Tracking Scene* sets them;
* :func:`plate_file` / :func:`plate_pixels` -- the footage file a camera's plate shows on a scene frame
  and its pixels (an image sequence as a Movie Clip or as an Image, or a still image).

Conventions: the clip's tracking camera stores the focal length in millimetres for a sensor width
in millimetres along the footage's width, and the principal point in footage pixels from the
bottom-left corner; the Blender camera gets horizontal sensor fit so that holds for portrait
footage too (``blender.camera`` explains how Blender maps a camera to pixels).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import bpy
import numpy as np

from ..core.errors import CameraError, FaceLabError

__all__ = ["PlateError", "ClipInfo", "footage_extensions", "check_footage", "load_clip", "loaded_clip", "clip_info",
           "add_clip_background", "match_scene_to_clip", "clip_lens_is_set", "lens_from_clip", "plate_file",
           "plate_pixels", "shown_footage"]

#: Focal length (mm) and sensor width (mm) Blender gives the tracking camera of a freshly loaded clip.
BLENDER_DEFAULT_LENS = (24.0, 35.0)


class PlateError(FaceLabError):
    """The footage is missing, in a format Blender cannot read, or unreadable."""


@dataclass
class ClipInfo:
    """What a loaded Movie Clip holds.

    Attributes
    ----------
    name : str
    filepath : str
    source : str
        ``"MOVIE"`` or ``"SEQUENCE"``.
    width, height : int
        Footage size, pixels.
    frames : int
        Number of frames.
    fps : float
        The movie's frame rate; 0 for an image sequence (it has none).
    frame_start : int
        The scene frame that shows the footage's first frame.
    """

    name: str
    filepath: str
    source: str
    width: int
    height: int
    frames: int
    fps: float
    frame_start: int


def footage_extensions() -> tuple[set, set]:
    """``(movie, image)`` file extensions (lower case, with the dot) this Blender reads."""
    return set(bpy.path.extensions_movie), set(bpy.path.extensions_image)


def _first_image(folder: Path) -> Path:
    _, images = footage_extensions()
    files = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in images)
    if not files:
        raise PlateError(f"The folder {str(folder)!r} holds no image Blender reads; pick a movie file or the "
                         f"first image of a numbered sequence ({', '.join(sorted(images)[:8])}, ...).")
    numbered = [p for p in files if re.search(r"\d+$", p.stem)]
    return (numbered or files)[0]


def check_footage(filepath) -> Path:
    """The footage file to load, checked: it exists and Blender reads its format.

    Parameters
    ----------
    filepath : str or Path
        A movie (``.mp4``, ``.mov``, ...), one image of a numbered sequence (``plate_0001.png``; the
        sequence runs from it), or a folder (its first image, sorted by name).

    Returns
    -------
    Path
        The file to give :func:`load_clip`.

    Raises
    ------
    PlateError
        The path is empty or missing, the folder has no image, or the extension is not a movie or
        image format of this Blender (the message lists the ones it reads).
    """
    if not str(filepath or "").strip():
        raise PlateError("No footage given; pick a movie file or the first image of an image sequence.")
    path = Path(bpy.path.abspath(str(filepath)))
    if path.is_dir():
        path = _first_image(path)
    if not path.exists():
        raise PlateError(f"The footage {str(path)!r} does not exist; check the path (a sequence is picked by "
                         "its first image, e.g. plate_0001.png).")
    movies, images = footage_extensions()
    ext = path.suffix.lower()
    if ext not in movies and ext not in images:
        raise PlateError(f"{path.name!r} is not footage Blender reads ({ext or 'no extension'}); convert it to a "
                         f"movie ({', '.join(sorted(movies)[:6])}, ...) or an image sequence "
                         f"({', '.join(sorted(images)[:6])}, ...).")
    return path


def load_clip(filepath, *, frame_start: int | None = None):
    """Load footage as a new Movie Clip and check Blender could decode it.

    Parameters
    ----------
    filepath : str or Path
        Checked with :func:`check_footage` first.
    frame_start : int, optional
        The scene frame showing the footage's first frame (default: Blender's, 1).

    Returns
    -------
    bpy.types.MovieClip
        A new clip (an already loaded clip of the same file is not reused, so its settings and
        tracks stay as they are).

    Raises
    ------
    PlateError
        As :func:`check_footage`, or the file could not be decoded (no frames); nothing is left in
        ``bpy.data`` then.
    """
    path = check_footage(filepath)
    try:
        clip = bpy.data.movieclips.load(str(path), check_existing=False)
    except RuntimeError as e:
        raise PlateError(f"Blender cannot read {path.name!r} ({e}); re-export it as H.264 .mp4 or as PNG/JPEG "
                         "images.") from None
    if clip.frame_duration < 1 or min(clip.size) < 1:
        bpy.data.movieclips.remove(clip)
        raise PlateError(f"Blender could not decode any frame of {path.name!r}; the file is damaged or its codec is "
                         "not supported. Re-export it as H.264 .mp4 or as PNG/JPEG images.")
    if frame_start is not None:
        clip.frame_start = int(frame_start)
    return clip


def loaded_clip(path):
    """The Movie Clip already loaded from the file ``path``, or None."""
    target = Path(bpy.path.abspath(str(path))).resolve()
    for clip in bpy.data.movieclips:
        if clip.library is None and Path(bpy.path.abspath(clip.filepath)).resolve() == target:
            return clip
    return None


def clip_info(clip) -> ClipInfo:
    """The :class:`ClipInfo` of a Movie Clip."""
    W, H = (int(v) for v in clip.size)
    return ClipInfo(name=clip.name, filepath=clip.filepath, source=clip.source, width=W, height=H,
                    frames=int(clip.frame_duration), fps=float(clip.fps), frame_start=int(clip.frame_start))


def add_clip_background(cam_obj, clip, *, alpha: float = 1.0):
    """Add ``clip`` as a new background image of the camera, shown in camera view.

    Backgrounds already on the camera are kept (the new one is added last and drawn behind the
    scene). Returns the new ``CameraBackgroundImage``.

    Raises
    ------
    CameraError
        ``cam_obj`` is not a camera object.
    """
    if cam_obj is None or getattr(cam_obj, "type", None) != "CAMERA":
        raise CameraError("The plate goes behind a camera; set the scene camera (Scene properties > Camera) or "
                          "add one with Add > Camera.")
    cam = cam_obj.data
    bg = cam.background_images.new()
    bg.source = "MOVIE_CLIP"
    bg.clip = clip
    bg.use_camera_clip = False
    bg.alpha = float(alpha)
    bg.display_depth = "BACK"
    bg.frame_method = "FIT"
    cam.show_background_images = True
    return bg


def match_scene_to_clip(scene, clip, *, frame_range: bool = True, fps: bool = True, resolution: bool = True) -> dict:
    """Make the scene's frame range, frame rate and render resolution those of the clip.

    Parameters
    ----------
    scene : bpy.types.Scene
    clip : bpy.types.MovieClip
    frame_range, fps, resolution : bool
        What to match. An image sequence has no frame rate; the scene's is kept then.

    Returns
    -------
    dict
        What changed: ``{"frame_range": (start, end), "fps": float, "resolution": (W, H)}`` for the
        items set.
    """
    info = clip_info(clip)
    changed = {}
    if frame_range:
        scene.frame_start = info.frame_start
        scene.frame_end = info.frame_start + info.frames - 1
        changed["frame_range"] = (scene.frame_start, scene.frame_end)
    if fps and info.fps > 0:
        rate = max(1, round(info.fps))
        scene.render.fps = rate
        scene.render.fps_base = rate / info.fps
        changed["fps"] = scene.render.fps / scene.render.fps_base
    if resolution:
        r = scene.render
        r.resolution_x, r.resolution_y, r.resolution_percentage = info.width, info.height, 100
        changed["resolution"] = (info.width, info.height)
    return changed


def clip_lens_is_set(clip) -> bool:
    """Whether the clip's tracking camera holds a lens: it was solved, or its focal length or sensor
    width differ from what Blender gives a freshly loaded clip (:data:`BLENDER_DEFAULT_LENS`)."""
    tc = clip.tracking.camera
    if clip.tracking.reconstruction.is_valid:
        return True
    f0, s0 = BLENDER_DEFAULT_LENS
    return abs(tc.focal_length - f0) > 1e-4 or abs(tc.sensor_width - s0) > 1e-4


def lens_from_clip(cam_obj, clip, scene=None) -> dict:
    """Give the camera the lens of the clip's tracking camera.

    Sets the focal length and sensor width (horizontal fit), the shift for the principal point and,
    when ``scene`` is given, its pixel aspect; with the render resolution of the footage
    (:func:`match_scene_to_clip`) the camera then projects like the calibrated one.

    Returns
    -------
    dict
        ``lens_mm``, ``sensor_mm``, ``shift`` ``(x, y)`` and ``pixel_aspect``.

    Raises
    ------
    CameraError
        ``cam_obj`` is not a camera object.
    """
    if cam_obj is None or getattr(cam_obj, "type", None) != "CAMERA":
        raise CameraError("The lens goes to a camera; set the scene camera first.")
    tc = clip.tracking.camera
    W, H = (int(v) for v in clip.size)
    cam = cam_obj.data
    cam.type = "PERSP"
    cam.lens_unit = "MILLIMETERS"
    cam.sensor_fit = "HORIZONTAL"
    cam.sensor_width = float(tc.sensor_width)
    cam.lens = float(tc.focal_length)
    aspect = float(tc.pixel_aspect)  # fy / fx
    cx, cy = (float(v) for v in tc.principal_point_pixels)  # footage pixels, y up from the bottom
    cam.shift_x = (0.5 * W - cx) / W
    cam.shift_y = (0.5 * H - cy) / W / aspect  # in frame widths: a pixel row is 1/aspect of a column
    if scene is not None:
        r = scene.render
        r.pixel_aspect_x, r.pixel_aspect_y = (aspect, 1.0) if aspect >= 1.0 else (1.0, 1.0 / aspect)
    return dict(lens_mm=cam.lens, sensor_mm=cam.sensor_width, shift=(cam.shift_x, cam.shift_y), pixel_aspect=aspect)


# --------------------------------------------------------------------------- pixels of a frame
def _numbered(path: Path, number: int) -> Path:
    """``path`` with the last run of digits in its name replaced by ``number`` (same zero padding)."""
    m = list(re.finditer(r"\d+", path.stem))
    if not m:
        return path
    d = m[-1]
    stem = path.stem[:d.start()] + f"{number:0{len(d.group())}d}" + path.stem[d.end():]
    return path.with_name(stem + path.suffix)


def _first_number(path: Path) -> int:
    m = list(re.finditer(r"\d+", path.stem))
    return int(m[-1].group()) if m else 1


def plate_file(cam_obj, frame: int):
    """The footage file the camera's plate shows on scene ``frame``, or None when it has no plate.

    The first shown background image of the camera that is a Movie Clip or an Image: an image
    sequence (a clip of source ``SEQUENCE``, or an Image of source ``SEQUENCE`` with its image user's
    start frame and offset) gives the numbered file of that frame, a still image its file.

    Raises
    ------
    PlateError
        The plate is a movie shown as an Image (a Movie Clip is read through ``blender.sketch_snap``),
        or the frame's file is missing.
    """
    shown = shown_footage(cam_obj)
    if shown is None:
        return None
    bg, footage = shown
    first = Path(bpy.path.abspath(footage.filepath))
    if footage.source == "MOVIE" and bg.source == "IMAGE":
        raise PlateError(f"The plate {first.name!r} is a movie shown as a background Image, which is read at its "
                         "first frame only: load it as a Movie Clip (Load Plate does) or export it as PNG/JPEG "
                         "images (a numbered sequence) and load that as the plate.")
    if footage.source == "MOVIE":
        raise PlateError(f"The plate {first.name!r} is a movie file, which has no image file per frame: read its "
                         "frames with blender.sketch_snap.plate_image, or export it as PNG/JPEG images.")
    if bg.source == "MOVIE_CLIP":
        n = _first_number(first) + int(frame) - int(footage.frame_start) + int(footage.frame_offset)
        path = _numbered(first, n)
    elif footage.source == "SEQUENCE":
        path = _numbered(first, _image_user_number(bg.image_user, frame))
    else:
        path = first
    if not path.exists():
        raise PlateError(f"The plate has no image for frame {frame} ({str(path)!r}); check the footage's start "
                         "frame (the clip's Start Frame) or the missing file.")
    return path


def shown_footage(cam_obj):
    """``(background image, footage)`` of the camera's plate, or None: its first shown background image that
    holds a Movie Clip or an Image (``footage`` is that ``bpy.types.MovieClip`` or ``bpy.types.Image``)."""
    cam = getattr(cam_obj, "data", None)
    if cam is None or getattr(cam_obj, "type", None) != "CAMERA":
        return None
    for bg in cam.background_images:
        if not getattr(bg, "show_background_image", True):
            continue
        footage = bg.clip if bg.source == "MOVIE_CLIP" else bg.image if bg.source == "IMAGE" else None
        if footage is not None:
            return bg, footage
    return None


def _image_user_number(iu, frame: int) -> int:
    """The file number an image user shows on scene ``frame`` (Blender's ``BKE_image_user_frame_get``: from its
    start frame, held at its first / last frame outside its duration, or cycling, plus its offset)."""
    n = int(iu.frame_duration)
    if n < 1:
        return int(iu.frame_offset)
    c = int(frame) - int(iu.frame_start) + 1
    if iu.use_cyclic:
        c %= n
        c = n if c == 0 else c
    return min(max(c, 0), n) + int(iu.frame_offset)


_PIXELS_CACHE = {}


def plate_pixels(path) -> np.ndarray:
    """(H,W,C) float32 pixels of an image file, row 0 at the top, as Blender reads it (0..1 for 8-bit
    footage). The last file read is kept (a live sketch snaps to the same plate stroke after stroke)."""
    path = Path(path)
    key = (str(path), path.stat().st_mtime_ns)
    if key in _PIXELS_CACHE:
        return _PIXELS_CACHE[key]
    img = bpy.data.images.load(str(path), check_existing=False)
    try:
        W, H = (int(v) for v in img.size)
        ch = int(img.channels)
        if W < 1 or H < 1:
            raise PlateError(f"Blender could not read {path.name!r}; re-export the plate as PNG or JPEG.")
        px = np.empty(W * H * ch, np.float32)
        img.pixels.foreach_get(px)
    finally:
        bpy.data.images.remove(img)
    out = px.reshape(H, W, ch)[::-1].copy()  # Blender's rows run bottom-up
    _PIXELS_CACHE.clear()
    _PIXELS_CACHE[key] = out
    return out
