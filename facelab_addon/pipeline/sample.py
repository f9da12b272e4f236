"""Load Sample: the shipped sample shot as a new scene, ready for the whole FaceLab route.

:func:`load_sample` reads ``assets/sample/`` (:mod:`facelab_addon.blender.sample`), creates a new
scene ``FaceLab Sample`` (the artist's scenes are not touched), builds the face with its 48-frame
captured performance (expression shape keys plus the capture's inner-lip error, keyed), the camera
and lights, and loads the plate frames behind the camera with :func:`facelab_addon.pipeline.plate.
load_plate`. No FaceLab region groups or keys are made: the sample starts where a real shot starts
(Auto Regions, sketch, Refine, Propagate). Works without network and without the ICT-FaceKit
checkout.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import bpy

from ..assets import asset_path
from ..blender.sample import ERROR_KEY, PLATE_DIR, build_sample, read_sample
from .plate import PlateSettings, load_plate
from .settings import setting

__all__ = ["SampleSettings", "SampleResult", "load_sample"]


@dataclass
class SampleSettings:
    """What :func:`load_sample` builds.

    Attributes
    ----------
    plate : bool
        Load the plate frames behind the camera.
    scene_name : str
        Name of the new scene (Blender adds ``.001`` if taken).
    """

    plate: bool = setting(True, label="With Plate",
                          description="Load the sample's footage behind the camera (48 JPEG frames)")
    scene_name: str = "FaceLab Sample"


@dataclass
class SampleResult:
    """What :func:`load_sample` made.

    Attributes
    ----------
    scene : bpy.types.Scene
        The new scene.
    face, camera : bpy.types.Object
    clip : str or None
        The plate's Movie Clip.
    frames : tuple of int
        First and last frame of the performance.
    vertices : int
    error_key : str
        The shape key holding the capture's lip error (mute it to see the truth).
    seconds : float
    """

    scene: object
    face: object
    camera: object
    clip: str | None
    frames: tuple
    vertices: int
    error_key: str = ERROR_KEY
    seconds: float = 0.0


def load_sample(settings: SampleSettings | None = None) -> SampleResult:
    """Build the sample shot in a new scene.

    Parameters
    ----------
    settings : SampleSettings, optional

    Returns
    -------
    SampleResult

    Raises
    ------
    AssetError
        A sample file is missing or broken (checked before anything is created).
    """
    settings = settings or SampleSettings()
    t0 = time.perf_counter()
    data = read_sample()
    plate = asset_path(*PLATE_DIR, "plate_0001.jpg") if settings.plate else None
    scene = bpy.data.scenes.new(settings.scene_name)
    made = build_sample(scene, data)
    clip = None
    if plate is not None:
        r = load_plate(scene, plate, PlateSettings(frame_start=int(data.frames[0]), match_fps=False),
                       camera=made["camera"])
        clip = r.clip
    return SampleResult(scene=scene, face=made["face"], camera=made["camera"], clip=clip,
                        frames=(int(data.frames[0]), int(data.frames[-1])), vertices=len(data.vertices),
                        seconds=time.perf_counter() - t0)
