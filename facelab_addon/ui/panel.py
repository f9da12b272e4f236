"""The FaceLab sidebar tab in the 3D view, top to bottom as the workflow:

1. Setup (face, camera and plate, fixed group, regions)  2. Sketch & Refine  3. Train & Propagate
4. Review (capture vs corrected, heat map, neighbouring sketches, frames to look at)
5. Solve from Markers (``panel_solve``)  6. Retarget to a Creature  7. Reconstruct from Bundles
(``panel_reconstruct``)  8. Bake / Export. Each step with settings has a closed settings
sub-panel generated from its pipeline's settings (:mod:`.scene_settings`), the solver weights in a
closed *Advanced* sub-panel below it.

Panels only draw; every button is an operator whose ``poll`` explains why it is disabled.
"""

import bpy

from ..blender.correction_files import correction_cache_problems, missing_correction_files
from ..blender.review import keyed_extrapolation, showing_capture
from ..names import CORRECTION_ATTR, CORRECTION_RANGE_PROP, EXTRAPOLATION_PROP, LIPS_GROUP, MOUTH_GROUP, SUGGEST_MARKER
from ..pipeline.wording import EXTRAPOLATING, extrapolation_word
from . import scene_settings
from .common import face_object
from .ops_live import draw_live
from .ops_propagate import RUNNING
from .panel_reconstruct import draw_reconstruct_section
from .panel_solve import draw_retarget_section, draw_solve_advanced, draw_solve_section


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
    """Training frames, sorted by frame: frame, correction (shape key or sculpt), a warning when its key is gone."""

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

    def filter_items(self, context, data, propname):
        return [], sorted_order([t.frame for t in getattr(data, propname)])


def sorted_order(frames) -> list:
    """``UIList.filter_items``'s new order: the display position of each item, by frame (stable)."""
    pos = [0] * len(frames)
    for rank, i in enumerate(sorted(range(len(frames)), key=lambda i: frames[i])):
        pos[i] = rank
    return pos


class _SidebarTab:
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "FaceLab"


class _Section(_SidebarTab):
    bl_parent_id = "FACELAB_PT_main"


def _operator_if_registered(layout, idname, **kw) -> bool:
    """Draw ``idname``'s button when that operator is registered (another module may add it)."""
    cat, name = idname.split(".")
    if not hasattr(bpy.types, f"{cat.upper()}_OT_{name}"):
        return False
    layout.operator(idname, **kw)
    return True


def _plate(bg, scene):
    """The image or Movie Clip a camera background shows (the scene's active clip for 'Camera Clip')."""
    if bg.source == "IMAGE":
        return bg.image
    return scene.active_clip if bg.use_camera_clip else bg.clip


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
            missing = missing_correction_files(ob)
            if missing:  # the .blend moved without them: the face shows (and would bake) the capture
                box = self.layout.box()
                box.alert = True
                box.label(text="Correction cache missing (the face shows the capture):", icon="ERROR")
                for prefix, path in missing:
                    box.label(text=f"{prefix}*: {path}")
                box.label(text="Copy it back beside the .blend, or run the step again; Bake refuses meanwhile")


class FACELAB_PT_setup(_Section, bpy.types.Panel):
    bl_label = "1. Setup"

    def draw(self, context):
        s = context.scene.facelab
        col = self.layout.column()
        row = col.row(align=True)
        _operator_if_registered(row, "facelab.load_plate", icon="FILE_MOVIE")
        _operator_if_registered(row, "facelab.load_sample", icon="FILE_BLEND")
        col.prop(s, "face")
        col.prop(context.scene, "camera")
        cam = context.scene.camera
        if cam is not None and cam.type == "CAMERA":
            plates = [p.name for p in map(lambda bg: _plate(bg, context.scene), cam.data.background_images)
                      if p is not None]
            if plates:
                col.label(text=f"Plate: {plates[0]}", icon="IMAGE_BACKGROUND")
            else:
                col.label(text="No plate: Camera > Background Images", icon="INFO")
        ob = face_object(context)
        if ob is not None:
            col.prop_search(s, "fixed_group", ob, "vertex_groups", icon="GROUP_VERTEX")
            if s.fixed_group and ob.vertex_groups.get(s.fixed_group) is None:
                col.label(text=f"No group '{s.fixed_group}': separate mesh parts are held", icon="INFO")
        else:
            col.prop(s, "fixed_group")
        col.separator()
        col.label(text="Regions")
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
        draw_live(col, context)
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
        word = extrapolation_word(score)
        # drawn as a flat button: its tooltip gives the score and the bands; a click goes to the worst frame
        box.operator("facelab.most_extrapolated_frame", text=f"Prediction on this frame: {word}", emboss=False,
                     icon="CHECKMARK" if word == "reliable" else "ERROR")
        ranges, n_over = extrapolating_ranges(ob)
        if ranges:
            box.label(text=f"Uncertain or guessing on {n_over} frames:", icon="ERROR")
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


