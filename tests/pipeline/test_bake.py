"""The Bake pipeline without operators: PC2, MDD and Alembic files of the corrected (evaluated)
mesh hold exactly its positions, an existing file is refused unless overwrite is asked, and a
cancelled bake leaves the destination as it was."""

import bpy
import numpy as np
import pytest

from facelab_addon.blender import bakes, caches
from facelab_addon.blender.scene import new_mesh_object
from facelab_addon.blender.shapekeys import add_corrective_key, key_values_bulk
from facelab_addon.core.capture.pointcache import read_mdd, read_pc2
from facelab_addon.core.errors import FaceLabError, MeshError
from facelab_addon.pipeline.bake import BakeResult, BakeSettings, bake, bake_steps
from facelab_addon.pipeline.steps import StepJob

pytestmark = pytest.mark.blender

FRAMES = np.arange(1, 7)


@pytest.fixture
def face():
    """A 6x6 grid whose key 'Up' lifts it 0..0.1 over frames 1..6 (the corrected performance)."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    g = np.stack(np.meshgrid(np.linspace(-1, 1, 6), np.linspace(-1, 1, 6), indexing="ij"), -1).reshape(-1, 2)
    F = [[i * 6 + j, (i + 1) * 6 + j, (i + 1) * 6 + j + 1, i * 6 + j + 1] for i in range(5) for j in range(5)]
    obj = new_mesh_object("Face", np.c_[g, np.zeros(len(g))], np.array(F))
    add_corrective_key(obj, "Up", np.tile([0.0, 0.0, 0.1], (36, 1)))
    key_values_bulk(obj, ["Up"], FRAMES, np.linspace(0, 1, 6)[:, None])
    bpy.context.scene.frame_set(3)
    return obj


@pytest.mark.parametrize("fmt, read", [("PC2", read_pc2), ("MDD", read_mdd)])
def test_point_cache_bake_holds_the_evaluated_mesh(face, tmp_path, fmt, read):
    expect = caches.evaluate_frames(face, FRAMES, mute_shape_keys_prefix=())
    labels = []
    r = bake(face, FRAMES, tmp_path / f"out.{fmt}", BakeSettings(format=fmt), progress=lambda *a: labels.append(a))
    assert isinstance(r, BakeResult) and (r.format, r.frames, r.object) == (fmt, 6, "Face")
    data = read(r.path)
    data = data[0] if isinstance(data, tuple) else data
    np.testing.assert_array_equal(data, expect)
    np.testing.assert_allclose(data[:, 0, 2], np.linspace(0, 0.1, 6), atol=1e-6)
    assert labels == [(f"baking frame {f}", i + 1, 6) for i, f in enumerate(FRAMES)]
    assert bpy.context.scene.frame_current == 3
    # the same file as the adapter's one-call bake
    ref = getattr(bakes, f"bake_{fmt.lower()}")(face, FRAMES, tmp_path / f"ref.{fmt}")
    assert ref.read_bytes() == r.path.read_bytes()


def test_bake_refuses_and_cancels_cleanly(face, tmp_path):
    target = tmp_path / "keep.pc2"
    target.write_bytes(b"artist's file")
    with pytest.raises(FaceLabError, match="exists"):
        bake_steps(face, FRAMES, target)  # raised by the call, before any file is opened
    with pytest.raises(FaceLabError, match="Choose a file"):
        bake_steps(face, FRAMES, "")
    with pytest.raises(FaceLabError, match="evenly spaced"):
        bake_steps(face, [1, 2, 4], tmp_path / "gap.pc2")
    with pytest.raises(FaceLabError, match="Unknown bake format"):
        bake_steps(face, FRAMES, tmp_path / "x.obj", BakeSettings(format="OBJ"))
    with pytest.raises(MeshError):
        bake_steps(bpy.data.objects.new("Empty", None), FRAMES, tmp_path / "e.pc2")
    job = StepJob(bake_steps(face, FRAMES, target, BakeSettings(overwrite=True)))
    assert job.step() and job.step() and job.stage == "baking frame 2"
    job.cancel()
    assert target.read_bytes() == b"artist's file" and sorted(p.name for p in tmp_path.iterdir()) == ["keep.pc2"]
    assert bpy.context.scene.frame_current == 3
    r = bake(face, FRAMES, target, BakeSettings(overwrite=True))
    np.testing.assert_array_equal(read_pc2(r.path)[0], caches.evaluate_frames(face, FRAMES, mute_shape_keys_prefix=()))


def test_alembic_bake_plays_back_the_corrected_mesh(face, tmp_path):
    expect = caches.evaluate_frames(face, FRAMES, mute_shape_keys_prefix=())
    r = bake(face, FRAMES, tmp_path / "out.abc", BakeSettings(format="ABC"))
    assert r.format == "ABC" and r.path.is_file()
    bpy.ops.wm.read_factory_settings(use_empty=True)
    assert bpy.ops.wm.alembic_import(filepath=str(r.path)) == {"FINISHED"}
    np.testing.assert_array_equal(caches.evaluate_frames(bpy.data.objects["Face"], FRAMES), expect)
