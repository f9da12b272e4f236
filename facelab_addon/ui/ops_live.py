"""Live Refine and Snap to Plate in 2. Sketch & Refine: the operators, the stroke watcher, the Influence
drawn in the viewport.

The work is :class:`facelab_addon.pipeline.live_refine.LiveRefine`. *Live Refine* starts a session on
the current frame; while it runs, a depsgraph handler re-solves after each change of the sketch's
strokes (:func:`on_depsgraph_update`), and a viewport draw handler shows the vertices the Influence
lets move. *Accept* is a Refine Lips of the same strokes; *Discard* (or Esc in the viewport) leaves
nothing. Under ``blender -b`` neither handler runs: :class:`FACELAB_OT_live_refine_update` is the
synchronous step the tests drive.
"""

import bpy
import numpy as np

from ..core.errors import FaceLabError
from ..names import SNAP_PROP, SNAP_REPORT_PROP
from ..pipeline.live_refine import PREVIEW_KEY, LiveRefine, remove_preview
from .common import face_object, poll_sketch
from .ops import refine_settings

#: The running session (one at a time), its sketch's stroke signature and its last message.
LIVE = {"session": None, "signature": None, "message": "", "draw": None}


def _influence_changed(props, context):
    s = session()
    if s is not None:
        s.influence_mm = float(props.influence_mm)
        LIVE["signature"] = None
        live_update(context.scene)


class FACELAB_PG_live(bpy.types.PropertyGroup):
    """Live Refine settings of the shot (``scene.facelab_live``)."""

    influence_mm: bpy.props.FloatProperty(
        name="Influence (mm)", default=0.0, min=0.0, soft_max=50.0, precision=1, update=_influence_changed,
        description="How far from the sketched lips the face may move, in millimetres, like the radius of "
                    "proportional editing; 0 uses Refine's Free Region")
    show_influence: bpy.props.BoolProperty(name="Show Influence", default=True,
                                           description="Draw the vertices the correction may move")


def session():
    """The running :class:`LiveRefine`, or None."""
    s = LIVE["session"]
    return s if s is not None and not s.closed else None


def stroke_signature(gp_obj, frame: int):
    """A cheap fingerprint of the lip sketch's strokes on ``frame`` (point count and position sums), to
    re-solve only when a stroke changed. None without a sketch."""
    if gp_obj is None or gp_obj.type != "GREASEPENCIL":
        return None
    sig = []
    for layer in gp_obj.data.layers:
        fr = layer.get_frame_at(frame)
        if fr is None or fr.drawing is None:
            continue
        pos = fr.drawing.attributes.get("position")
        n = len(pos.data) if pos is not None else 0
        a = np.empty(n * 3, np.float32)
        if n:
            pos.data.foreach_get("vector", a)
        sig.append((layer.name, n, float(a.sum()), float(np.abs(a).sum())))
    return tuple(sig)


def live_update(scene) -> str:
    """Re-solve the running session if the sketch's strokes changed; returns the message shown."""
    s = session()
    if s is None:
        return ""
    sig = stroke_signature(s.sketch or scene.facelab.sketch, s.frame)
    if sig == LIVE["signature"]:
        return LIVE["message"]
    LIVE["signature"] = sig
    try:
        u = s.update()
        LIVE["message"] = (f"Live: {u.seconds * 1000:.0f} ms, {u.n_free} vertices free "
                           f"(Influence {u.influence_mm:.1f} mm)")
        if u.warnings:  # e.g. strokes that may sit on swapped layers: shown while drawing, not only on Accept
            LIVE["message"] += " | Check: " + " ".join(u.warnings)
    except FaceLabError as e:
        LIVE["message"] = f"Live: waiting ({e})"
    return LIVE["message"]


@bpy.app.handlers.persistent
def on_depsgraph_update(scene, depsgraph=None):
    """``depsgraph_update_post``: a changed lip sketch re-solves the preview (the preview's own writes leave the
    strokes' signature as it was, so they do not)."""
    if session() is not None:
        live_update(scene)



@bpy.app.handlers.persistent
def on_undo(scene, *args):
    """``undo_post`` / ``redo_post`` (registered with the add-on): an undo changes the face under a session:
    end it, and drop any preview key a restored state still holds."""
    if LIVE["session"] is not None:
        LIVE["session"].closed = True
        stop_live()
    for ob in bpy.data.objects:
        if ob.type == "MESH" and ob.data.shape_keys is not None and ob.data.shape_keys.key_blocks.get(PREVIEW_KEY):
            remove_preview(ob)


def influence_points(s=None):
    """(k,3) world positions of the preview's vertices the Influence lets move (what the viewport draws);
    empty before the first solve."""
    s = s or session()
    if s is None or s.region() is None:
        return np.zeros((0, 3))
    return s.preview_vertices()[s.region()]


