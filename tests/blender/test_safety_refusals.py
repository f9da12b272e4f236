"""Operators and pipelines check before they change anything (issue 13, part C), on small meshes:
a face linked from a library (or an override whose mesh is the library's) is refused with its name
and the fix, output paths are checked before a bake starts, frame ranges are checked (negative
frames honoured), FaceLab removes only the keys it recorded as its own, and what an operator
changed on the modifiers is put back on cancel or failure. Each test also checks the artist's data
is intact afterwards."""

import os

import bpy
import numpy as np
import pytest

from facelab_addon.blender.bakes import bake_destination
from facelab_addon.blender.objects import ModifierState, NotEditableError, require_editable
from facelab_addon.blender.ownership import owned_keys
from facelab_addon.blender.shapekeys import add_corrective_key, add_keys_from_deltas, key_spike, remove_keys
from facelab_addon.core.errors import FaceLabError, OutputError
from facelab_addon.names import OWNED_KEYS_PROP, PROPAGATE_PREFIX, SOLVE_PREFIX
from facelab_addon.pipeline.bake import BakeSettings, bake
from facelab_addon.pipeline.correctives import write_corrective_keys
from facelab_addon.pipeline.frames import MAX_FRAME, check_frames, frame_range

pytestmark = pytest.mark.blender


def grid(name="Face", n=6):
    """A small animated grid mesh object linked to the scene (n*n vertices)."""
    from facelab_addon.blender.scene import new_mesh_object

    x, y = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n))
    V = np.c_[x.ravel(), y.ravel(), np.zeros(n * n)]
    quads = [[i * n + j, i * n + j + 1, (i + 1) * n + j + 1, (i + 1) * n + j]
             for i in range(n - 1) for j in range(n - 1)]
    offs = np.arange(0, 4 * len(quads) + 1, 4)
    ob = new_mesh_object(name, V, poly_verts=np.ravel(quads), poly_offsets=offs)
    bpy.context.view_layer.update()
    return ob


def key_coords(obj, name):
    kb = obj.data.shape_keys.key_blocks[name]
    c = np.empty(len(obj.data.vertices) * 3, np.float32)
    kb.data.foreach_get("co", c)
    return c.reshape(-1, 3)