class FACELAB_PT_review(_Section, bpy.types.Panel):
    bl_label = "4. Review"

    def draw(self, context):
        col = self.layout.column()
        ob = face_object(context)
        if ob is None:
            col.label(text="No face mesh selected", icon="INFO")
            return
        capture = showing_capture(ob)
        col.label(text="Showing: the capture (corrections muted)" if capture else "Showing: the corrected face",
                  icon="HIDE_ON" if capture else "HIDE_OFF")
        col.operator("facelab.review_toggle", icon="UV_SYNC_SELECT",
                     text="Show Corrected" if capture else "Show Capture")
        row = col.row(align=True)
        row.operator("facelab.correction_heatmap", icon="COLOR")
        rng = ob.data.get(CORRECTION_RANGE_PROP)
        if rng is not None and ob.data.color_attributes.get(CORRECTION_ATTR) is not None:
            col.label(text=f"Heat map (frame {int(rng[2])}): grey 0 mm - red {rng[1]:.2f} mm", icon="INFO")
        row = col.row(align=True)
        row.operator("facelab.sketch_onion_skin", text="Neighbouring Sketches", icon="ONIONSKIN_ON").show = True
        row.operator("facelab.sketch_onion_skin", text="", icon="ONIONSKIN_OFF").show = False
        row = col.row(align=True)
        row.operator("facelab.next_suggested_frame", text="Next Suggested", icon="MARKER_HLT")
        row.operator("facelab.most_extrapolated_frame", text="Most Extrapolated", icon="ERROR")


class FACELAB_PT_solve(_Section, bpy.types.Panel):
    """Solve a shape-key rig's weights on every frame from tracked markers and contours"""

    bl_label = "5. Solve from Markers"
    bl_options = {"DEFAULT_CLOSED"}

    @classmethod
    def poll(cls, context):
        return draw_solve_section is not None and hasattr(context.scene, "facelab_solve")

    def draw(self, context):
        draw_solve_section(self.layout, context)


class FACELAB_PT_solve_advanced(_SidebarTab, bpy.types.Panel):
    """Solver weights of Solve Performance: change them when the solve misses markers or contours"""

    bl_parent_id = "FACELAB_PT_solve"
    bl_label = "Advanced"
    bl_options = {"DEFAULT_CLOSED"}

    @classmethod
    def poll(cls, context):
        return hasattr(context.scene, "facelab_solve")

    def draw(self, context):
        draw_solve_advanced(self.layout, context)


class FACELAB_PT_retarget(_Section, bpy.types.Panel):
    """Carry the solved performance to a creature mesh"""

    bl_label = "6. Retarget to a Creature"
    bl_options = {"DEFAULT_CLOSED"}

    @classmethod
    def poll(cls, context):
        return draw_retarget_section is not None and hasattr(context.scene, "facelab_solve")

    def draw(self, context):
        draw_retarget_section(self.layout, context)


class FACELAB_PT_reconstruct(_Section, bpy.types.Panel):
    bl_label = "7. Reconstruct from Bundles"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        draw_reconstruct_section(self.layout, context)


class FACELAB_PT_bake(_Section, bpy.types.Panel):
    bl_label = "8. Bake / Export"
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
    FACELAB_PT_review,
    FACELAB_PT_solve,
    FACELAB_PT_solve_advanced,
    FACELAB_PT_retarget,
    FACELAB_PT_reconstruct,
    FACELAB_PT_bake,
)

_register, _unregister = bpy.utils.register_classes_factory(classes)


@bpy.app.handlers.persistent
def report_missing_caches(_dummy=None):
    """On opening a .blend: name every FaceLab correction cache whose file is missing or broken (on stderr,
    Blender's console; the sidebar shows it too), so the loss is known before anything is baked."""
    import sys

    for ob in bpy.data.objects:
        for problem in correction_cache_problems(ob):
            print(f"FaceLab: {problem}", file=sys.stderr, flush=True)


def register():
    _register()
    scene_settings.register_panels()  # each step's Settings sub-panel, after its parent
    if report_missing_caches not in bpy.app.handlers.load_post:
        bpy.app.handlers.load_post.append(report_missing_caches)


def unregister():
    if report_missing_caches in bpy.app.handlers.load_post:
        bpy.app.handlers.load_post.remove(report_missing_caches)
    scene_settings.unregister_panels()
    _unregister()