def _draw_influence():
    import gpu
    from gpu_extras.batch import batch_for_shader

    props = getattr(bpy.context.scene, "facelab_live", None)
    P = influence_points()
    if props is None or not props.show_influence or not len(P):
        return
    try:
        shader = gpu.shader.from_builtin("POINT_UNIFORM_COLOR")  # round points where the GPU backend has them
    except (ValueError, KeyError):
        shader = gpu.shader.from_builtin("UNIFORM_COLOR")
    batch = batch_for_shader(shader, "POINTS", {"pos": P.astype(np.float32).tolist()})
    gpu.state.point_size_set(4.0)
    gpu.state.blend_set("ALPHA")
    shader.uniform_float("color", (1.0, 0.55, 0.1, 0.6))
    batch.draw(shader)
    gpu.state.blend_set("NONE")


def start_live(context) -> LiveRefine:
    """Start a session on the current frame (ending one still running) and its handlers."""
    stop_live(discard=True)
    scene = context.scene
    s = LiveRefine(scene, face_object(context), settings=refine_settings(context), sketch=scene.facelab.sketch,
                   influence_mm=scene.facelab_live.influence_mm)
    LIVE.update(session=s, signature=None, message="Live: draw a stroke")
    if on_depsgraph_update not in bpy.app.handlers.depsgraph_update_post:
        bpy.app.handlers.depsgraph_update_post.append(on_depsgraph_update)
    if LIVE["draw"] is None and not bpy.app.background:
        LIVE["draw"] = bpy.types.SpaceView3D.draw_handler_add(_draw_influence, (), "WINDOW", "POST_VIEW")
    return s


def stop_live(discard: bool = False) -> None:
    """End the session's handlers (and discard its preview with ``discard``)."""
    s = LIVE["session"]
    if discard and s is not None and not s.closed:
        s.discard()
    LIVE.update(session=None, signature=None, message="")
    if on_depsgraph_update in bpy.app.handlers.depsgraph_update_post:
        bpy.app.handlers.depsgraph_update_post.remove(on_depsgraph_update)
    if LIVE["draw"] is not None:
        bpy.types.SpaceView3D.draw_handler_remove(LIVE["draw"], "WINDOW")
        LIVE["draw"] = None
    for area in getattr(bpy.context.screen, "areas", []) if bpy.context.screen else []:
        if area.type == "VIEW_3D":
            area.tag_redraw()


class FACELAB_OT_live_refine(bpy.types.Operator):
    """Re-solve the lips after each stroke and show the result as a preview (Accept keeps it as a Refine, Esc or Discard drops it)"""

    bl_idname = "facelab.live_refine"
    bl_label = "Live Refine"
    bl_options = {"REGISTER"}

    @classmethod
    def poll(cls, context):
        why = poll_sketch(context)
        if why is not None:
            cls.poll_message_set(why)
            return False
        return True

    def execute(self, context):
        try:
            start_live(context)
            msg = live_update(context.scene)
        except FaceLabError as e:
            stop_live(discard=True)
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        self.report({"INFO"}, msg or "Live Refine on: draw the lips; Accept or Discard when done")
        return {"FINISHED"}

    def invoke(self, context, event):
        if self.execute(context) != {"FINISHED"}:
            return {"CANCELLED"}
        context.window_manager.modal_handler_add(self)
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        if session() is None:
            return {"FINISHED"}
        if event.type == "ESC" and event.value == "PRESS":
            stop_live(discard=True)
            self.report({"INFO"}, "Live Refine discarded")
            return {"CANCELLED"}
        return {"PASS_THROUGH"}


class _WhileLive:
    """``poll`` of the operators of a running session."""

    @classmethod
    def poll(cls, context):
        if session() is None:
            cls.poll_message_set("Live Refine is not running")
            return False
        return True


class FACELAB_OT_live_refine_update(_WhileLive, bpy.types.Operator):
    """Re-solve the live preview from the strokes drawn now"""

    bl_idname = "facelab.live_refine_update"
    bl_label = "Update Preview"
    bl_options = {"REGISTER"}

    def execute(self, context):
        LIVE["signature"] = None
        self.report({"INFO"}, live_update(context.scene))
        return {"FINISHED"}


class FACELAB_OT_live_refine_accept(_WhileLive, bpy.types.Operator):
    """Keep the live preview: refine the frame from the same strokes (a new FL_Refine key and training frame)"""

    bl_idname = "facelab.live_refine_accept"
    bl_label = "Accept"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        s = session()
        try:
            r = s.accept()
        except FaceLabError as e:
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        finally:
            stop_live()
        self.report({"INFO"}, f"Refined lips on frame {r.frame}: shape key '{r.shape_key}', {r.moved_vertices} "
                              "vertices moved")
        for w in r.warnings:
            self.report({"WARNING"}, w)
        return {"FINISHED"}


class FACELAB_OT_live_refine_discard(_WhileLive, bpy.types.Operator):
    """Drop the live preview; nothing is left"""

    bl_idname = "facelab.live_refine_discard"
    bl_label = "Discard"
    bl_options = {"REGISTER"}

    def execute(self, context):
        stop_live(discard=True)
        self.report({"INFO"}, "Live Refine discarded")
        return {"FINISHED"}


