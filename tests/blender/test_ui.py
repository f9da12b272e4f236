"""The sidebar and its operators, headless: everything registers (and again), every operator is
polled with and without a face and explains a refusal, the cheap ones run (with undo), panels are
in workflow order, property defaults, the extrapolation helpers the panel draws from."""

import re

import bpy
import numpy as np
import pytest

import facelab_addon
from facelab_addon.blender.review import keyed_extrapolation
from facelab_addon.names import EXTRAPOLATION_PROP
from facelab_addon.pipeline import bake as bake_pipeline
from facelab_addon.pipeline import propagate as propagate_pipeline
from facelab_addon.pipeline import shot_settings
from facelab_addon.pipeline.steps import StepJob
from facelab_addon.pipeline.wording import EXTRAPOLATING
from facelab_addon.ui import common, ops, ops_propagate, panel

pytestmark = pytest.mark.blender

OPERATORS = ["new_lip_sketch", "refine_lips", "auto_regions", "mark_training_frame", "remove_training_frame",
             "jump_training_frame", "jump_to_frame", "propagate", "bake", "reconstruct_from_bundles",
             "bind_tracks", "solve_performance", "retarget", "generate_correctives", "bundles_from_clip",
             "review_toggle", "correction_heatmap", "sketch_onion_skin", "next_suggested_frame",
             "most_extrapolated_frame", "reset_settings", "save_settings_defaults"]
# operators that change the scene: they must support undo
UNDOABLE = ["new_lip_sketch", "refine_lips", "auto_regions", "mark_training_frame", "remove_training_frame",
            "propagate", "reconstruct_from_bundles", "bind_tracks", "solve_performance", "retarget",
            "generate_correctives", "bundles_from_clip", "review_toggle", "correction_heatmap", "sketch_onion_skin",
            "next_suggested_frame", "most_extrapolated_frame", "reset_settings"]
PANELS = ["FACELAB_PT_main", "FACELAB_PT_setup", "FACELAB_PT_sketch", "FACELAB_PT_propagate", "FACELAB_PT_review",
          "FACELAB_PT_solve", "FACELAB_PT_retarget", "FACELAB_PT_reconstruct", "FACELAB_PT_bake"]


def op_class(name):
    return getattr(bpy.types, "FACELAB_OT_" + name)


def empty_scene():
    bpy.ops.wm.read_factory_settings(use_empty=True)
    return bpy.context.scene


def small_face(scene):
    from facelab_addon.blender.scene import new_mesh_object

    g = np.stack(np.meshgrid(np.linspace(-1, 1, 6), np.linspace(-1, 1, 6), indexing="ij"), -1).reshape(-1, 2)
    V = np.c_[g, np.zeros(len(g))]
    F = [[i * 6 + j, (i + 1) * 6 + j, (i + 1) * 6 + j + 1, i * 6 + j + 1] for i in range(5) for j in range(5)]
    obj = new_mesh_object("Face", V, np.array(F))
    bpy.context.view_layer.objects.active = obj
    obj.select_set(True)
    return obj


def test_register_unregister_register():
    facelab_addon.register()
    try:
        registered = sorted(n[len("FACELAB_OT_"):] for n in dir(bpy.types) if n.startswith("FACELAB_OT_"))
        # every operator of FaceLab's ui modules is listed here (issue 4's register themselves, if present)
        assert set(OPERATORS) <= set(registered), set(OPERATORS) - set(registered)
        for op in OPERATORS:
            assert hasattr(bpy.ops.facelab, op)
        for p in PANELS:
            assert hasattr(bpy.types, p), p
        assert hasattr(bpy.types.Scene, "facelab") and hasattr(bpy.types.Object, "facelab")
    finally:
        facelab_addon.unregister()
    assert not hasattr(bpy.types, "FACELAB_PT_main") and not hasattr(bpy.types, "FACELAB_OT_propagate")
    facelab_addon.register()  # and again, as Blender does on reload
    facelab_addon.unregister()


def test_operators_have_tooltips_and_undo(addon):
    for op in OPERATORS:
        cls = op_class(op)
        assert (cls.__doc__ or "").strip(), f"{op}: no tooltip"
        assert cls.bl_label
    for op in UNDOABLE:
        assert {"REGISTER", "UNDO"} <= set(op_class(op).bl_options), op


