"""The version helpers of facelab_addon/blender/compat.py do the same thing on every supported Blender.

``bash scripts/test.sh`` runs these on the oldest (4.5 LTS) and the newest (5.3) supported ``bpy``.
"""

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import bpy
import numpy as np
import pytest

from facelab_addon.blender import compat

ROOT = Path(__file__).resolve().parents[2]

pytestmark = pytest.mark.blender


def test_channelbag_is_created_once_and_keys_evaluate(empty_scene):
    obj = bpy.data.objects.new("Empty", None)
    empty_scene.collection.objects.link(obj)
    ad = obj.animation_data_create()
    ad.action = bpy.data.actions.new("Act")
    assert compat.anim_data_channelbag(ad) is None  # no slot assigned yet, nothing created
    cb = compat.anim_data_channelbag(ad, create=True)
    assert ad.action_slot is not None and compat.anim_data_channelbag(ad) == cb
    assert compat.action_channelbag(ad.action, ad.action_slot, create=True) == cb  # the same one, not a second
    assert len(ad.action.layers) == 1 and len(ad.action.layers[0].strips) == 1

    fc = cb.fcurves.new("location", index=2)
    fc.keyframe_points.add(2)
    fc.keyframe_points.foreach_set("co", [1.0, 0.0, 11.0, 5.0])
    for k in fc.keyframe_points:
        k.interpolation = "LINEAR"
    fc.update()
    empty_scene.frame_set(6)
    assert obj.location.z == pytest.approx(2.5)  # halfway from 0 at frame 1 to 5 at frame 11
    assert compat.action_channelbag(None, None) is None


def test_grease_pencil_data_makes_grease_pencil_objects(empty_scene):
    data = compat.grease_pencil_data()
    before = len(data)
    gp = data.new("Sketch")
    assert len(data) == before + 1 and isinstance(gp, compat.grease_pencil_struct())
    obj = bpy.data.objects.new("Sketch", gp)
    assert obj.type == compat.GREASE_PENCIL_TYPE
    layer = gp.layers.new("Upper lip")
    assert [lay.name for lay in gp.layers] == ["Upper lip"] and layer.frames.new(3).frame_number == 3


def test_scene_annotation_round_trip(empty_scene):
    assert compat.scene_annotation(empty_scene) is None
    ann = compat.annotation_data().new("Annotations")
    compat.set_scene_annotation(empty_scene, ann)
    assert compat.scene_annotation(empty_scene) == ann
    layer = ann.layers.new("Upper lip")
    assert layer.info == "Upper lip" and [lay.info for lay in compat.scene_annotation(empty_scene).layers] == [
        "Upper lip"]


def test_node_tree_and_material_fill(empty_scene):
    world = bpy.data.worlds.new("World")
    nodes = compat.node_tree(world).nodes
    assert "Background" in nodes
    mat = bpy.data.materials.new("Skin")
    assert "Principled BSDF" in compat.node_tree(mat).nodes

    gp_mat = bpy.data.materials.new("Ink")
    bpy.data.materials.create_gpencil_data(gp_mat)
    gp_mat.grease_pencil.fill_color = (0.2, 0.4, 0.6, 1.0)
    compat.set_gp_material_fill(gp_mat.grease_pencil, True)
    assert compat.gp_material_fill_shown(gp_mat.grease_pencil)
    compat.set_gp_material_fill(gp_mat.grease_pencil, False)
    assert not compat.gp_material_fill_shown(gp_mat.grease_pencil)
    assert np.allclose(gp_mat.grease_pencil.fill_color, (0.2, 0.4, 0.6, 0.0))


@pytest.mark.slow
def test_cli_unregisters_what_it_registered(tmp_path):
    """A process that leaves FaceLab registered hangs at exit in bpy 4.5: the CLI unregisters first."""
    script = tmp_path / "run_cli.py"
    script.write_text(textwrap.dedent("""
        import bpy
        import facelab_addon.cli as cli
        code = cli.main(["propagate", "missing.blend", "--object", "Face"])
        print("RESULT", code, hasattr(bpy.types, "FACELAB_OT_propagate"))
    """))
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    r = subprocess.run([sys.executable, str(script)], cwd=tmp_path, env=env, stdout=subprocess.PIPE,
                       stderr=subprocess.PIPE, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    (line,) = [ln for ln in r.stdout.splitlines() if ln.startswith("RESULT")]
    assert line == "RESULT 3 False"  # exit code 3: the input file is missing; FaceLab no longer registered