@pytest.fixture
def linked_face(addon, tmp_path):
    """'Face' (with a Basis and an artist key 'Smile') linked from a library .blend into a fresh scene."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    obj = grid()
    obj.shape_key_add(name="Basis")
    obj.shape_key_add(name="Smile")
    lib = tmp_path / "lib.blend"
    bpy.data.libraries.write(str(lib), {obj}, fake_user=True)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    with bpy.data.libraries.load(str(lib), link=True) as (src, dst):
        dst.objects = ["Face"]
    ob = dst.objects[0]
    bpy.context.scene.collection.objects.link(ob)
    bpy.context.view_layer.objects.active = ob
    return ob


# --------------------------------------------------------------------------- library-linked faces
def test_linked_face_is_refused_by_every_writer(linked_face, tmp_path):
    from facelab_addon.pipeline.propagate import propagate_steps
    from facelab_addon.pipeline.reconstruct import ReconstructSettings, reconstruct_from_bundles
    from facelab_addon.pipeline.regions import auto_regions
    from facelab_addon.pipeline.solve import SolveSettings, solve_performance
    from facelab_addon.pipeline.training import add_corrected_frame

    ob, scene = linked_face, bpy.context.scene
    before = key_coords(ob, "Smile").copy()
    with pytest.raises(NotEditableError, match=r"Propagate cannot change 'Face'.*lib\.blend.*Make Local"):
        propagate_steps(scene, ob, np.arange(1, 11))
    with pytest.raises(NotEditableError, match="Auto Regions cannot change 'Face'"):
        auto_regions(ob)
    with pytest.raises(NotEditableError, match="Mark Corrected Frame cannot change 'Face'"):
        add_corrected_frame(scene, ob, 3, np.zeros((len(ob.data.vertices), 3)))
    with pytest.raises(NotEditableError, match="Solve cannot change 'Face'"):
        solve_performance(scene, ob, SolveSettings())
    with pytest.raises(NotEditableError, match="Reconstruct cannot change 'Face'"):
        reconstruct_from_bundles(scene, ob, ReconstructSettings())
    # the operators report the refusal and change nothing
    with pytest.raises(RuntimeError, match="Auto Regions cannot change 'Face'.*Make Local"):
        bpy.ops.facelab.auto_regions()
    assert list(ob.data.shape_keys.key_blocks.keys()) == ["Basis", "Smile"]
    assert not ob.vertex_groups and not ob.facelab.training_frames
    np.testing.assert_array_equal(key_coords(ob, "Smile"), before)


def test_linked_creature_and_rig_are_refused(linked_face):
    from facelab_addon.pipeline.reconstruct import CorrectiveSettings, generate_correctives
    from facelab_addon.pipeline.retarget import RetargetSettings, retarget

    actor = grid("Actor")
    with pytest.raises(NotEditableError, match="Retarget cannot change 'Face'"):
        retarget(bpy.context.scene, actor, linked_face, RetargetSettings())
    with pytest.raises(NotEditableError, match="Generate Correctives cannot change 'Face'"):
        generate_correctives(bpy.context.scene, actor, CorrectiveSettings(rig_object=linked_face, combinations="a+b"))


def test_refine_on_a_linked_face_is_refused(linked_face):
    from facelab_addon.pipeline.refine import refine

    cam = bpy.data.objects.new("Cam", bpy.data.cameras.new("Cam"))
    bpy.context.scene.collection.objects.link(cam)
    bpy.context.scene.camera = cam
    with pytest.raises(NotEditableError, match="Refine Lips cannot change 'Face'"):
        refine(bpy.context.scene, linked_face, 1)
    assert list(linked_face.data.shape_keys.key_blocks.keys()) == ["Basis", "Smile"]


def test_override_with_library_mesh_is_refused_and_local_copy_accepted(linked_face):
    ov = linked_face.override_create(remap_local_usages=True)
    assert ov.library is None and ov.data.library is not None
    with pytest.raises(NotEditableError, match="mesh data is linked from the library"):
        require_editable(ov, "Propagate")
    assert require_editable(grid("Plain")).name == "Plain"


# --------------------------------------------------------------------------- ownership of keys
def test_only_recorded_keys_are_replaced(addon):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    obj = grid()
    n = len(obj.data.vertices)
    rng = np.random.default_rng(0)
    mine = add_corrective_key(obj, "FL_Prop_MyFix", rng.normal(0, 0.01, (n, 3)))  # through FaceLab's API...
    obj.data.shape_keys[OWNED_KEYS_PROP] = []  # ...but made by the artist: not recorded
    obj.shape_key_add(name="FL_Solve_Sculpt")  # named by hand in the Shape Keys panel
    artist = key_coords(obj, "FL_Prop_MyFix").copy()
    D = np.zeros((4, n, 3))
    D[:, 3, 2] = [0.0, 0.01, 0.02, 0.03]
    first = write_corrective_keys(obj, PROPAGATE_PREFIX, D, np.arange(1, 5))
    assert first == ["FL_Prop_00"] and owned_keys(obj, PROPAGATE_PREFIX) == ["FL_Prop_00"]
    second = write_corrective_keys(obj, PROPAGATE_PREFIX, 2 * D, np.arange(1, 5))
    assert second == ["FL_Prop_00"]  # the old one was FaceLab's: replaced, not FL_Prop_00.001
    assert remove_keys(obj, SOLVE_PREFIX) == 0  # the artist's FL_Solve_Sculpt is not FaceLab's
    keys = obj.data.shape_keys.key_blocks
    assert {"FL_Prop_MyFix", "FL_Solve_Sculpt", "FL_Prop_00"} <= set(keys.keys())
    np.testing.assert_array_equal(key_coords(obj, "FL_Prop_MyFix"), artist)
    assert mine.name == "FL_Prop_MyFix"
    assert remove_keys(obj, PROPAGATE_PREFIX) == 1 and "FL_Prop_MyFix" in keys.keys()


def test_keys_of_older_files_are_adopted_by_their_exact_names(addon):
    """A file from before the registry: FL_Prop_00 / FL_Refine_0012 as FaceLab named them are FaceLab's,
    FL_Prop_MyFix is not; the registry is created with the adopted names."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    obj = grid()
    for name in ("Basis", "FL_Prop_00", "FL_Prop_01.001", "FL_Prop_MyFix", "FL_Refine_0012"):
        kb = obj.shape_key_add(name=name)
        if name.startswith("FL_Prop_0"):  # as FaceLab set them up (an artist's FL_Prop_00 is not adopted)
            kb.slider_min, kb.slider_max = -10.0, 10.0
    key_spike(obj.data.shape_keys.key_blocks["FL_Refine_0012"], 12)
    assert obj.data.shape_keys.get(OWNED_KEYS_PROP) is None
    assert sorted(owned_keys(obj)) == ["FL_Prop_00", "FL_Prop_01.001", "FL_Refine_0012"]
    n = len(obj.data.vertices)
    names = add_keys_from_deltas(obj, "FL_Solve_", np.ones((1, n, 3)))  # creates the registry: adopts first
    assert sorted(obj.data.shape_keys[OWNED_KEYS_PROP]) == ["FL_Prop_00", "FL_Prop_01.001", "FL_Refine_0012",
                                                             "FL_Solve_00"] and names == ["FL_Solve_00"]
    assert remove_keys(obj, PROPAGATE_PREFIX) == 2
    assert list(obj.data.shape_keys.key_blocks.keys()) == ["Basis", "FL_Prop_MyFix", "FL_Refine_0012", "FL_Solve_00"]


