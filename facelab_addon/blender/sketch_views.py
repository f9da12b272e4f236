"""Lip sketches of several cameras: which camera a sketch is drawn through, which sketches a frame has.

Dinev et al. 2018 §5 sketch the inner lips through one camera; FaceLab lets the artist sketch the
same frame through several (a helmet stereo pair, a witness camera), one Grease Pencil sketch per
camera (:func:`facelab_addon.blender.strokes.new_lip_sketch` names them ``FL_LipSketch`` and
``FL_LipSketch.<camera>``). A sketch records its camera in the custom property
:data:`facelab_addon.blender.strokes.SKETCH_CAMERA_PROP` (:func:`~facelab_addon.blender.strokes.sketch_camera`
reads it); a sketch parented to a camera (as New Lip Sketch makes it) belongs to
that camera too. :func:`sketch_views` lists the sketches keyed on a frame with their cameras, one
view each of the Refine Lips solve (:func:`facelab_addon.core.lips.sketch.refine_lips_views`).
"""

from __future__ import annotations

from .strokes import SKETCH_CAMERA_PROP, has_lip_layers, lip_layers, sketch_camera, sketch_name_for

__all__ = ["SKETCH_CAMERA_PROP", "sketch_camera", "sketch_name_for", "sketch_views"]


def sketch_views(scene, frame: int) -> list:
    """``[(sketch, camera_object), ...]``: the Grease Pencil lip sketches keyed on ``frame`` and their cameras.

    A sketch counts when both lip layers have a keyframe on ``frame`` and its camera is known
    (:func:`sketch_camera`); one sketch per camera (the first by name). The scene camera's sketch
    comes first (the main view: the others are matched from its result, see
    :func:`~facelab_addon.core.lips.sketch.refine_lips_views`), the others sorted by sketch name.
    """
    out, seen = [], set()
    for o in sorted(scene.objects, key=lambda o: o.name):
        if o.type != "GREASEPENCIL" or not has_lip_layers(o.data):
            continue
        cam = sketch_camera(o)
        if cam is None or cam.name in seen:
            continue
        lips = lip_layers(o.data.layers, lambda lay: lay.name)
        keyed = all(lips[lab] and any(int(fr.frame_number) == int(frame) for lay in lips[lab] for fr in lay.frames)
                    for lab in ("upper", "lower"))
        if keyed:
            seen.add(cam.name)
            out.append((o, cam))
    main = scene.camera
    return sorted(out, key=lambda p: p[1] != main)  # stable: the scene camera's first, the rest by name
