"""One reading of scene time for every reader and writer of frames.

FaceLab reads the capture on scene frames (the evaluated mesh, a Mesh Cache's file, the shape keys'
F-curves) and writes corrections keyed on scene frames. Blender plays a frame ``f`` at the animation
time ``f * frame_map_old / frame_map_new`` (Output > Frame Range > Time Stretching), so with Time
Stretching on, the frames FaceLab reads and the keys it writes would land on other frames than the ones
Blender shows (some readers follow the stretch, F-curves read directly do not). FaceLab refuses it:
:func:`require_scene_time` is checked by every pipeline that reads or writes frames before it changes
anything, and by the frame readers (``blender.caches``) and key writers (``blender.shapekeys``) themselves.

Siblings handled here too: a shape-key datablock in NLA tweak mode (its action plays in the strip's
time: keys written on scene frames would land elsewhere, :func:`require_key_time`). Subframes are not
refused: readers set whole frames (``scene.frame_set(frame)`` resets the subframe).
"""

from __future__ import annotations

import bpy

from ..core.errors import FaceLabError

__all__ = ["SceneTimeError", "time_stretch", "require_scene_time", "require_key_time"]


class SceneTimeError(FaceLabError):
    """The scene plays its frames at another animation time than their numbers (Time Stretching, NLA tweak)."""


def time_stretch(scene) -> float:
    """Blender's animation time per scene frame, ``render.frame_map_old / render.frame_map_new`` (1 without
    Time Stretching)."""
    r = scene.render
    return float(r.frame_map_old) / float(r.frame_map_new)


def require_scene_time(scene, what: str = "FaceLab", obj=None) -> None:
    """Refuse a scene whose frames are not played at their own time, before anything is read or written.

    Parameters
    ----------
    scene : bpy.types.Scene or None
        None: the context's scene.
    what : str
        The step asking, for the message (``"Propagate"``).
    obj : bpy.types.Object, optional
        The face: its shape keys are checked too (:func:`require_key_time`).

    Raises
    ------
    SceneTimeError
        Time Stretching is on (Old != New), naming both values and the fix.
    """
    scene = scene if scene is not None else bpy.context.scene
    r = scene.render
    if r.frame_map_old != r.frame_map_new:
        raise SceneTimeError(
            f"{what}: scene '{scene.name}' uses Time Stretching (Output properties > Frame Range > Time "
            f"Stretching, Old {r.frame_map_old} / New {r.frame_map_new}): Blender shows on frame F the animation "
            f"of frame F x {r.frame_map_old}/{r.frame_map_new}, so the frames FaceLab reads and the keys it "
            "writes would not be the ones you see. Set Old and New to the same value while you correct (retime "
            "the shot with an NLA strip's Scale or the Mesh Cache's Frame Scale instead), then run again."
        )
    if obj is not None:
        require_key_time(obj, what)


def require_key_time(obj, what: str = "FaceLab") -> None:
    """Refuse a face whose shape-key animation is in NLA tweak mode (its action plays in a strip's time).

    Raises
    ------
    SceneTimeError
        Naming the object and the fix (leave tweak mode).
    """
    data = getattr(obj, "data", None)
    key = getattr(data, "shape_keys", None)
    ad = getattr(key, "animation_data", None)
    if ad is not None and ad.use_tweak_mode:
        raise SceneTimeError(
            f"{what}: the shape keys of '{obj.name}' are in NLA tweak mode (an NLA strip's action is being "
            "edited, played in the strip's own time), so keys written on scene frames would land on other "
            "frames. Leave tweak mode (Tab in the NLA editor, or Stop Tweaking Strip Actions), then run again."
        )
