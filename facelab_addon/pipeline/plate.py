"""Load Plate: real footage behind the scene camera, the scene matched to it, ready to sketch over.

:func:`load_plate` checks the footage, loads it as a new Movie Clip, adds it as a new background
image of the camera (existing backgrounds stay), matches the scene's frame range, frame rate and
render resolution to the clip, and takes the lens from the clip's tracking camera when one is set
(a solved camera, or a focal length / sensor the artist entered; see
:func:`facelab_addon.blender.plate.clip_lens_is_set`). Everything is checked before the scene
changes.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

from ..blender import plate as plate_io
from ..core.errors import CameraError
from .settings import setting

__all__ = ["PlateSettings", "PlateResult", "load_plate"]


@dataclass
class PlateSettings:
    """What :func:`load_plate` matches to the footage.

    Attributes
    ----------
    match_frame_range, match_fps, match_resolution : bool
        Set the scene's frame range / frame rate / render resolution from the clip.
    lens_from_clip : bool
        Take the camera's lens, sensor and shift from the clip's tracking camera when it is set.
    frame_start : int
        The scene frame that shows the footage's first frame.
    alpha : float
        Opacity of the background image, 0..1.
    """

    match_frame_range: bool = setting(True, label="Match Frame Range",
                                      description="Set the scene's start and end frame to the footage's frames")
    match_fps: bool = setting(True, label="Match Frame Rate",
                              description="Set the scene's frame rate to the movie's (image sequences have none)")
    match_resolution: bool = setting(True, label="Match Resolution",
                                     description="Set the render resolution to the footage's size in pixels, at 100 %")
    lens_from_clip: bool = setting(True, label="Lens from Clip",
                                   description="Take the camera's focal length, sensor and shift from the clip's "
                                               "tracking camera when it is set (solved or entered)")
    frame_start: int = setting(1, label="Start Frame", unit="frames",
                               description="The scene frame that shows the footage's first frame")
    alpha: float = setting(1.0, label="Opacity", min=0.0, max=1.0,
                           description="Opacity of the plate in camera view, 0 to 1")


@dataclass
class PlateResult:
    """What :func:`load_plate` did.

    Attributes
    ----------
    clip : str
        The new Movie Clip's name.
    camera : str
        The camera that shows it.
    info : ClipInfo
        Size, frames, frame rate and source of the footage.
    backgrounds : int
        Background images on the camera now (the plate is the last).
    reused : bool
        The clip was already loaded (its start frame and tracking data are kept).
    changed : dict
        Scene settings set: ``frame_range``, ``fps``, ``resolution``, ``lens`` (see
        :func:`facelab_addon.blender.plate.match_scene_to_clip` / ``lens_from_clip``).
    skipped : list of str
        What was not matched, and why.
    seconds : float
    """

    clip: str
    camera: str
    info: object
    backgrounds: int
    reused: bool = False
    changed: dict = field(default_factory=dict)
    skipped: list = field(default_factory=list)
    seconds: float = 0.0


def load_plate(scene, filepath=None, settings: PlateSettings | None = None, *, clip=None, camera=None) -> PlateResult:
    """Put footage behind the camera and match the scene to it.

    Parameters
    ----------
    scene : bpy.types.Scene
    filepath : str or Path, optional
        A movie, one image of a numbered sequence (the sequence runs from it), or a folder of images.
        When a Movie Clip of this file is already loaded, that clip is used (with its tracking
        camera) instead of loading a second copy.
    settings : PlateSettings, optional
    clip : bpy.types.MovieClip, optional
        Use this loaded clip instead of a file (for footage already tracked in Blender).
    camera : bpy.types.Object, optional
        Default: the scene camera.

    Returns
    -------
    PlateResult

    Raises
    ------
    PlateError
        The footage is missing, not a movie/image format, or cannot be decoded.
    CameraError
        There is no camera to put the plate behind.
    """
    settings = settings or PlateSettings()
    t0 = time.perf_counter()
    cam_obj = camera if camera is not None else scene.camera
    if cam_obj is None or getattr(cam_obj, "type", None) != "CAMERA":
        raise CameraError("Load Plate puts the footage behind the scene camera, and the scene has none; add the "
                          "camera the footage was shot with (Add > Camera) and make it the scene camera.")
    reused = clip is not None
    if clip is None:
        path = plate_io.check_footage(filepath)
        clip = plate_io.loaded_clip(path)
        reused = clip is not None
        if clip is None:
            clip = plate_io.load_clip(path, frame_start=settings.frame_start)
    info = plate_io.clip_info(clip)
    bg = plate_io.add_clip_background(cam_obj, clip, alpha=settings.alpha)
    del bg
    if scene.active_clip is None:
        scene.active_clip = clip
    changed = plate_io.match_scene_to_clip(scene, clip, frame_range=settings.match_frame_range,
                                           fps=settings.match_fps, resolution=settings.match_resolution)
    skipped = []
    if settings.match_fps and "fps" not in changed:
        skipped.append(f"frame rate: an image sequence has none, the scene keeps {scene.render.fps} fps")
    if settings.lens_from_clip:
        if plate_io.clip_lens_is_set(clip):
            changed["lens"] = plate_io.lens_from_clip(cam_obj, clip, scene)
        else:
            skipped.append("lens: the clip's tracking camera is not set (Blender's 24 mm default), the camera "
                           "keeps its own")
    return PlateResult(clip=clip.name, camera=cam_obj.name, info=info, backgrounds=len(cam_obj.data.background_images),
                       reused=reused, changed=changed, skipped=skipped, seconds=time.perf_counter() - t0)
