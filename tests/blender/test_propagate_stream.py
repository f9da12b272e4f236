"""Streaming Propagate in Blender: the shot read, corrected and compressed in chunks gives the same
keys, weights, extrapolation and suggestions as one whole-shot chunk (chunk sizes that do not divide
the shot), from shape-key animation and from a PC2 Mesh Cache; ``CaptureReader`` returns exactly
what ``read_captured_frames`` returns on the vertices it is asked for, by each of its paths."""

import bpy
import numpy as np
import pytest

from facelab_addon.blender import caches
from facelab_addon.blender.capture_stream import CaptureReader
from facelab_addon.names import PROPAGATE_PREFIX
from facelab_addon.pipeline.propagate import PropagateSettings, propagate
from facelab_addon.pipeline.regions import auto_regions
from facelab_addon.pipeline.training import record_training_frame

from ..pipeline.test_propagate import corrected_scene, pc2_capture_face
from .test_propagate_operator import FRAMES

pytestmark = [pytest.mark.blender, pytest.mark.slow]


def _result(scene, obj, frames, chunk):
    r = propagate(scene, obj, frames, PropagateSettings(suggestions=3), chunk=chunk)
    shown = caches.evaluate_frames(obj, frames, mute_shape_keys_prefix=())  # capture + FaceLab's keys
    return r, shown


def _same(a, b):
    (ra, sa), (rb, sb) = a, b
    assert ra.keys == rb.keys and len(ra.keys) >= 1
    np.testing.assert_allclose(sa, sb, rtol=0, atol=1e-7)  # float32 key data
    np.testing.assert_allclose(ra.extrapolation, rb.extrapolation, rtol=0, atol=1e-9)
    assert ra.suggested == rb.suggested and len(ra.suggested) == 3


def test_chunked_and_whole_shot_propagate_agree_on_shape_keys(ict, addon):
    scene, obj, err, cap_w = corrected_scene(ict)
    capture = caches.evaluate_frames(obj, FRAMES)
    whole = _result(scene, obj, FRAMES, chunk=len(FRAMES))
    assert np.abs(whole[1] - capture).max() > 1e-4  # a real correction (metres)
    for chunk in (7, 3):  # 40 frames: neither divides the shot
        _same(_result(scene, obj, FRAMES, chunk=chunk), whole)


def test_chunked_and_whole_shot_propagate_agree_on_a_mesh_cache(ict, addon, tmp_path):
    cap = pc2_capture_face(ict, tmp_path)
    scene, face = cap.scene, cap.face
    auto_regions(face)
    record_training_frame(scene, face, 9, "", "sculpt")
    frames = np.arange(1, 17)
    whole = _result(scene, face, frames, chunk=16)
    assert cap.md.deform_mode == "INTEGRATE"
    _same(_result(scene, face, frames, chunk=5), whole)


def test_capture_reader_matches_read_captured_frames(ict, addon, tmp_path):
    scene, obj, err, cap_w = corrected_scene(ict)
    propagate(scene, obj, FRAMES, PropagateSettings(suggestions=0))  # FaceLab's keys exist and are left out
    assert any(kb.name.startswith(PROPAGATE_PREFIX) for kb in obj.data.shape_keys.key_blocks)
    v = np.sort(np.random.default_rng(0).choice(len(obj.data.vertices), 500, replace=False))
    frames = [3, 4, 17, 40]
    want = caches.read_captured_frames(obj, frames)[:, v]
    reader = CaptureReader(obj, v)
    assert reader.path == "shape_keys"
    np.testing.assert_allclose(reader.read(frames), want, rtol=0, atol=1e-7)
    md = obj.modifiers.new("Still", "DISPLACE")  # a modifier: the generic, frame-by-frame path
    md.strength = 0.0
    reader = CaptureReader(obj, v)
    assert reader.path == "evaluate"
    np.testing.assert_allclose(reader.read(frames), want, rtol=0, atol=1e-7)
    obj.modifiers.remove(md)

    cap = pc2_capture_face(ict, tmp_path)
    cap.md.forward_axis, cap.md.up_axis = "POS_Z", "NEG_Y"  # the modifier's axis matrix applies
    reader = CaptureReader(cap.face, v)
    assert reader.path == "mesh_cache"
    f = np.array([1, 2.5, 9, 16])  # a subframe blends two samples
    np.testing.assert_allclose(reader.read(f), caches.read_captured_frames(cap.face, f)[:, v], rtol=0, atol=1e-7)
    bpy.context.scene.frame_set(1)
