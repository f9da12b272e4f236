"""The FaceLab sidebar tab in the 3D view, top to bottom as the workflow."""

import bpy

from .ops import face_object


class FACELAB_UL_training_frames(bpy.types.UIList):
    def draw_item(self, context, layout, data, item, icon, active_data, active_propname, index):
        row = layout.row(align=True)
        row.label(text=f"Frame {item.frame}", icon="KEYFRAME")
        row.label(text=item.shape_key)


class FACELAB_PT_main(bpy.types.Panel):
    bl_idname = "FACELAB_PT_main"
    bl_label = "FaceLab"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "FaceLab"

    def draw(self, context):
        pass


class FACELAB_PT_setup(bpy.types.Panel):
    bl_label = "1. Setup"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "FaceLab"
    bl_parent_id = "FACELAB_PT_main"

    def draw(self, context):
        s = context.scene.facelab
        col = self.layout.column()
        col.prop(s, "face")
        col.prop(context.scene, "camera")
        col.prop(s, "fixed_group")


class FACELAB_PT_sketch(bpy.types.Panel):
    bl_label = "2. Sketch & Refine"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "FaceLab"
    bl_parent_id = "FACELAB_PT_main"

    def draw(self, context):
        s = context.scene.facelab
        col = self.layout.column()
        col.operator("facelab.new_lip_sketch", icon="GREASEPENCIL")
        col.prop(s, "sketch")
        col.operator("facelab.refine_lips", icon="MOD_SMOOTH")
        ob = face_object(context)
        if ob is not None and len(ob.facelab.training_frames):
            col.label(text="Training frames")
            col.template_list(
                "FACELAB_UL_training_frames", "", ob.facelab, "training_frames", ob.facelab, "active_training_index",
                rows=3,
            )


classes = (FACELAB_UL_training_frames, FACELAB_PT_main, FACELAB_PT_setup, FACELAB_PT_sketch)


def register():
    for c in classes:
        bpy.utils.register_class(c)


def unregister():
    for c in reversed(classes):
        bpy.utils.unregister_class(c)
