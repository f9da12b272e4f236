"""Frame ranges every pipeline shares: the scene's range unless one is given, checked before any work.

Negative frames are ordinary Blender frames and are honoured; ``None`` (not -1) means "the
scene's start / end". A range must not end before it starts and must lie within Blender's
frame limits (+-1,048,574), so a typo fails with a message instead of an ``IndexError`` or an
allocation of millions of frames.
"""

from __future__ import annotations

import numpy as np

from ..core.errors import FaceLabError

__all__ = ["MAX_FRAME", "frame_range", "check_frames"]

#: Largest frame number Blender accepts (``MAXFRAME``); the smallest is ``-MAX_FRAME``.
MAX_FRAME = 1048574


def frame_range(scene, frame_start: int | None = None, frame_end: int | None = None, what: str = "FaceLab"
                ) -> np.ndarray:
    """(T,) int64 frames ``frame_start..frame_end`` inclusive (None: the scene's start / end).

    Parameters
    ----------
    scene : bpy.types.Scene
        Gives the range ends that are None.
    frame_start, frame_end : int or None
        Scene frames; negative frames are legal.
    what : str
        The step asking, for the message (e.g. ``"Propagate"``).

    Raises
    ------
    FaceLabError
        End before Start, or a frame outside Blender's limits.
    """
    f0 = scene.frame_start if frame_start is None else int(frame_start)
    f1 = scene.frame_end if frame_end is None else int(frame_end)
    if f1 < f0:
        raise FaceLabError(f"{what}: the frame range {f0}-{f1} ends before it starts; set End >= Start "
                           f"(for example {f1}-{f0}).")
    for f in (f0, f1):
        if abs(f) > MAX_FRAME:
            raise FaceLabError(f"{what}: frame {f} is outside Blender's frames (-{MAX_FRAME} to {MAX_FRAME}); "
                               "choose a range within them.")
    return np.arange(f0, f1 + 1, dtype=np.int64)


def check_frames(frames, what: str = "FaceLab", *, consecutive: bool = False) -> np.ndarray:
    """``frames`` as a (T,) int64 array, if it is a usable list of scene frames.

    Parameters
    ----------
    frames : (T,) int array_like
    what : str
        The step asking, for the message.
    consecutive : bool
        Require ``frames[i+1] == frames[i] + 1`` (a range such as 1-250).

    Raises
    ------
    FaceLabError
        No frames, frames not increasing (a reversed range), gaps where a range is needed,
        non-integer frames or frames outside Blender's limits.
    """
    a = np.asarray(frames)
    if a.ndim != 1 or not len(a):
        raise FaceLabError(f"{what}: no frames to work on; give a frame range such as 1-250 (End >= Start).")
    if not np.issubdtype(a.dtype, np.integer):
        if not np.issubdtype(a.dtype, np.floating) or not np.all(np.isfinite(a)) or np.any(a != np.round(a)):
            raise FaceLabError(f"{what}: frames must be whole numbers; give a frame range such as 1-250.")
    a = a.astype(np.int64)
    if np.any(np.abs(a) > MAX_FRAME):
        raise FaceLabError(f"{what}: frames outside Blender's frames (-{MAX_FRAME} to {MAX_FRAME}); choose a range "
                           "within them.")
    step = np.diff(a)
    if np.any(step <= 0):
        raise FaceLabError(f"{what}: the frames {int(a[0])}..{int(a[-1])} are not increasing (a reversed or repeated "
                           "range); give them from first to last, End >= Start.")
    if consecutive and np.any(step != 1):
        raise FaceLabError(f"{what}: the frames {int(a[0])}..{int(a[-1])} have gaps; give one consecutive range "
                           "such as 1-250.")
    return a