def test_panels_read_as_the_workflow(addon):
    cls = [getattr(bpy.types, p) for p in PANELS]
    assert all(c.bl_category == "FaceLab" and c.bl_space_type == "VIEW_3D" and c.bl_region_type == "UI" for c in cls)
    assert all(c.bl_parent_id == "FACELAB_PT_main" for c in cls[1:])
    # registration order = display order, numbered as the workflow (sub-panels follow their parent)
    order = [c.__name__ for c in panel.classes if c.__name__.startswith("FACELAB_PT_")
             and getattr(c, "bl_parent_id", "FACELAB_PT_main") == "FACELAB_PT_main"]
    assert order == PANELS
    labels = [getattr(bpy.types, p).bl_label for p in PANELS[1:]]
    numbers = [lab.split(".")[0] for lab in labels]
    assert numbers == [str(i) for i in range(1, len(PANELS))]  # no two panels with the same number
    assert bpy.types.FACELAB_PT_retarget.bl_label == "6. Retarget to a Creature"  # findable (docs/retarget.md)
    ctx = bpy.context
    assert bpy.types.FACELAB_PT_solve.poll(ctx) and bpy.types.FACELAB_PT_retarget.poll(ctx)
    # every step with settings has a closed settings sub-panel under it, the solver weights in a closed
    # Advanced sub-panel under that; no two sub-panels of one panel share a title
    from facelab_addon.pipeline.shot_settings import SCENE_SETTINGS, panel_fields

    for e in SCENE_SETTINGS:
        sub = getattr(bpy.types, f"FACELAB_PT_{e.attr}")
        assert sub.bl_parent_id == e.panel and sub.bl_label == e.label and "DEFAULT_CLOSED" in sub.bl_options
        adv = getattr(bpy.types, f"FACELAB_PT_{e.attr}_advanced", None)
        assert (adv is not None) == bool(panel_fields(e, True)), e.attr
        if adv is not None:
            assert adv.bl_parent_id == sub.bl_idname and adv.bl_label == "Advanced" and "DEFAULT_CLOSED" in adv.bl_options
    subs = [getattr(bpy.types, n) for n in dir(bpy.types) if n.startswith("FACELAB_PT_")]
    for parent in {c.bl_parent_id for c in subs if getattr(c, "bl_parent_id", "")}:
        labels = [c.bl_label for c in subs if getattr(c, "bl_parent_id", "") == parent]
        assert len(labels) == len(set(labels)), (parent, labels)
    assert bpy.types.FACELAB_PT_facelab_propagate.bl_label != bpy.types.FACELAB_PT_facelab_store.bl_label
    # Refine: the everyday settings in the sub-panel, the solver weights in Advanced
    refine_entry = next(e for e in SCENE_SETTINGS if e.attr == "facelab_refine")
    everyday = {d["name"] for d in panel_fields(refine_entry, False)}
    advanced = {d["name"] for d in panel_fields(refine_entry, True)}
    assert {"free_radius", "use_regions"} <= everyday and not everyday & advanced
    assert {"lambda_pos", "lambda_reg", "lambda_silh", "iterations"} <= advanced


def test_without_a_face_every_operator_explains(addon):
    empty_scene()
    for op in OPERATORS:
        if op in ("jump_to_frame", "bundles_from_clip", "sketch_onion_skin", "next_suggested_frame",
                  "reset_settings", "save_settings_defaults"):  # no face needed
            continue
        fn = getattr(bpy.ops.facelab, op)
        assert not fn.poll(), op
        with pytest.raises(RuntimeError, match=r"(?i)select|camera|training|sketch|Propagate"):
            fn()


