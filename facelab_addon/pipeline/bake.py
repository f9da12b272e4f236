"""Bake: the corrected performance (capture + FaceLab's corrective keys) to a PC2, MDD or Alembic file
for other packages.

PC2 and MDD are written one frame a step by :func:`facelab_addon.blender.bakes.bake_point_cache_steps`
(cancelling leaves an existing file untouched); Alembic is one call of Blender's exporter
(:func:`facelab_addon.blender.bakes.bake_alembic`), a single step.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..blender import bakes, caches, correction_files, review
from ..blender.scene_time import require_scene_time
from ..core.errors import FaceLabError
from .settings import setting
from .steps import run_steps

__all__ = ["FORMATS", "BakeSettings", "BakeResult", "bake_steps", "bake"]

#: Bake formats and their file extensions.
FORMATS = {"PC2": ".pc2", "MDD": ".mdd", "ABC": ".abc"}


@dataclass
class BakeSettings:
    """How :func:`bake` writes.

    Attributes
    ----------
    format : {"PC2", "MDD", "ABC"}
    overwrite : bool
        Replace an existing file (otherwise refuse).
    """

    format: str = setting("PC2", label="Format", description="File format of the baked point cache",
                          choices=(("PC2", "PC2", "Point cache 2 (Mesh Cache modifier)"),
                                   ("MDD", "MDD", "Lightwave MDD (Mesh Cache modifier)"),
                                   ("ABC", "Alembic", "Alembic (Mesh Sequence Cache modifier)")))
    overwrite: bool = setting(False, label="Overwrite", description="Replace an existing file (otherwise refuse)")


@dataclass
class BakeResult:
    """What :func:`bake` wrote.

    Attributes
    ----------
    object : str
    path : pathlib.Path
        The file written.
    format : str
    frames : int
        Number of frames baked.
    seconds : float
        From the call to the last step.
    """

    object: str
    path: Path
    format: str
    frames: int
    seconds: float = 0.0


def bake(obj, frames, path, settings: BakeSettings | None = None, progress=None) -> BakeResult:
    """Bake the evaluated (corrected) mesh of ``obj`` over ``frames`` to ``path``; runs :func:`bake_steps`.

    Parameters
    ----------
    obj : bpy.types.Object
    frames : (T,) int array_like
        Scene frames (PC2: evenly spaced; MDD: increasing; Alembic: the whole range they span).
    path : str or os.PathLike
        Destination, an absolute path (or ``//``-relative to the saved .blend).
    settings : BakeSettings, optional
    progress : callable(label, done, total), optional

    Returns
    -------
    BakeResult
    """
    return run_steps(bake_steps(obj, frames, path, settings), progress)


def bake_steps(obj, frames, path, settings: BakeSettings | None = None):
    """The bake as a generator of steps (one per frame for PC2 / MDD) returning a :class:`BakeResult`.

    The input is checked by this call, before any file is opened.

    Raises
    ------
    FaceLabError
        Review shows the capture on ``obj`` (*Show Capture*), no destination, the file exists and
        ``settings.overwrite`` is off, an unknown format, frames unfit for the format; ``MeshError`` when ``obj``
        is not a mesh object.
    OutputError
        A relative path, or a destination that cannot be written (a read-only
        folder, a parent that is a file): :func:`facelab_addon.blender.bakes.bake_destination`.
    CacheFileError
        A correction cache of ``obj`` is missing or broken (the .blend moved
        without it): :func:`facelab_addon.blender.correction_files.require_correction_caches`.
    """
    settings = settings or BakeSettings()
    t0 = time.perf_counter()
    if review.showing_capture(obj):
        raise FaceLabError(f"Review shows the capture on '{obj.name}' (Show Capture), so the bake would hold the "
                           "capture, not the corrected performance; click Show Corrected first.")
    if not path:
        raise FaceLabError("Choose a file to bake to.")
    if settings.format not in FORMATS:
        raise FaceLabError(f"Unknown bake format {settings.format!r}; choose one of {', '.join(FORMATS)}.")
    path = bakes.bake_destination(path)
    if path.exists() and not settings.overwrite:
        raise FaceLabError(f"{path} exists; enable Overwrite or choose another file.")
    frames = np.asarray(frames)
    caches.require_mesh_object(obj)
    require_scene_time(None, "Bake", obj)  # a baked cache would be played stretched again
    correction_files.require_correction_caches(obj, "Bake Corrected Sequence")  # never the capture baked as corrected
    if settings.format == "ABC":
        return _alembic_step(obj, frames, path, t0)
    steps = bakes.bake_point_cache_steps(obj, frames, path, settings.format)
    return _point_cache(steps, obj, frames, settings.format, t0)


def _point_cache(steps, obj, frames, fmt, t0):
    out = yield from steps
    return BakeResult(object=obj.name, path=out, format=fmt, frames=len(frames), seconds=time.perf_counter() - t0)


def _alembic_step(obj, frames, path, t0):
    yield "exporting Alembic", 0, 1
    out = bakes.bake_alembic(obj, frames, path)
    return BakeResult(object=obj.name, path=out, format="ABC", frames=len(frames), seconds=time.perf_counter() - t0)
