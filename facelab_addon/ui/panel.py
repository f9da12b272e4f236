"""The FaceLab sidebar tab in the 3D view, top to bottom as the workflow:

1. Setup (face, camera and plate, regions)  2. Sketch & Refine  3. Train & Propagate
4. Solve from Markers / Retarget (issue 4, ``panel_solve``) and Reconstruct from Bundles
(``panel_reconstruct``)  5. Bake / Export.

Panels only draw; every button is an operator whose ``poll`` explains why it is disabled.
"""

import bpy
import numpy as np

from ..blender.shapekeys import find_fcurve
from ..names import EXTRAPOLATION_PROP, LIPS_GROUP, MOUTH_GROUP, SUGGEST_MARKER
from .ops import face_object
from .ops_propagate import RUNNING
from .panel_reconstruct import draw_reconstruct_section
from .panel_solve import draw_retarget_section, draw_solve_section

# Extrapolation scores above this are flagged (the frame's mouth lies well outside the training poses).
EXTRAPOLATING = 0.5


def keyed_extrapolation(obj):
    """(frames (T,), scores (T,)) keyed by Propagate on the object's extrapolation property, or None."""
    fc = find_fcurve(obj, f'["{EXTRAPOLATION_PROP}"]')
    if fc is None or not len(fc.keyframe_points):
        return None
    co = np.empty(2 * len(fc.keyframe_points), np.float32)
    fc.keyframe_points.foreach_get("co", co)
    co = co.reshape(-1, 2)
    return co[:, 0].round().astype(int), co[:, 1]


def frame_ranges(frames) -> list:
    """Sorted frames -> [(first, last), ...] runs of consecutive frames."""
    out = []
    for f in frames:
        if out and f == out[-1][1] + 1:
            out[-1][1] = f
        else:
            out.append([f, f])
    return [tuple(r) for r in out]


def extrapolating_ranges(obj, threshold=EXTRAPOLATING, limit=6):
    """Frame runs where the keyed extrapolation score exceeds ``threshold`` (at most ``limit``) and the total."""
    keyed = keyed_extrapolation(obj)
    if keyed is None:
        return None, 0
    frames, score = keyed
    over = frames[score > threshold]
    return frame_ranges(over.tolist())[:limit], int(len(over))


class FACELAB_UL_training_frames(bpy.types.UIList):
    """Training frames: frame, correction (shape key or sculpt), a warning when its key is gone."""

    def draw_item(self, context, layout, data, item, icon, active_data, active_propname, index):
        ob = data.id_data
        keys = ob.data.shape_keys.key_blocks if ob.data.shape_keys else {}
        row = layout.row(align=True)
        current = item.frame == context.scene.frame_current
        row.label(text=f"Frame {item.frame}", icon="PLAY" if current else "KEYFRAME")
        if item.source == "sketch" and item.shape_key not in keys:
            row.label(text=f"{item.shape_key} deleted", icon="ERROR")
        else:
            row.label(text=item.shape_key or "sculpted mesh", icon="GREASEPENCIL" if item.source == "sketch"
                      else "SCULPTMODE_HLT")


class _SidebarTab:
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "FaceLab"


class _Section(_SidebarTab):
    bl_parent_id = "FACELAB_PT_main"


class FACELAB_PT_main(_SidebarTab, bpy.types.Panel):
    """The tab's header: which face FaceLab works on."""

    bl_idname = "FACELAB_PT_main"
    bl_label = "FaceLab"

    def draw(self, context):
        ob = face_object(context)
        if ob is None:
            self.layout.label(text="Select the captured face mesh", icon="INFO")
        else:
            self.layout.label(text=f"Face: {ob.name}", icon="MESH_DATA")