def test_with_a_face_polls_and_messages(addon):
    scene = empty_scene()
    obj = small_face(scene)
    polls = {op: getattr(bpy.ops.facelab, op).poll() for op in OPERATORS}
    assert polls == {
        "new_lip_sketch": False,  # no camera yet
        "refine_lips": False,  # no camera yet
        "auto_regions": True,
        "mark_training_frame": True,
        "remove_training_frame": False,  # no training frames
        "jump_training_frame": False,
        "jump_to_frame": True,
        "propagate": False,  # no training frames
        "bake": True,
        "reconstruct_from_bundles": False,  # no shape keys (dataset), no bundles
        "bind_tracks": False,  # no tracking views yet
        "solve_performance": False,  # no tracking views yet
        "retarget": False,  # no creature picked
        "generate_correctives": False,  # no shape keys, no template rig picked
        "bundles_from_clip": False,  # no Movie Clip
        "review_toggle": False,  # nothing corrected yet
        "correction_heatmap": True,  # (all grey)
        "sketch_onion_skin": False,  # no sketch
        "next_suggested_frame": False,  # no Propagate yet
        "most_extrapolated_frame": False,
        "reset_settings": True,
        "save_settings_defaults": False,  # the bpy module: no add-on preferences
    }
    for op, msg in (("refine_lips", "camera"), ("new_lip_sketch", "camera"), ("propagate", "Correct at least one"),
                    ("remove_training_frame", "No training frames"), ("jump_training_frame", "No training frames"),
                    ("bind_tracks", "Add a view"), ("solve_performance", "Add a view"), ("retarget", "creature"),
                    ("reconstruct_from_bundles", "no shape keys"), ("generate_correctives", "no shape keys"),
                    ("bundles_from_clip", "No Movie Clip: load the footage"),
                    ("review_toggle", "No FaceLab correction"), ("next_suggested_frame", "FL suggest"),
                    ("most_extrapolated_frame", "Propagate first")):
        with pytest.raises(RuntimeError, match=msg):
            getattr(bpy.ops.facelab, op)()
    # a camera enables the sketch; Edit Mode disables Refine with a reason
    cam = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    scene.collection.objects.link(cam)
    scene.camera = cam
    assert bpy.ops.facelab.new_lip_sketch.poll()
    with pytest.raises(RuntimeError, match="No lip sketch yet"):
        bpy.ops.facelab.refine_lips()
    assert bpy.ops.facelab.new_lip_sketch() == {"FINISHED"}
    assert bpy.ops.facelab.refine_lips.poll()
    bpy.context.view_layer.objects.active = obj
    bpy.ops.object.mode_set(mode="EDIT")
    with pytest.raises(RuntimeError, match="Object Mode"):
        bpy.ops.facelab.refine_lips()
    bpy.ops.object.mode_set(mode="OBJECT")
    # Setup > Face wins over the active object
    other = small_face(scene)
    scene.facelab.face = obj
    assert common.face_object(bpy.context) == obj and bpy.context.active_object == other


def test_training_list_markers_jump_remove_undo(addon):
    scene = empty_scene()
    obj = small_face(scene)
    scene.frame_set(7)
    bpy.ops.ed.undo_push(message="before")
    assert bpy.ops.facelab.mark_training_frame() == {"FINISHED"}
    bpy.ops.ed.undo_push(message="Mark Training Frame")  # headless: the UI would push it
    assert [(t.frame, t.source) for t in obj.facelab.training_frames] == [(7, "marked")]  # sculpted in place
    assert [(m.name, m.frame) for m in scene.timeline_markers] == [("FL train 7", 7)]
    assert bpy.ops.facelab.mark_training_frame() == {"FINISHED"}  # again: the frame's record is renewed, not doubled
    assert [(t.frame, t.source) for t in obj.facelab.training_frames] == [(7, "marked")]
    assert [(m.name, m.frame) for m in scene.timeline_markers] == [("FL train 7", 7)]
    scene.frame_set(20)
    bpy.ops.facelab.mark_training_frame()
    obj.facelab.active_training_index = 0
    scene.frame_set(1)
    assert bpy.ops.facelab.jump_training_frame() == {"FINISHED"} and scene.frame_current == 7
    assert bpy.ops.facelab.jump_to_frame(frame=33) == {"FINISHED"} and scene.frame_current == 33
    assert bpy.ops.facelab.remove_training_frame() == {"FINISHED"}
    assert [t.frame for t in obj.facelab.training_frames] == [20]
    assert [m.frame for m in scene.timeline_markers] == [20]  # frame 7's marker went with it
    # undo goes back to the step after the first mark
    bpy.ops.ed.undo_push(message="Remove")
    bpy.ops.ed.undo()
    obj = bpy.data.objects["Face"]
    assert [t.frame for t in obj.facelab.training_frames] == [7]


def test_bake_runs_headless(addon, tmp_path):
    from facelab_addon.core.capture.pointcache import read_pc2

    scene = empty_scene()
    obj = small_face(scene)
    scene.frame_start, scene.frame_end = 1, 4
    out = tmp_path / "face.pc2"
    assert bpy.ops.facelab.bake(filepath=str(out), format="PC2") == {"FINISHED"}
    data = read_pc2(out)
    data = data[0] if isinstance(data, tuple) else data
    assert data.shape == (4, 36, 3)
    np.testing.assert_allclose(data[2], np.array([v.co[:] for v in obj.data.vertices]), atol=1e-6)
    with pytest.raises(RuntimeError, match="exists"):  # never overwrites silently
        bpy.ops.facelab.bake(filepath=str(out), format="PC2")