class FACELAB_OT_snap_selected_strokes(bpy.types.Operator):
    """Choose Snap to Plate for the selected strokes of the lip sketch on this frame: snapped, never, or as the
    sketch's Snap to Plate says (the strokes drawn are not moved; they are read snapped)"""

    bl_idname = "facelab.snap_selected_strokes"
    bl_label = "Snap Selected Strokes"
    bl_options = {"REGISTER", "UNDO"}

    choice: bpy.props.EnumProperty(
        name="Snap", default="ON",
        description="How the selected strokes are read: snapped to the plate's lip edges, as drawn, or as the "
                    "sketch's Snap to Plate says",
        items=(("ON", "Snap", "Read the selected strokes snapped to the plate"),
               ("OFF", "Never", "Read the selected strokes as drawn, whatever the sketch's Snap to Plate"),
               ("SKETCH", "As Sketch", "Follow the sketch's Snap to Plate option")))

    @classmethod
    def poll(cls, context):
        gp = getattr(context.scene.facelab, "sketch", None)
        if gp is None or gp.type != "GREASEPENCIL":
            cls.poll_message_set("No lip sketch yet: press New Lip Sketch")
            return False
        return True

    def execute(self, context):
        from ..blender.lip_layers import live_lip_layers
        from ..blender.strokes import selected_strokes, set_stroke_snap

        gp = context.scene.facelab.sketch
        frame = context.scene.frame_current
        value = {"ON": 1, "OFF": -1, "SKETCH": 0}[self.choice]
        lips = live_lip_layers(gp.data.layers, lambda lay: lay.name, f"Sketch '{gp.name}'")
        n = 0
        for layer in {lay.name: lay for lab in lips for lay in lips[lab]}.values():
            fr = layer.get_frame_at(frame)
            if fr is None or fr.drawing is None or fr.drawing.type != "DRAWING":
                continue
            n += set_stroke_snap(fr.drawing, selected_strokes(fr.drawing), value)
        if n == 0:
            self.report({"WARNING"}, "No stroke of the lip layers is selected on this frame: select strokes in "
                                     "Edit Mode, then press Snap Selected Strokes")
            return {"CANCELLED"}
        gp.data.update_tag()
        if session() is not None:  # the strokes Live Refine reads changed: re-solve now
            LIVE["signature"] = None
            live_update(context.scene)
        what = {"ON": "snapped to the plate", "OFF": "read as drawn", "SKETCH": "as the sketch's Snap to Plate"}
        self.report({"INFO"}, f"{n} stroke(s) {what[self.choice]}")
        return {"FINISHED"}


def draw_live(layout, context) -> None:
    """The Live Refine and Snap to Plate rows of 2. Sketch & Refine."""
    scene = context.scene
    gp = scene.facelab.sketch
    col = layout.column(align=True)
    if gp is not None:
        row = col.row(align=True)
        row.operator("facelab.sketch_lip_layer", text="Upper Lip", icon="TRIA_UP").lip = "upper"
        row.operator("facelab.sketch_lip_layer", text="Lower Lip", icon="TRIA_DOWN").lip = "lower"
        col.prop(gp, SNAP_PROP, text="Snap to Plate")
        row = col.row(align=True)
        row.operator("facelab.snap_selected_strokes", text="Snap Selected").choice = "ON"
        row.operator("facelab.snap_selected_strokes", text="Never").choice = "OFF"
        report = gp.get(SNAP_REPORT_PROP)
        if report:
            col.label(text=report, icon="INFO")
    box = layout.box()
    props = scene.facelab_live
    box.prop(props, "influence_mm")
    box.prop(props, "show_influence")
    if session() is None:
        box.operator("facelab.live_refine", icon="PLAY")
        return
    box.label(text=LIVE["message"] or "Live: draw a stroke", icon="TIME")
    row = box.row(align=True)
    row.operator("facelab.live_refine_accept", icon="CHECKMARK")
    row.operator("facelab.live_refine_discard", icon="CANCEL")


classes = (FACELAB_PG_live, FACELAB_OT_live_refine, FACELAB_OT_live_refine_update, FACELAB_OT_live_refine_accept,
           FACELAB_OT_live_refine_discard, FACELAB_OT_snap_selected_strokes)


def register():
    for c in classes:
        bpy.utils.register_class(c)
    bpy.types.Scene.facelab_live = bpy.props.PointerProperty(type=FACELAB_PG_live)
    setattr(bpy.types.Object, SNAP_PROP, bpy.props.BoolProperty(
        name="Snap to Plate", default=False,
        description="Read this sketch's strokes snapped onto the lip edges of the plate (the strokes drawn stay as "
                    "they are); points with no edge within a few pixels stay as drawn. A stroke set with Snap "
                    "Selected Strokes follows its own choice"))
    for h in (bpy.app.handlers.undo_post, bpy.app.handlers.redo_post):
        if on_undo not in h:
            h.append(on_undo)


def unregister():
    stop_live(discard=True)
    for h in (bpy.app.handlers.undo_post, bpy.app.handlers.redo_post):
        if on_undo in h:
            h.remove(on_undo)
    delattr(bpy.types.Object, SNAP_PROP)
    del bpy.types.Scene.facelab_live
    for c in reversed(classes):
        bpy.utils.unregister_class(c)
