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

from ..core.errors import SketchError
from .lip_layers import has_lip_layers, hidden_object, live_lip_layers
from .strokes import sketch_camera

__all__ = ["sketch_views"]


def sketch_views(scene, frame: int) -> list:
    """``[(sketch, camera_object), ...]``: the Grease Pencil lip sketches keyed on ``frame`` and their cameras.

    A sketch counts when it is shown (:func:`~.lip_layers.hidden_object`), both of its live lip layers
    (:func:`~.lip_layers.live_lip_layers`) have a keyframe on ``frame`` and its camera is known
    (:func:`sketch_camera`). Two such sketches of one camera are refused (``SketchError`` naming both).
    The scene camera's sketch comes first (the main view: the others are matched from its result, see
    :func:`~facelab_addon.core.lips.sketch.refine_lips_views`), the others sorted by sketch name.
    """
    out, seen = [], {}
    for o in sorted(scene.objects, key=lambda o: o.name):
        if o.type != "GREASEPENCIL" or not has_lip_layers(o.data) or hidden_object(o):
            continue
        cam = sketch_camera(o)
        if cam is None:
            continue
        lips = live_lip_layers(o.data.layers, lambda lay: lay.name, f"The lip sketch '{o.name}'")
        keyed = all(lips[lab] and any(int(fr.frame_number) == int(frame) for lay in lips[lab] for fr in lay.frames)
                    for lab in ("upper", "lower"))
        if not keyed:
            continue
        if cam.name in seen:
            raise SketchError(
                f"The lip sketches '{seen[cam.name].name}' and '{o.name}' are both drawn through camera "
                f"'{cam.name}' and keyed on frame {int(frame)}, so it is not clear which one to refine to. Delete "
                "the stale one (or hide it: hidden sketches are not read)."
            )
        seen[cam.name] = o
        out.append((o, cam))
    main = scene.camera
    return sorted(out, key=lambda p: p[1] != main)  # stable: the scene camera's first, the rest by name