def test_property_defaults(addon):
    scene = empty_scene()
    obj = small_face(scene)
    s = scene.facelab
    assert s.face is None and s.sketch is None and s.fixed_group == "FL_fixed"
    assert len(obj.facelab.training_frames) == 0 and obj.facelab.active_training_index == 0
    item = obj.facelab.training_frames.add()
    assert (item.frame, item.shape_key, item.source) == (0, "", "sketch")
    # solver settings: the shot's, the paper's (Dinev §5) when the add-on preferences are not there
    r = ops.refine_settings(bpy.context)
    assert (r.iterations, r.lambda_pos, r.lambda_reg, r.lambda_silh, r.fixed_group) == (5, 0.1, 3.0, 1.0, "FL_fixed")
    assert shot_settings.preferences(bpy.context) is None  # the bpy module: FaceLab is not an enabled add-on
    p = bpy.types.AddonPreferences.bl_rna_get_subclass_py("FACELAB_AP_preferences")
    assert p.bl_idname == "facelab_addon"  # from a checkout; bl_ext.<repo>.facelab installed
    # operator options
    props = bpy.ops.facelab.propagate.get_rna_type().properties
    assert props["suggestions"].default == 3  # Start / End: the scene's range unless set (negative frames allowed)
    assert "starts at the scene's start" in props["frame_start"].description
    props = bpy.ops.facelab.auto_regions.get_rna_type().properties
    assert not props["replace"].default and not props["use_selection"].default
    props = bpy.ops.facelab.bake.get_rna_type().properties
    assert props["format"].default == "PC2" and not props["overwrite"].default


def test_redo_panels_start_from_the_scene_range(addon):
    """Propagate's and Reconstruct's Start / End show the frames they work on (not 1 / 250 on a 48-frame
    shot), and every new run starts from the scene's range again (SKIP_SAVE)."""
    scene = empty_scene()
    scene.frame_start, scene.frame_end = 7, 48

    class Given:
        def __init__(self, names):
            self.names = names

        def is_property_set(self, name):
            return name in self.names

    op = type("Op", (), {})()
    op.properties, op.frame_start, op.frame_end = Given({"frame_end"}), 1, 30  # End given, Start not
    common.fill_scene_range(op, scene)
    assert (op.frame_start, op.frame_end) == (7, 30)
    for name in ("propagate", "reconstruct_from_bundles"):
        props = getattr(bpy.ops.facelab, name).get_rna_type().properties
        assert props["frame_start"].is_skip_save and props["frame_end"].is_skip_save, name
    assert bpy.ops.facelab.propagate.get_rna_type().properties["suggestions"].is_skip_save


def _registered_properties():
    """``(owner, property)`` of every property FaceLab registers: its property groups (scene, object,
    preferences, generated settings) and its operators' options."""
    out = []
    for name in dir(bpy.types):
        if name.startswith("FACELAB_OT_"):
            rna = getattr(bpy.ops.facelab, getattr(bpy.types, name).bl_idname.split(".")[-1]).get_rna_type()
            out += [(name, p) for p in rna.properties if p.identifier != "rna_type"]
    groups = [c for base in (bpy.types.PropertyGroup, bpy.types.AddonPreferences) for c in base.__subclasses__()
              if c.__name__.startswith("FACELAB_") and c.is_registered]
    for cls in groups:
        out += [(cls.__name__, p) for p in cls.bl_rna.properties if p.identifier not in ("rna_type", "name")]
    return out


def test_every_registered_property_has_a_tooltip(addon):
    """Every property an artist can see says what it is (no empty tooltip), and no tooltip or operator
    description cites a paper (citations live in the docs)."""
    props = _registered_properties()
    assert len(props) > 100 and any(o == "FACELAB_PG_facelab_refine" for o, _ in props)
    def internal(p):  # never drawn as a field: lists (drawn as a list), their active row, the preferences'
        return (p.type == "COLLECTION" or p.identifier.startswith("active_") or p.identifier == "bl_idname"
                or p.is_hidden or (p.type == "POINTER" and p.fixed_type.identifier.startswith("FACELAB_PG")))

    empty = [f"{o}.{p.identifier}" for o, p in props if not p.description.strip() and not internal(p)]
    assert not empty, empty
    cited = re.compile(r"et al\.|§|\bpaper\b|\bBhat\b|\bDinev\b|Eq\. ?\d")
    texts = [(f"{o}.{p.identifier}", p.description) for o, p in props]
    texts += [(n, getattr(bpy.types, n).__doc__ or "") for n in dir(bpy.types)
              if n.startswith(("FACELAB_OT_", "FACELAB_PT_"))]
    assert not [n for n, t in texts if cited.search(t)], [n for n, t in texts if cited.search(t)]


