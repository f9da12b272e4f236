"""Settings stored with the shot: scene properties generated from the pipelines' settings dataclasses,
saved in the .blend, read by the operators, filled from the preferences' defaults for new scenes, a
new settings class added with one line (property, sub-panel, CLI flag)."""

import argparse
import types
from dataclasses import dataclass

import bpy
import pytest

import facelab_addon
from facelab_addon.pipeline.propagate import PropagateSettings
from facelab_addon.pipeline.refine import RefineSettings
from facelab_addon.pipeline.regions import RegionSettings
from facelab_addon.pipeline import shot_settings
from facelab_addon.pipeline.settings import describe, setting
from facelab_addon.pipeline.shot_settings import SCENE_SETTINGS, Entry
from facelab_addon.ui import ops, prefs

from .test_ui import RecordingLayout, empty_scene, small_face

pytestmark = pytest.mark.blender


def test_every_declared_field_is_a_scene_property(addon):
    scene = empty_scene()
    assert {e.cls for e in SCENE_SETTINGS} >= {RefineSettings, RegionSettings, PropagateSettings}
    for e in SCENE_SETTINGS:
        grp = getattr(scene, e.attr)
        rna = grp.bl_rna.properties
        for d in describe(e.cls):
            if d["name"] in shot_settings.SHARED:  # stored once, in Setup
                assert d["name"] not in rna and d["name"] in scene.facelab.bl_rna.properties
                continue
            p = rna[d["name"]]
            assert p.description == d["description"] and p.name.startswith(d["label"])
            if d["type"] in (int, float):
                assert p.default == pytest.approx(d["default"])
                if d["min"] is not None:
                    assert p.hard_min == pytest.approx(d["min"])
                if d["max"] is not None:
                    assert p.hard_max == pytest.approx(d["max"])
            if d["choices"]:
                assert [i.identifier for i in p.enum_items] == [c[0] for c in d["choices"]]
    assert scene.facelab_regions.bl_rna.properties["lip_width"].name == "Lip Band (mouth widths)"
    # the settings the operators get are the dataclass's (exact decimals, not 32-bit floats)
    assert ops.refine_settings(bpy.context) == RefineSettings()
    assert shot_settings.scene_settings(scene, RegionSettings, replace=True) == RegionSettings(replace=True)


def test_settings_are_saved_with_the_shot_and_used(addon, tmp_path):
    scene = empty_scene()
    small_face(scene)
    scene.facelab_refine.lambda_silh = 2.5
    scene.facelab_refine.iterations = 7
    scene.facelab.fixed_group = "Teeth"
    scene.facelab_propagate.suggestions = 6
    path = tmp_path / "shot.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.wm.open_mainfile(filepath=str(path))
    r = ops.refine_settings(bpy.context)
    assert (r.lambda_silh, r.iterations, r.fixed_group, r.lambda_pos) == (2.5, 7, "Teeth", 0.1)
    assert shot_settings.scene_settings(bpy.context.scene, PropagateSettings).suggestions == 6
    # Reset: back to the defaults (the preferences', here the dataclass's)
    assert bpy.ops.facelab.reset_settings(target="facelab_refine") == {"FINISHED"}
    assert ops.refine_settings(bpy.context) == RefineSettings(fixed_group="Teeth")
    with pytest.raises(RuntimeError, match="No FaceLab settings called 'nope'"):
        bpy.ops.facelab.reset_settings(target="nope")


def test_new_scenes_take_the_preferences_defaults(addon, monkeypatch):
    empty_scene()
    scene = bpy.data.scenes.new("Shot")  # (a loaded file's scenes are filled on load)
    entry = shot_settings.entry_for("facelab_refine")
    mine = dict(iterations=9, lambda_pos=0.2, lambda_reg=4.0, lambda_silh=1.5)
    stored = {d["name"]: d["default"] for d in shot_settings.fields(entry)} | mine
    fake = types.SimpleNamespace(facelab_refine=types.SimpleNamespace(**stored))
    monkeypatch.setattr(shot_settings, "preferences", lambda context=None: fake)
    assert shot_settings.preference_defaults(entry) == stored
    r = shot_settings.scene_settings(scene, RefineSettings)  # first use: filled from the preferences
    assert (r.iterations, r.lambda_reg) == (9, 4.0)
    fake.facelab_refine.iterations = 3  # preferences changed later: this shot keeps its own
    assert shot_settings.scene_settings(scene, RefineSettings).iterations == 9
    other = bpy.data.scenes.new("Other")
    other.facelab_refine.lambda_silh = 3.0  # an edit makes the values the shot's own
    r = shot_settings.scene_settings(other, RefineSettings)
    assert (r.lambda_silh, r.iterations) == (3.0, 5)


