"""FaceLab arrays -> Blender Movie Clips with tracks (import side of Bhat et al. 2013, §4.1 inputs).

The inverse of :mod:`facelab_addon.blender.tracking`: turns tracked marker
pixels produced elsewhere (another tracker's export, a simulation) into what
Solve Performance reads -- a Movie Clip with one 2D track per marker and the
clip's camera calibration -- so a pipeline can import tracks without going
through Blender's own tracker.

* :func:`write_dot_plates` -- a stand-in image sequence (grey frames with the
  markers drawn as dots) when the footage is not at hand; Blender needs
  footage to create a Movie Clip;
* :func:`set_clip_calibration` -- a pinhole :class:`~facelab_addon.core.capture.camera.Camera`'s
  intrinsics as the clip's tracking camera;
* :func:`add_tracks` -- ``(T,M,2)`` pixels as tracks (NaN: disabled markers);
* :func:`clip_from_pixels` -- all of it at once.

Conventions are :mod:`~facelab_addon.blender.tracking`'s: FaceLab pixels
(top-left origin, y down) map to ``marker.co = (x / W, 1 - y / H)``; pixel row
``t`` is clip frame ``first_clip_frame + t``; scene frame ``f`` shows clip
frame ``f - clip.frame_start + 1``.
"""

from __future__ import annotations

from pathlib import Path

import bpy
import numpy as np

from ..core.errors import CameraError, FaceLabError

__all__ = ["write_dot_plates", "set_clip_calibration", "add_tracks", "clip_from_pixels"]


def _pixels(pixels) -> np.ndarray:
    P = np.asarray(pixels, dtype=np.float64)
    if P.ndim == 2 and P.shape[-1] == 2:
        P = P[:, None]
    if P.ndim != 3 or P.shape[-1] != 2 or P.shape[0] == 0:
        raise FaceLabError(
            f"Marker pixels must be an array (frames, markers, 2) of x, y pixels, got shape {P.shape}; "
            "reshape the tracker's export to one row per frame and one column per marker (NaN where untracked)."
        )
    return P


def write_dot_plates(directory, pixels, size, *, prefix: str = "plate", background=(92, 92, 96),
                     dot=(20, 20, 20), radius: float = 4.0) -> Path:
    """Write one PNG per frame: a flat background with the markers drawn as dots.

    Parameters
    ----------
    directory : str or Path
        Created if missing.
    pixels : (T,M,2) array_like
        Marker pixels (top-left origin, y down); NaN markers are not drawn.
    size : (W, H) int
        Image size, pixels.
    prefix : str
        Files are ``{prefix}_0001.png`` ... (frame numbers from 1, Blender's
        image-sequence convention).
    background, dot : (3,) int
        RGB 0..255.
    radius : float
        Dot radius, pixels.

    Returns
    -------
    Path
        The first frame's file (load it with ``bpy.data.movieclips.load``).
    """
    from PIL import Image, ImageDraw

    P = _pixels(pixels)
    W, H = (int(v) for v in size)
    if W <= 0 or H <= 0:
        raise FaceLabError(f"Plate size must be positive (width, height) pixels, got {size}.")
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    r = float(radius)
    for t in range(len(P)):
        img = Image.new("RGB", (W, H), tuple(background))
        dr = ImageDraw.Draw(img)
        for x, y in P[t]:
            if np.isfinite(x) and np.isfinite(y):
                dr.ellipse([x - r, y - r, x + r, y + r], fill=tuple(dot))
        img.save(d / f"{prefix}_{t + 1:04d}.png")
    return d / f"{prefix}_0001.png"