def test_refine_and_live_refine_refuse_a_missing_camera_or_sketch_alike(addon):
    """Refine Lips and Live Refine share one sketch check: the same reason, the face first, then the camera, then
    the sketch."""
    scene = empty_scene()

    def refused(reason):
        for op in ("refine_lips", "live_refine"):
            assert not getattr(bpy.ops.facelab, op).poll(), op
            with pytest.raises(RuntimeError, match=re.escape(reason)):
                getattr(bpy.ops.facelab, op)()

    refused("Select the captured face mesh (or set it in FaceLab > Setup)")
    small_face(scene)
    refused("Set a scene camera first (the camera the sketch is drawn in)")
    scene.camera = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    scene.collection.objects.link(scene.camera)
    refused("No lip sketch yet: press New Lip Sketch and draw the inner lips in camera view")
    assert bpy.ops.facelab.new_lip_sketch() == {"FINISHED"}
    assert bpy.ops.facelab.refine_lips.poll() and bpy.ops.facelab.live_refine.poll()


def test_extrapolation_helpers(addon):
    from facelab_addon.blender.shapekeys import key_property_bulk

    assert panel.frame_ranges([1, 2, 3, 7, 9, 10]) == [(1, 3), (7, 7), (9, 10)]
    assert panel.frame_ranges([]) == []
    scene = empty_scene()
    obj = small_face(scene)
    assert keyed_extrapolation(obj) is None and panel.extrapolating_ranges(obj) == (None, 0)
    frames = np.arange(1, 21)
    score = np.where((frames >= 5) & (frames <= 8) | (frames == 15), 0.9, 0.1)
    obj[EXTRAPOLATION_PROP] = 0.0
    key_property_bulk(obj, f'["{EXTRAPOLATION_PROP}"]', frames, score)
    f, sc = keyed_extrapolation(obj)
    np.testing.assert_array_equal(f, frames)
    np.testing.assert_allclose(sc, score, atol=1e-6)
    assert panel.extrapolating_ranges(obj) == ([(5, 8), (15, 15)], 5)
    assert EXTRAPOLATING == 0.5


@pytest.mark.slow
def test_propagate_job_steps_and_cancels(ict, addon):
    """The modal Propagate's job, driven by hand (timers never run headless): it reports stages in
    order with growing progress, Esc between steps changes no key, and run to the end it writes keys."""
    from facelab_addon.blender.shapekeys import add_corrective_key, key_spike

    from .test_propagate_operator import FRAMES, TRAIN, build

    scene, obj, err, cap_w = build(ict)
    for f, w in zip(TRAIN, cap_w[np.searchsorted(FRAMES, TRAIN)]):
        scene.frame_set(f)
        key_spike(add_corrective_key(obj, f"Sculpt_{f}", -w * err), f)
        bpy.ops.facelab.mark_training_frame()
    bpy.ops.facelab.auto_regions()
    keys_before = [kb.name for kb in obj.data.shape_keys.key_blocks]

    settings = propagate_pipeline.PropagateSettings(suggestions=2)
    job = StepJob(propagate_pipeline.propagate_steps(scene, obj, FRAMES, settings))
    for _ in range(3):
        assert job.step()
    assert job.stage == "correcting the frames" and 0 < job.factor < 0.5
    job.cancel()  # Esc
    assert not job.step() and job.result is None
    assert [kb.name for kb in obj.data.shape_keys.key_blocks] == keys_before
    assert not any(m.name.startswith("FL suggest") for m in scene.timeline_markers)

    job = StepJob(propagate_pipeline.propagate_steps(scene, obj, FRAMES, settings))
    stages, factors = [], []
    while job.step():
        factors.append(job.factor)
        if not stages or stages[-1] != job.stage:
            stages.append(job.stage)
    assert stages == ["fitting", "correcting the frames", "writing the corrective keys"]
    assert factors == sorted(factors) and factors[-1] < 1.0
    summary = job.result
    assert summary.rank >= 1 and summary.keys == [kb.name for kb in obj.data.shape_keys.key_blocks
                                                  if kb.name.startswith("FL_Prop_")]
    assert len(summary.suggested) == 2 and ops_propagate.RUNNING["job"] is None


def test_every_registered_operator_explains_a_refusal(addon):
    """All FACELAB_OT_* registered (including ones other modules add later): on an empty scene, an
    operator that refuses says why through poll_message_set, never Blender's generic message."""
    empty_scene()
    names = sorted(n for n in dir(bpy.types) if n.startswith("FACELAB_OT_"))
    assert len(names) >= len(OPERATORS)
    for n in names:
        idname = getattr(bpy.types, n).bl_idname.split(".")[1]
        fn = getattr(bpy.ops.facelab, idname)
        if fn.poll():
            continue
        with pytest.raises(RuntimeError) as e:
            fn()
        assert "context is incorrect" not in str(e.value), f"{n}: poll() without poll_message_set"