class FACELAB_PT_setup(_Section, bpy.types.Panel):
    bl_label = "1. Setup"

    def draw(self, context):
        s = context.scene.facelab
        col = self.layout.column()
        col.prop(s, "face")
        col.prop(context.scene, "camera")
        cam = context.scene.camera
        if cam is not None and cam.type == "CAMERA":
            plates = [bg.image.name for bg in cam.data.background_images if bg.image is not None]
            if plates:
                col.label(text=f"Plate: {plates[0]}", icon="IMAGE_BACKGROUND")
            else:
                col.label(text="No plate: Camera > Background Images", icon="INFO")
        col.prop(s, "fixed_group")
        col.separator()
        col.label(text="Regions")
        ob = face_object(context)
        if ob is not None:
            row = col.row(align=True)
            for g in (MOUTH_GROUP, LIPS_GROUP):
                row.label(text=g, icon="CHECKMARK" if ob.vertex_groups.get(g) else "X")
        col.operator("facelab.auto_regions", icon="GROUP_VERTEX")


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
        if ob is None:
            col.label(text="No face mesh selected", icon="INFO")
            return
        col.label(text=f"Training frames ({len(ob.facelab.training_frames)})")
        row = col.row()
        row.template_list("FACELAB_UL_training_frames", "", ob.facelab, "training_frames", ob.facelab,
                          "active_training_index", rows=3)
        sub = row.column(align=True)
        sub.operator("facelab.mark_training_frame", icon="ADD", text="")
        sub.operator("facelab.remove_training_frame", icon="REMOVE", text="")
        sub.separator()
        sub.operator("facelab.jump_training_frame", icon="TIME", text="")
        job = RUNNING["job"]
        if job is not None:  # a Propagate started from this button is stepping on a timer
            col.progress(factor=job.factor, type="BAR", text=f"{RUNNING['label']}: {job.stage} (Esc cancels)")
        else:
            col.operator("facelab.propagate", icon="MOD_DATA_TRANSFER")

        score = ob.get(EXTRAPOLATION_PROP)
        if score is None:
            return
        box = col.box()
        flag = "ERROR" if score > EXTRAPOLATING else "CHECKMARK"
        box.label(text=f"Extrapolation on this frame: {score:.2f}", icon=flag)
        ranges, n_over = extrapolating_ranges(ob)
        if ranges:
            box.label(text=f"Model extrapolates on {n_over} frames:", icon="ERROR")
            flow = box.grid_flow(columns=3, align=True)
            for a, b in ranges:
                op = flow.operator("facelab.jump_to_frame", text=f"{a}" if a == b else f"{a}-{b}")
                op.frame = a
        sug = sorted(m.frame for m in context.scene.timeline_markers if m.name.startswith(SUGGEST_MARKER))
        if sug:
            box.label(text="Correct next (suggested):", icon="MARKER_HLT")
            flow = box.grid_flow(columns=4, align=True)
            for f in sug:
                flow.operator("facelab.jump_to_frame", text=str(f)).frame = f


class FACELAB_PT_solve(_Section, bpy.types.Panel):
    """Issue 4 (Bhat et al. 2013): shown once ui/panel_solve.py exists."""

    bl_label = "4. Solve from Markers"
    bl_options = {"DEFAULT_CLOSED"}

    @classmethod
    def poll(cls, context):
        return draw_solve_section is not None and hasattr(context.scene, "facelab_solve")

    def draw(self, context):
        draw_solve_section(self.layout, context)
        if draw_retarget_section is not None:
            self.layout.separator()
            self.layout.label(text="Retarget to a creature", icon="MOD_DATA_TRANSFER")
            draw_retarget_section(self.layout, context)


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
        scene = context.scene
        col.label(text=f"Frames {scene.frame_start}-{scene.frame_end} of the scene")
        job = RUNNING["job"]
        if job is not None:
            col.progress(factor=job.factor, type="BAR", text=f"{RUNNING['label']}: {job.stage} (Esc cancels)")
        for fmt, label in (("PC2", "Bake PC2"), ("MDD", "Bake MDD"), ("ABC", "Export Alembic")):
            col.operator("facelab.bake", text=label, icon="EXPORT").format = fmt


classes = (
    FACELAB_UL_training_frames,
    FACELAB_PT_main,
    FACELAB_PT_setup,
    FACELAB_PT_sketch,
    FACELAB_PT_propagate,
    FACELAB_PT_solve,
    FACELAB_PT_reconstruct,
    FACELAB_PT_bake,
)


register, unregister = bpy.utils.register_classes_factory(classes)