@dataclass
class _StorageSettings:
    """How corrections are stored (a stand-in for a settings class another step adds)."""

    tolerance: float = setting(0.05, label="Tolerance", min=0.0, max=5.0, unit="mm",
                               description="Largest error the compression may leave, in mm")
    sparse: bool = setting(True, label="Sparse Keys", description="Store only the vertices that move")
    max_keys: int = setting(8, label="Max Keys", min=1, max=64, description="At most this many keys")
    codec: str = setting("keys", label="Storage", description="Where corrections go",
                         choices=(("keys", "Shape Keys", ""), ("cache", "Point Cache", "")))
    internal: int = 3


def test_a_settings_class_is_added_with_one_line(addon, monkeypatch):
    facelab_addon.unregister()
    monkeypatch.setattr(shot_settings, "SCENE_SETTINGS", SCENE_SETTINGS + (
        Entry("facelab_example", _StorageSettings, "FACELAB_PT_propagate", ("propagate",)),))
    facelab_addon.register()
    try:
        scene = empty_scene()
        small_face(scene)
        grp = scene.facelab_example
        assert grp.bl_rna.properties["tolerance"].name == "Tolerance (mm)" and "internal" not in grp.bl_rna.properties
        grp.tolerance, grp.codec = 0.2, "cache"
        assert shot_settings.scene_settings(scene, _StorageSettings) == _StorageSettings(tolerance=0.2, codec="cache")
        # its sub-panel under Train & Propagate draws every field
        sub = bpy.types.FACELAB_PT_facelab_example
        assert sub.bl_parent_id == "FACELAB_PT_propagate"
        fake = type("P", (), {"layout": RecordingLayout()})()
        sub.draw(fake, bpy.context)
        drawn = [a[1] for m, a, kw in fake.layout.log if m == "prop"]
        assert drawn == ["tolerance", "sparse", "max_keys", "codec"]
        # and the propagate command's flags
        from facelab_addon.cli import build_parser

        args = build_parser().parse_args(["propagate", "x.blend", "--tolerance", "0.5", "--no-sparse",
                                          "--codec", "keys", "--lip-width", "0.2"])
        got = shot_settings.apply_flags(args, scene, "propagate")
        assert got["facelab_example"] == dict(tolerance=0.5, sparse=False, max_keys=8, codec="keys")
        assert got["facelab_regions"]["lip_width"] == 0.2 and scene.facelab_regions.lip_width == pytest.approx(0.2)
        args = build_parser().parse_args(["propagate", "x.blend", "--max-keys", "0"])
        with pytest.raises(ValueError, match="--max-keys 0: below the minimum 1"):
            shot_settings.apply_flags(args, scene, "propagate")
        with pytest.raises(SystemExit):
            build_parser().parse_args(["propagate", "x.blend", "--codec", "zip"])
    finally:
        facelab_addon.unregister()
        monkeypatch.undo()
        facelab_addon.register()
    assert not hasattr(bpy.types.Scene, "facelab_example")


def test_settings_subpanels_draw(addon):
    scene = empty_scene()
    ctx = bpy.context
    for e in SCENE_SETTINGS:
        fake = type("P", (), {"layout": RecordingLayout()})()
        getattr(bpy.types, f"FACELAB_PT_{e.attr}").draw(fake, ctx)
        props = [a[1] for m, a, kw in fake.layout.log if m == "prop"]
        ops_ = [a[0] for m, a, kw in fake.layout.log if m == "operator"]
        assert ops_ == ["facelab.reset_settings", "facelab.save_settings_defaults"]
        # every field is drawn once: the everyday ones here, the others in the closed Advanced sub-panel
        adv = getattr(bpy.types, f"FACELAB_PT_{e.attr}_advanced", None)
        if adv is not None:
            fake = type("P", (), {"layout": RecordingLayout()})()
            adv.draw(fake, ctx)
            props += [a[1] for m, a, kw in fake.layout.log if m == "prop"]
        assert sorted(props) == sorted(d["name"] for d in shot_settings.fields(e)), e.attr
    # flags of a command without FaceLab settings: none added
    p = argparse.ArgumentParser()
    shot_settings.add_flags(p, "no-such-command")
    assert [a.dest for a in p._actions] == ["help"]
    assert scene is not None