def test_bake_job_matches_the_bake_and_cancels_cleanly(addon, tmp_path):
    from facelab_addon.blender import bakes
    from facelab_addon.blender.shapekeys import add_corrective_key, key_values_bulk
    from facelab_addon.core.capture.pointcache import read_mdd, read_pc2

    scene = empty_scene()
    obj = small_face(scene)
    add_corrective_key(obj, "Up", np.tile([0.0, 0.0, 0.1], (36, 1)))
    key_values_bulk(obj, ["Up"], np.arange(1, 7), np.linspace(0, 1, 6)[:, None])
    frames = np.arange(1, 7)
    scene.frame_set(3)
    for fmt, bake, read in (("PC2", bakes.bake_pc2, read_pc2), ("MDD", bakes.bake_mdd, read_mdd)):
        ref = bake(obj, frames, tmp_path / f"ref.{fmt}")
        got = StepJob(bake_pipeline.bake_steps(obj, frames, tmp_path / f"job.{fmt}",
                                               bake_pipeline.BakeSettings(format=fmt))).run().path
        assert ref.read_bytes() == got.read_bytes()  # the same file, header included
        data = read(got)
        data = data[0] if isinstance(data, tuple) else data
        np.testing.assert_allclose(data[:, 0, 2], np.linspace(0, 0.1, 6), atol=1e-6)
    # Esc after two frames: the existing file stays as it was, no temporary file is left, frame restored
    target = tmp_path / "keep.pc2"
    target.write_bytes(b"artist's file")
    job = StepJob(bake_pipeline.bake_steps(obj, frames, target, bake_pipeline.BakeSettings("PC2", overwrite=True)))
    assert job.step() and job.step() and job.stage == "baking frame 2" and job.factor == pytest.approx(2 / 6)
    job.cancel()
    assert target.read_bytes() == b"artist's file"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["job.MDD", "job.PC2", "keep.pc2", "ref.MDD", "ref.PC2"]
    assert scene.frame_current == 3


class RecordingLayout:
    """Stands in for bpy.types.UILayout (drawing needs a window): records every call, checks that
    every ``prop`` names a real property and every ``operator`` a registered operator."""

    def __init__(self, log=None):
        self.log = [] if log is None else log

    def __getattr__(self, name):
        def call(*args, **kw):
            self.log.append((name, args, kw))
            if name == "prop":
                data, prop = args[0], args[1]
                assert prop in data.bl_rna.properties, f"{type(data).__name__} has no property {prop!r}"
            if name == "operator":
                cat, op = args[0].split(".")
                assert hasattr(getattr(bpy.types, "FACELAB_OT_" + op, None), "bl_idname"), args[0]
                return type("OpProps", (), {})()  # takes any attribute, like OperatorProperties
            if name == "prop_search":
                assert args[1] in args[0].bl_rna.properties and args[3] in args[2].bl_rna.properties, args[1:4]
            if name == "template_list":
                assert hasattr(bpy.types, args[0]) and args[3] in args[2].bl_rna.properties and args[5] in args[4].bl_rna.properties
            return RecordingLayout(self.log)

        return call

    def texts(self, method=None):
        return [kw.get("text", "") for m, a, kw in self.log if method in (None, m)]


def draw(panel_cls, context):
    fake = type("FakePanel", (), {"layout": RecordingLayout()})()
    panel_cls.draw(fake, context)
    return fake.layout