def set_clip_calibration(clip, camera, *, sensor_width: float = 36.0) -> None:
    """Set the clip's tracking camera (focal, principal point, pixel aspect) from a pinhole camera.

    Parameters
    ----------
    clip : bpy.types.MovieClip
    camera : core.capture.camera.Camera
        Its ``K`` (pixels) and ``width, height`` must match the clip's footage.
    sensor_width : float
        Sensor width, millimetres (the focal length in mm follows from it).

    Raises
    ------
    CameraError
        The footage size differs from the camera's image size.
    """
    W, H = (int(v) for v in clip.size)
    if (W, H) != (int(camera.width), int(camera.height)):
        raise CameraError(
            f"Movie Clip '{clip.name}' is {W}x{H} px but the camera's image is {camera.width}x{camera.height} px; "
            "load the footage the camera was calibrated for (or rescale the calibration to the footage)."
        )
    K = np.asarray(camera.K, dtype=np.float64)
    tc = clip.tracking.camera
    tc.sensor_width = float(sensor_width)
    tc.focal_length = float(K[0, 0] * sensor_width / W)
    tc.pixel_aspect = float(K[1, 1] / K[0, 0])
    tc.principal_point_pixels = (float(K[0, 2]), float(H - K[1, 2]))


def add_tracks(clip, pixels, *, names=None, first_clip_frame: int = 1) -> list:
    """Add one track per marker with a marker on every frame.

    Parameters
    ----------
    clip : bpy.types.MovieClip
    pixels : (T,M,2) array_like
        Pixels of the clip's footage (top-left origin, y down); row ``t`` is
        clip frame ``first_clip_frame + t``. NaN: the marker is added disabled
        (``mute``), which FaceLab and Blender's solver read as "not tracked".
    names : sequence of str, optional
        Track names (default ``M000``, ``M001``...); existing names get
        Blender's ``.001`` suffix.
    first_clip_frame : int

    Returns
    -------
    list of bpy.types.MovieTrackingTrack
    """
    P = _pixels(pixels)
    T, M, _ = P.shape
    names = [f"M{j:03d}" for j in range(M)] if names is None else list(names)
    if len(names) != M:
        raise FaceLabError(f"{len(names)} track names for {M} markers; give one name per marker column.")
    W, H = (int(v) for v in clip.size)
    if W <= 0 or H <= 0:
        raise CameraError(f"Movie Clip '{clip.name}' has no readable footage; check its file path.")
    ok = np.isfinite(P).all(axis=2)
    co = np.where(ok[..., None], np.stack([P[..., 0] / W, 1.0 - P[..., 1] / H], axis=-1), 0.0)
    f0 = int(first_clip_frame)
    tracks = []
    for j, n in enumerate(names):
        tr = clip.tracking.tracks.new(name=n, frame=f0)
        for t in range(1, T):
            tr.markers.insert_frame(f0 + t)
        tr.markers.foreach_set("co", co[:, j].astype(np.float32).ravel())
        tr.markers.foreach_set("mute", (~ok[:, j]).astype(bool))
        tracks.append(tr)
    return tracks


def clip_from_pixels(filepath, pixels, camera=None, *, names=None, scene_frame_start: int = 1, name=None):
    """Load footage as a Movie Clip and add the tracks (and the calibration).

    Parameters
    ----------
    filepath : str or Path
        The footage (a movie or the first image of a sequence, e.g. from
        :func:`write_dot_plates`).
    pixels : (T,M,2) array_like
        Marker pixels; row ``t`` is the footage's frame ``t + 1``.
    camera : core.capture.camera.Camera, optional
        Sets the clip's calibration (:func:`set_clip_calibration`).
    names : sequence of str, optional
    scene_frame_start : int
        The scene frame that shows the footage's first frame (the clip's
        Start Frame).
    name : str, optional
        The clip's name (default: the file's).

    Returns
    -------
    bpy.types.MovieClip
    """
    P = _pixels(pixels)
    path = Path(filepath)
    if not path.exists():
        raise FaceLabError(f"Footage {str(path)!r} does not exist; write the plates first (write_dot_plates).")
    clip = bpy.data.movieclips.load(str(path))
    if name:
        clip.name = name
    clip.frame_start = int(scene_frame_start)
    if clip.frame_duration < len(P):
        n = clip.frame_duration
        bpy.data.movieclips.remove(clip)
        raise FaceLabError(
            f"The footage {path.name!r} has {n} frames but the tracks have {len(P)}; give footage covering every "
            "tracked frame (an image sequence needs one numbered file per frame)."
        )
    if camera is not None:
        set_clip_calibration(clip, camera)
    add_tracks(clip, P, names=names, first_clip_frame=1)
    return clip
