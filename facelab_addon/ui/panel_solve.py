"""Sidebar UI of the contour-based solve and retargeting (Bhat et al. 2013).

``draw_solve_section(layout, context)``, ``draw_solve_advanced`` and ``draw_retarget_section(layout,
context)`` are called by the panels *5. Solve from Markers* (and its *Advanced* sub-panel) and
*6. Retarget to a Creature* in ``ui/panel.py``; this module registers only the views list. Frames
whose ``-1`` means "the current / scene frame" are drawn as toggles, never as -1.
"""

import bpy

from .common import face_object


class FACELAB_UL_solve_views(bpy.types.UIList):
    def draw_item(self, context, layout, data, item, icon, active_data, active_propname, index):
        row = layout.row(align=True)
        row.prop(item, "camera", text="", icon="CAMERA_DATA")
        row.prop(item, "clip", text="", icon="TRACKER")


def draw_solve_section(layout, context):
    """Views, binding, sources and options, Solve Performance."""
    s = context.scene.facelab_solve
    col = layout.column()
    col.label(text="Views (camera + footage)")
    row = col.row()
    row.template_list("FACELAB_UL_solve_views", "", s, "views", s, "active_view_index", rows=2)
    sub = row.column(align=True)
    sub.operator("facelab.solve_add_view", icon="ADD", text="")
    sub.operator("facelab.solve_remove_view", icon="REMOVE", text="")
    if len(s.views):
        v = s.views[min(s.active_view_index, len(s.views) - 1)]
        box = col.box()
        box.prop(v, "mask", icon="MOD_MASK")
        box.prop(v, "sketch", icon="GREASEPENCIL")
    col.separator()
    col.prop(s, "bundles")
    if s.bundles == "EMPTIES":
        col.prop(s, "bundle_collection")
    row = col.row(align=True)
    row.prop(s, "bind_current", text="Bind on Current Frame")
    if not s.bind_current:
        row.prop(s, "bind_frame")
    col.operator("facelab.bind_tracks", icon="PIVOT_CURSOR")
    ob = face_object(context)
    if ob is not None and hasattr(ob, "facelab_solve"):
        n = len(ob.facelab_solve.bindings)
        if n:
            col.label(text=f"{n} bindings (frame {ob.facelab_solve.bind_frame})", icon="CHECKMARK")
    col.separator()
    row = col.row(align=True)
    row.prop(s, "use_contours")
    row.prop(s, "sliding")
    row.prop(s, "use_corrective")
    if s.use_contours:
        row = col.row(align=True)
        row.prop(s, "use_annotation")
        if s.use_annotation:
            row.prop(s, "annotation_view", text="View")
    row = col.row(align=True)
    row.prop(s, "use_scene_range")
    if s.use_scene_range:
        scene = context.scene
        row.label(text=f"Scene: {scene.frame_start}-{scene.frame_end}")
    else:
        row.prop(s, "frame_start")
        row.prop(s, "frame_end")
    col.prop(s, "existing_animation")
    col.operator("facelab.solve_performance", icon="SHAPEKEY_DATA")


#: The solver weights of Solve Performance, in its closed *Advanced* sub-panel.
SOLVE_ADVANCED = ("weight_min", "weight_max", "marker_weight", "contour_weight", "anchor_weight",
                  "contour_damping", "lip_passes", "lip_line_weight", "lip_damping")


def draw_solve_advanced(layout, context):
    """The solver weights, one per row (each tooltip says when to change it)."""
    s = context.scene.facelab_solve
    col = layout.column()
    for name in SOLVE_ADVANCED:
        col.prop(s, name)


def draw_retarget_section(layout, context):
    """Creature, correspondence, lip sync, Retarget."""
    s = context.scene.facelab_solve
    col = layout.column()
    col.prop(s, "creature")
    col.prop(s, "correspondence")
    if s.correspondence != "TOPOLOGY":
        col.prop(s, "creature_markers")
    col.prop(s, "lip_sync")
    if s.lip_sync:
        col.prop(s, "lip_threshold")
        col.prop(s, "use_end_points")
        if s.use_end_points:
            col.prop(s, "end_points_upper")
            col.prop(s, "end_points_lower")
    col.operator("facelab.retarget", icon="MOD_DATA_TRANSFER")


classes = (FACELAB_UL_solve_views,)
register, unregister = bpy.utils.register_classes_factory(classes)