def test_panels_draw_the_workflow(addon):
    from facelab_addon.blender.shapekeys import key_property_bulk

    scene = empty_scene()
    ctx = bpy.context
    # no face yet: the tab says so, sections still draw
    assert draw(bpy.types.FACELAB_PT_main, ctx).texts("label") == ["Select the captured face mesh"]
    assert "No face mesh selected" in draw(bpy.types.FACELAB_PT_propagate, ctx).texts("label")
    obj = small_face(scene)
    cam = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    scene.collection.objects.link(cam)
    scene.camera = cam
    setup = draw(bpy.types.FACELAB_PT_setup, ctx)
    assert "No plate: Camera > Background Images" in setup.texts("label")
    assert ("facelab.auto_regions",) in [a for m, a, kw in setup.log if m == "operator"]
    img = bpy.data.images.new("plate.png", 4, 4)
    bg = cam.data.background_images.new()
    bg.image = img
    assert "Plate: plate.png" in draw(bpy.types.FACELAB_PT_setup, ctx).texts("label")

    for f in (5, 30):
        scene.frame_set(f)
        bpy.ops.facelab.mark_training_frame()
    frames = np.arange(1, 41)
    obj[EXTRAPOLATION_PROP] = 0.0
    key_property_bulk(obj, f'["{EXTRAPOLATION_PROP}"]', frames, np.where((frames > 10) & (frames < 14), 0.9, 0.1))
    scene.timeline_markers.new("FL suggest 12", frame=12)
    scene.frame_set(12)
    lay = draw(bpy.types.FACELAB_PT_propagate, ctx)
    labels = lay.texts("label")
    assert "Training frames (2)" in labels
    assert "Uncertain or guessing on 3 frames:" in labels
    ops_drawn = [(a[0], kw.get("text")) for m, a, kw in lay.log if m == "operator"]
    # the current frame's prediction in words (0.9: uncertain), the score in the button's tooltip
    assert ("facelab.most_extrapolated_frame", "Prediction on this frame: uncertain") in ops_drawn
    tip = bpy.types.FACELAB_OT_most_extrapolated_frame.description(ctx, None)
    assert tip.startswith("Extrapolation 0.90 on this frame") and "reliable up to 0.5" in tip
    assert ("facelab.jump_to_frame", "11-13") in ops_drawn and ("facelab.jump_to_frame", "12") in ops_drawn
    assert ("facelab.propagate", None) in ops_drawn
    # the training list's rows
    ul = bpy.types.FACELAB_UL_training_frames
    row = RecordingLayout()
    ul.draw_item(None, ctx, row, obj.facelab, obj.facelab.training_frames[0], 0, None, "", 0)
    assert row.texts("label") == ["Frame 5", "sculpted mesh"]
    # a running job: a progress bar instead of the button
    job = StepJob(iter([("reading the capture", 3, 10)]))
    job.step()
    ops_propagate.RUNNING.update(job=job, label="Propagate 40 frames")
    try:
        lay = draw(bpy.types.FACELAB_PT_propagate, ctx)
        (bar,) = [kw for m, a, kw in lay.log if m == "progress"]
        assert bar["factor"] == pytest.approx(0.3) and "Esc" in bar["text"]
        assert "facelab.propagate" not in [a[0] for m, a, kw in lay.log if m == "operator"]
        assert not bpy.ops.facelab.propagate.poll() and not bpy.ops.facelab.bake.poll()
    finally:
        ops_propagate.RUNNING.update(job=None, label="")
    for p in ("FACELAB_PT_sketch", "FACELAB_PT_reconstruct", "FACELAB_PT_bake"):
        assert draw(getattr(bpy.types, p), ctx).log
    if bpy.types.FACELAB_PT_solve.poll(ctx):
        assert draw(bpy.types.FACELAB_PT_solve, ctx).log


def draw_everything(ctx) -> dict:
    """Draw every registered FaceLab panel (sub-panels included) whose poll passes; {panel: layout}."""
    out = {}
    for n in sorted(n for n in dir(bpy.types) if n.startswith("FACELAB_PT_")):
        cls = getattr(bpy.types, n)
        if hasattr(cls, "poll") and not cls.poll(ctx):
            continue
        out[n] = draw(cls, ctx)
    return out


