"""Helpers every FaceLab operator and panel shares: the face being worked on, the shared ``poll`` checks,
the frame range an operator was given, and a progress callback."""

import sys

import bpy

from ..blender.strokes import has_lip_sketch


def progress_callback(context, T, label="FaceLab"):
    """A ``progress(done, n)`` callback (``done`` items of ``n`` finished): the window's progress
    cursor, and in background mode (``blender -b``, the bpy module, the CLI) a line on stderr about
    every 10 %. Callers end it with ``context.window_manager.progress_end()``."""
    wm = context.window_manager
    wm.progress_begin(0, max(T, 1))
    last = [-1]

    def update(done, n=T):
        wm.progress_update(done)
        if bpy.app.background and n:
            pct = int(100 * done / n)
            if pct // 10 != last[0] // 10 or done == n:
                last[0] = pct
                print(f"{label}: {done}/{n} frames ({pct} %)", file=sys.stderr, flush=True)

    return update


def operator_range(op) -> tuple:
    """``(start, end)`` of an operator's ``frame_start`` / ``frame_end``: the values given (negative
    frames included), None for one not given (the pipeline then takes the scene's)."""
    return tuple(getattr(op, p) if op.properties.is_property_set(p) else None for p in ("frame_start", "frame_end"))


def fill_scene_range(op, scene) -> None:
    """Give an operator's unset ``frame_start`` / ``frame_end`` the scene's range, so its redo panel shows
    the frames it works on (the properties are ``SKIP_SAVE``: the next run starts from the scene again)."""
    for p, v in (("frame_start", scene.frame_start), ("frame_end", scene.frame_end)):
        if not op.properties.is_property_set(p):
            setattr(op, p, v)


def face_object(context):
    """The face to correct: FaceLab > Setup > Face, else the active mesh object."""
    s = context.scene.facelab
    if s.face is not None:
        return s.face
    ob = context.active_object
    return ob if ob is not None and ob.type == "MESH" else None


#: Why an operator on the face cannot run without one (``poll_message_set``).
NO_FACE = "Select the captured face mesh (or set it in FaceLab > Setup)"


def poll_face(cls, context) -> bool:
    """Shared ``poll``: a face mesh must be selected (or set in Setup); explains itself otherwise."""
    if face_object(context) is None:
        cls.poll_message_set(NO_FACE)
        return False
    return True


def poll_sketch(context) -> str | None:
    """Why the lips of the face cannot be solved from the sketch in ``context``'s scene, or None when they can.

    The reason (a ``str`` for ``poll_message_set``) names what is missing and what to do, in this order: the face
    (:func:`face_object`), a scene camera (the camera the sketch is drawn in), a lip sketch
    (:func:`~facelab_addon.blender.strokes.has_lip_sketch`).
    """
    scene = context.scene
    if face_object(context) is None:
        return NO_FACE
    if scene.camera is None:
        return "Set a scene camera first (the camera the sketch is drawn in)"
    if not has_lip_sketch(scene, scene.facelab.sketch):
        return "No lip sketch yet: press New Lip Sketch and draw the inner lips in camera view"
    return None
