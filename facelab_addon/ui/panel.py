"""The FaceLab sidebar tab in the 3D view, top to bottom as the workflow."""

import bpy

from .ops import face_object
from .panel_reconstruct import draw_reconstruct_section

# Extrapolation scores above this are flagged (the frame's mouth lies well outside the training poses).
EXTRAPOLATING = 0.5


class FACELAB_UL_training_frames(bpy.types.UIList):
    def draw_item(self, context, layout, data, item, icon, active_data, active_propname, index):
        row = layout.row(align=True)
        row.label(text=f"Frame {item.frame}", icon="KEYFRAME")
        row.label(text=item.shape_key)


class _SidebarTab:
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "FaceLab"


class _Section(_SidebarTab):
    bl_parent_id = "FACELAB_PT_main"


class FACELAB_PT_main(_SidebarTab, bpy.types.Panel):
    bl_idname = "FACELAB_PT_main"
    bl_label = "FaceLab"

    def draw(self, context):
        pass


class FACELAB_PT_setup(_Section, bpy.types.Panel):
    bl_label = "1. Setup"

    def draw(self, context):
        s = context.scene.facelab
        col = self.layout.column()
        col.prop(s, "face")
        col.prop(context.scene, "camera")
        col.prop(s, "fixed_group")


class FACELAB_PT_sketch(_Section, bpy.types.Panel):
    bl_label = "2. Sketch & Refine"

    def draw(self, context):
        s = context.scene.facelab
        col = self.layout.column()
        col.operator("facelab.new_lip_sketch", icon="GREASEPENCIL")
        col.prop(s, "sketch")
        col.operator("facelab.refine_lips", icon="MOD_SMOOTH")


class FACELAB_PT_propagate(_Section, bpy.types.Panel):
    bl_label = "3. Train & Propagate"

    def draw(self, context):
        layout = self.layout
        ob = face_object(context)
        col = layout.column()
        col.operator("facelab.auto_regions", icon="GROUP_VERTEX")
        if ob is None:
            col.label(text="No face mesh selected", icon="INFO")
            return
        col.label(text="Training frames")
        row = col.row()
        row.template_list("FACELAB_UL_training_frames", "", ob.facelab, "training_frames", ob.facelab,
                          "active_training_index", rows=3)
        sub = row.column(align=True)
        sub.operator("facelab.mark_training_frame", icon="ADD", text="")
        sub.operator("facelab.remove_training_frame", icon="REMOVE", text="")
        sub.operator("facelab.jump_training_frame", icon="TIME", text="")
        col.operator("facelab.propagate", icon="MOD_DATA_TRANSFER")
        score = ob.get("FL_extrapolation")
        if score is not None:
            box = col.box()
            flag = "ERROR" if score > EXTRAPOLATING else "CHECKMARK"
            box.label(text=f"Extrapolation here: {score:.2f}", icon=flag)
            sug = [m.frame for m in context.scene.timeline_markers if m.name.startswith("FL suggest")]
            if sug:
                box.label(text="Correct next: " + ", ".join(map(str, sorted(sug))), icon="MARKER_HLT")


class FACELAB_PT_reconstruct(_Section, bpy.types.Panel):
    bl_label = "4. Reconstruct from Bundles"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        draw_reconstruct_section(self.layout, context)


class FACELAB_PT_bake(_Section, bpy.types.Panel):
    bl_label = "5. Bake / Export"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        col = self.layout.column(align=True)
        for fmt, label in (("PC2", "Bake PC2"), ("MDD", "Bake MDD"), ("ABC", "Export Alembic")):
            col.operator("facelab.bake", text=label, icon="EXPORT").format = fmt


classes = (
    FACELAB_UL_training_frames,
    FACELAB_PT_main,
    FACELAB_PT_setup,
    FACELAB_PT_sketch,
    FACELAB_PT_propagate,
    FACELAB_PT_reconstruct,
    FACELAB_PT_bake,
)


register, unregister = bpy.utils.register_classes_factory(classes)