def test_an_artists_key_of_a_legacy_name_is_not_adopted(addon):
    """A file FaceLab never touched: the artist's FL_Prop_00 (slider 0..1) and FL_Refine_0012 (not keyed
    0, 1, 0 around frame 12) keep their names and stay the artist's; FaceLab writes under free names."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    obj = grid()
    for name in ("Basis", "FL_Prop_00", "FL_Refine_0012"):
        obj.shape_key_add(name=name)
    kb = obj.data.shape_keys.key_blocks["FL_Refine_0012"]
    kb.value = 0.5
    kb.keyframe_insert("value", frame=12)
    assert owned_keys(obj) == []
    names = add_keys_from_deltas(obj, PROPAGATE_PREFIX, np.ones((2, len(obj.data.vertices), 3)))
    assert names == ["FL_Prop_00.001", "FL_Prop_01"]
    assert sorted(owned_keys(obj)) == names
    assert remove_keys(obj, PROPAGATE_PREFIX) == 2 and remove_keys(obj, "FL_Refine_") == 0
    assert list(obj.data.shape_keys.key_blocks.keys()) == ["Basis", "FL_Prop_00", "FL_Refine_0012"]


# --------------------------------------------------------------------------- frame ranges
def test_frame_ranges_are_checked_and_negative_frames_honoured(addon):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 1, 20
    np.testing.assert_array_equal(frame_range(scene), np.arange(1, 21))
    np.testing.assert_array_equal(frame_range(scene, -5, 2), np.arange(-5, 3))  # negative: a real frame
    np.testing.assert_array_equal(frame_range(scene, -1, None), np.arange(-1, 21))
    with pytest.raises(FaceLabError, match=r"Propagate: the frame range 30-10 ends before it starts; set End >= Start"):
        frame_range(scene, 30, 10, "Propagate")
    with pytest.raises(FaceLabError, match="outside Blender's frames"):
        frame_range(scene, 1, MAX_FRAME + 10)
    with pytest.raises(FaceLabError, match="not increasing"):
        check_frames([10, 9, 8], "Propagate")
    with pytest.raises(FaceLabError, match="gaps"):
        check_frames([1, 2, 5], "Propagate", consecutive=True)
    with pytest.raises(FaceLabError, match="no frames"):
        check_frames([], "Propagate")
    np.testing.assert_array_equal(check_frames(np.arange(-3, 4), consecutive=True), np.arange(-3, 4))


def test_solve_panel_range_honours_negative_frames(addon):
    from facelab_addon.pipeline.shot_settings import retarget_settings, solve_settings

    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 1, 20
    s = scene.facelab_solve
    assert s.use_scene_range and (s.frame_start, s.frame_end) == (1, 20)
    assert (solve_settings(scene).frame_start, solve_settings(scene).frame_end) == (1, 20)
    s.frame_start = -5  # a script or the CLI sets the range: the scene range is off, -5 is kept
    assert not s.use_scene_range and (s.frame_start, s.frame_end) == (-5, 20)
    assert (retarget_settings(scene).frame_start, retarget_settings(scene).frame_end) == (-5, 20)
    s.use_scene_range = True
    assert (s.frame_start, s.frame_end) == (1, 20)


def test_propagate_operator_refuses_a_reversed_range(addon):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    obj = grid()
    bpy.context.view_layer.objects.active = obj
    obj.facelab.training_frames.add().frame = 3
    with pytest.raises(RuntimeError, match="Propagate: the frame range 30-10 ends before it starts"):
        bpy.ops.facelab.propagate(frame_start=30, frame_end=10)
    assert obj.data.shape_keys is None and not obj.vertex_groups


# --------------------------------------------------------------------------- output paths
def test_output_paths_are_checked_before_a_bake(addon, tmp_path):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    obj = grid()
    assert not bpy.data.filepath
    with pytest.raises(OutputError, match=r"relative to the \.blend, but the \.blend is not saved yet; save it first"):
        bake(obj, np.arange(1, 4), "//face.pc2")
    with pytest.raises(OutputError, match="is a relative path, which would be written into the folder Blender"):
        bake(obj, np.arange(1, 4), "face.pc2")
    blocker = tmp_path / "notafolder"
    blocker.write_text("artist notes")
    with pytest.raises(OutputError, match="is a file, not a folder"):
        bake(obj, np.arange(1, 4), blocker / "sub" / "face.pc2")
    with pytest.raises(OutputError, match="it is a folder. Give a file name"):
        bake(obj, np.arange(1, 4), tmp_path)
    with pytest.raises(OutputError, match="Cannot write '/proc/facelab_i13c/face.pc2'"):
        bake_destination("/proc/facelab_i13c/face.pc2")
    ro = tmp_path / "ro.pc2"
    ro.write_bytes(b"keep")
    os.chmod(ro, 0o444)
    if not os.access(ro, os.W_OK):  # (root may write anyway)
        with pytest.raises(OutputError, match="read-only"):
            bake(obj, np.arange(1, 4), ro, BakeSettings(overwrite=True))
    assert blocker.read_text() == "artist notes" and ro.read_bytes() == b"keep"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notafolder", "ro.pc2"]  # no probe or partial file left
    # a good path: absolute, parents created by the writer
    r = bake(obj, np.arange(1, 4), tmp_path / "new" / "face.pc2")
    assert r.path == tmp_path / "new" / "face.pc2" and r.path.is_file()
    # '//' beside a saved .blend
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "shot.blend"))
    assert bake_destination("//out/face.pc2") == tmp_path / "out" / "face.pc2"


# --------------------------------------------------------------------------- restoring modifiers
def test_modifier_state_puts_back_modes_and_removes_what_was_added(addon, tmp_path):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    obj = grid()
    md = obj.modifiers.new("Capture", "MESH_CACHE")
    md.cache_format, md.filepath = "PC2", str(tmp_path / "capture.pc2")
    other = obj.modifiers.new("Smooth", "SMOOTH")
    state = ModifierState(obj)
    md.deform_mode = "INTEGRATE"
    other.show_viewport = other.show_render = False
    baked = tmp_path / "Face_capture.pc2"
    baked.write_bytes(b"baked by FaceLab")
    added = obj.modifiers.new("FL capture", "MESH_CACHE")
    added.filepath = str(baked)
    undone = state.restore()
    assert [m.name for m in obj.modifiers] == ["Capture", "Smooth"]
    assert md.deform_mode == "OVERWRITE" and other.show_viewport and other.show_render
    assert not baked.exists() and len(undone) == 4
    assert state.restore() == []  # nothing left to undo


def test_solve_panel_settings_default_to_the_pipeline_defaults(addon):
    """Every Solve setting declared with ``pipeline.settings.setting``, and every solver option the panel
    offers, reaches the pipeline from the panel with the pipeline's default (which is the core's: a field
    missing from the panel, or a panel default drifting from the core's, would silently run at a different
    value); likewise for Retarget."""
    from dataclasses import fields

    from facelab_addon.pipeline.retarget import RetargetSettings
    from facelab_addon.pipeline.solve import SolveSettings
    from facelab_addon.pipeline.shot_settings import retarget_settings, solve_settings

    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    got, want = solve_settings(scene), SolveSettings()
    declared = [f.name for f in fields(SolveSettings) if f.metadata.get("facelab")]
    assert {"anchor_weight", "lip_passes", "lip_line_weight", "lip_damping"} <= set(declared)
    options = ("bundles", "use_contours", "annotation_view", "use_corrective", "sliding", "weight_min", "weight_max",
               "marker_weight", "contour_weight", "existing_animation")
    for name in declared + list(options):
        assert getattr(got, name) == pytest.approx(getattr(want, name)), name
    got, want = retarget_settings(scene), RetargetSettings()
    for name in ("correspondence", "lip_sync", "lip_threshold", "existing_animation"):
        assert getattr(got, name) == pytest.approx(getattr(want, name)), name
    scene.facelab_solve.lip_passes = 0
    assert solve_settings(scene).lip_passes == 0