def test_panels_draw_in_every_state(ict, addon):
    """No face, no camera, no regions, regions, training frames, after Propagate, capture shown: every
    panel draws (every prop / prop_search / operator it names exists), never a -1 placeholder."""
    from facelab_addon.blender.shapekeys import add_corrective_key, key_spike

    from .test_propagate_operator import FRAMES, TRAIN, build

    ctx = bpy.context
    empty_scene()
    states = {"no face": draw_everything(ctx)}
    assert "Select the captured face mesh" in states["no face"]["FACELAB_PT_main"].texts("label")
    scene, obj, err, cap_w = build(ict)
    scene.camera = None
    states["no camera, no regions"] = draw_everything(ctx)
    setup = states["no camera, no regions"]["FACELAB_PT_setup"]
    assert [(a[1], a[3]) for m, a, kw in setup.log if m == "prop_search"] == [("fixed_group", "vertex_groups")]
    assert "No group 'FL_fixed': separate mesh parts are held" in setup.texts("label")
    bpy.ops.facelab.auto_regions()
    states["regions"] = draw_everything(ctx)
    for f, w in zip(TRAIN[::-1], cap_w[np.searchsorted(FRAMES, TRAIN)][::-1]):  # marked out of order
        scene.frame_set(f)
        key_spike(add_corrective_key(obj, f"Sculpt_{f}", -w * err), f)
        bpy.ops.facelab.mark_training_frame()
    states["training frames"] = draw_everything(ctx)
    ul = bpy.types.FACELAB_UL_training_frames
    flags, order = ul.filter_items(None, ctx, obj.facelab, "training_frames")
    shown = sorted(range(len(order)), key=lambda i: order[i])
    assert [obj.facelab.training_frames[i].frame for i in shown] == sorted(TRAIN)  # the list reads by frame
    assert bpy.ops.facelab.propagate(suggestions=2) == {"FINISHED"}
    states["after Propagate"] = draw_everything(ctx)
    bpy.ops.facelab.review_toggle()
    states["capture shown"] = draw_everything(ctx)
    for state, panels in states.items():
        assert {"FACELAB_PT_main", "FACELAB_PT_setup", "FACELAB_PT_review", "FACELAB_PT_bake"} <= set(panels), state
        for name, lay in panels.items():
            texts = [str(t) for t in lay.texts()]
            assert not any(t == "-1" or t.endswith(" -1") for t in texts), (state, name)
    prop = states["after Propagate"]["FACELAB_PT_propagate"]
    assert any(str(kw.get("text", "")).startswith("Prediction on this frame: ") for m, a, kw in prop.log
               if m == "operator")
    review_ops = [a[0] for m, a, kw in states["after Propagate"]["FACELAB_PT_review"].log if m == "operator"]
    assert {"facelab.review_toggle", "facelab.correction_heatmap", "facelab.sketch_onion_skin",
            "facelab.next_suggested_frame", "facelab.most_extrapolated_frame"} <= set(review_ops)
    # solve / reconstruct: bind frames and the annotation view are toggles, not -1
    solve = states["after Propagate"]["FACELAB_PT_solve"]
    drawn = [a[1] for m, a, kw in solve.log if m == "prop"]
    assert "bind_current" in drawn and "bind_frame" not in drawn and "annotation_view" not in drawn
    # the solver weights are in the closed Advanced sub-panel, not in the Solve panel
    from facelab_addon.ui.panel_solve import SOLVE_ADVANCED

    advanced = [a[1] for m, a, kw in states["after Propagate"]["FACELAB_PT_solve_advanced"].log if m == "prop"]
    assert advanced == list(SOLVE_ADVANCED) and not set(SOLVE_ADVANCED) & set(drawn)
    assert "use_annotation" in drawn and "frame_start" not in drawn  # Scene Range: "Scene: 1-40" instead
    assert f"Scene: {scene.frame_start}-{scene.frame_end}" in solve.texts("label")
    scene.facelab_solve.bind_current = False
    assert scene.facelab_solve.bind_frame == scene.frame_current
    scene.facelab_solve.use_annotation = True
    assert scene.facelab_solve.annotation_view == 0
    solve = draw(bpy.types.FACELAB_PT_solve, ctx)
    drawn = [a[1] for m, a, kw in solve.log if m == "prop"]
    assert "bind_frame" in drawn and "annotation_view" in drawn
    recon = [a[1] for m, a, kw in states["after Propagate"]["FACELAB_PT_reconstruct"].log if m == "prop"]
    assert "bind_scene_start" in recon and "bind_frame" not in recon


def test_reconstruct_buttons_poll_with_reasons(addon):
    """Reconstruct, Generate Correctives and Bundles from Tracking are disabled until they can run."""
    scene = empty_scene()
    obj = small_face(scene)
    for k in ("Basis", "A", "B", "C", "D"):
        obj.shape_key_add(name=k, from_mix=False)
    with pytest.raises(RuntimeError, match="No bundles: select the bundle empties"):
        bpy.ops.facelab.reconstruct_from_bundles()
    e = bpy.data.objects.new("B00", None)
    scene.collection.objects.link(e)
    e.select_set(True)
    assert bpy.ops.facelab.reconstruct_from_bundles.poll()
    scene.facelab_recon.bundle_source = "COLLECTION"
    with pytest.raises(RuntimeError, match="pick a Collection"):
        bpy.ops.facelab.reconstruct_from_bundles()
    scene.facelab_recon.bundle_collection = bpy.data.collections.new("Bundles")
    scene.facelab_recon.bundle_collection.objects.link(e)
    assert bpy.ops.facelab.reconstruct_from_bundles.poll()
    with pytest.raises(RuntimeError, match="Pick the template Rig"):
        bpy.ops.facelab.generate_correctives()
    rig = small_face(scene)
    scene.facelab.face = obj
    scene.facelab_recon.rig_object = rig
    with pytest.raises(RuntimeError, match="has no shape keys: pick the mesh holding the template rig"):
        bpy.ops.facelab.generate_correctives()
    rig.shape_key_add(name="Basis")
    rig.shape_key_add(name="smile")
    assert bpy.ops.facelab.generate_correctives.poll()
    with pytest.raises(RuntimeError, match="No Movie Clip: load the footage"):
        bpy.ops.facelab.bundles_from_clip()
