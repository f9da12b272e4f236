"""Ready to draw: the lip sketch active, in Grease Pencil Draw mode, on a lip layer, seen through its camera.

What New Lip Sketch and the *Upper Lip* / *Lower Lip* buttons leave the artist in. Grease Pencil v3's
mode names are the same in Blender 4.5, 5.0 and 5.3 (:data:`DRAW_MODE`).
"""

from __future__ import annotations

import bpy

from .strokes import set_lip_layer, sketch_camera

__all__ = ["DRAW_MODE", "SKETCH_MODES", "start_drawing"]

#: ``Object.mode`` / ``context.mode`` of Grease Pencil (v3) Draw mode (Blender 4.3 and newer: 4.5, 5.0, 5.3).
DRAW_MODE = "PAINT_GREASE_PENCIL"
#: ``context.mode`` values a sketch step may run from: Object mode, and Draw / Edit mode of the sketch.
SKETCH_MODES = ("OBJECT", DRAW_MODE, "EDIT_GREASE_PENCIL")


def start_drawing(context, gp_obj, lip: str = "upper") -> dict:
    """Leave the artist drawing on the sketch: active and selected, in Draw mode, on the ``lip`` layer,
    every 3D view of the window looking through the sketch's camera with its plate shown.

    Parameters
    ----------
    context : bpy.types.Context
    gp_obj : bpy.types.Object
        The lip sketch.
    lip : str
        ``"upper"`` or ``"lower"``.

    Returns
    -------
    dict
        ``mode`` (the object's mode now), ``layer`` (the active layer's name), ``views`` (3D views
        switched to the camera; 0 without a window, as under ``blender -b``), ``plate`` (whether the
        camera has a background image shown).
    """
    view_layer = context.view_layer
    active = view_layer.objects.active
    if active is not None and active != gp_obj and active.mode != "OBJECT":
        bpy.ops.object.mode_set(mode="OBJECT")  # leave the face's Edit / Sculpt mode first
    for o in context.selected_objects:
        o.select_set(False)
    gp_obj.hide_set(False)
    gp_obj.hide_viewport = False
    view_layer.objects.active = gp_obj
    gp_obj.select_set(True)
    layer = set_lip_layer(gp_obj, lip)
    if gp_obj.mode != DRAW_MODE:
        bpy.ops.object.mode_set(mode=DRAW_MODE)
    cam_obj = sketch_camera(gp_obj) or context.scene.camera
    plate = False
    if cam_obj is not None and cam_obj.type == "CAMERA" and len(cam_obj.data.background_images):
        cam_obj.data.show_background_images = True
        for bg in cam_obj.data.background_images:
            bg.show_background_image = True
        plate = True
    views = 0
    if cam_obj is not None and context.scene.camera != cam_obj:
        context.scene.camera = cam_obj  # "look through the camera" shows the scene camera
    wm = getattr(context, "window_manager", None)
    for win in (wm.windows if wm is not None else []):
        for area in win.screen.areas:
            if area.type != "VIEW_3D":
                continue
            for space in area.spaces:
                if space.type == "VIEW_3D" and space.region_3d is not None:
                    space.region_3d.view_perspective = "CAMERA"
                    views += 1
    return dict(mode=gp_obj.mode, layer=layer, views=views, plate=plate)
