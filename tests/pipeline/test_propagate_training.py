"""Propagate learns from the captured frame: a training correction that also moved the trusted mouth
region (as a Refine with a wide free region does) teaches the regression only its inner-lip part, the
extrapolation score is exactly 0 on the training frames, and the training frames still show the artist's
whole correction."""

import numpy as np
import pytest

from facelab_addon.blender import caches
from facelab_addon.blender.mesh import mesh_triangles, vertex_group_mask
from facelab_addon.blender.shapekeys import add_corrective_key, key_spike, rest_vertices
from facelab_addon.core.lips.regressor import LipRegressor
from facelab_addon.core.lips.regions import faces_in_region
from facelab_addon.names import LIPS_GROUP, MOUTH_GROUP, REFINE_PREFIX
from facelab_addon.pipeline.propagate import PropagateSettings, propagate
from facelab_addon.pipeline.regions import auto_regions
from facelab_addon.pipeline.training import record_training_frame

from ..blender.test_propagate_operator import FRAMES, TRAIN, build

pytestmark = pytest.mark.blender

HELD = [2, 11, 24, 37]


def test_training_features_come_from_the_captured_frame(ict, addon):
    scene, obj, err, cap_w = build(ict)
    auto_regions(obj)
    tris = mesh_triangles(obj.data)
    mouth = vertex_group_mask(obj, MOUTH_GROUP)
    lips = vertex_group_mask(obj, LIPS_GROUP)
    rest = rest_vertices(obj)
    # a spill: a smooth 0.3 mm push over the trusted mouth band and the lip border (FL_mouth holds both),
    # different per frame; the interior lips get only the fix of the capture error
    c = rest[lips].mean(axis=0)
    r = np.linalg.norm(rest - c, axis=1)
    spill = np.zeros_like(rest)
    spill[:, 2] = 0.0003 * np.exp(-((r / 0.02) ** 2)) * mouth
    assert np.abs(spill[mouth & ~lips, 2]).max() > 1e-4  # the correction does move the mouth input
    i = np.searchsorted(FRAMES, TRAIN)
    for n, (f, w) in enumerate(zip(TRAIN, cap_w[i])):
        kb = add_corrective_key(obj, f"{REFINE_PREFIX}{f:04d}", -w * err + (1 + n) * spill)
        key_spike(kb, f)
        record_training_frame(scene, obj, f, kb.name, "sketch")
    corrected = caches.evaluate_frames(obj, TRAIN, mute_shape_keys_prefix=())
    captured_train = caches.evaluate_frames(obj, TRAIN)  # FaceLab's keys muted

    res = propagate(scene, obj, FRAMES, PropagateSettings(suggestions=0, ridge="none", damping=False))

    # exactly 0 on the training frames (the docs promise it), and not 0 elsewhere
    e = res.extrapolation
    t = np.isin(FRAMES, TRAIN)
    assert np.abs(e[t]).max() < 1e-9, e[t]
    assert e[~t].max() > 1e-3
    # the training frames keep the artist's whole correction, spill included
    np.testing.assert_allclose(caches.evaluate_frames(obj, TRAIN, mute_shape_keys_prefix=()), corrected, atol=1e-7)
    # held-out frames: what a regressor learns from the inner-lip fix alone (the spill never enters)
    reg = LipRegressor(rest, tris, faces_in_region(tris, mouth), faces_in_region(tris, lips))
    cap64 = captured_train.astype(np.float64)
    reg.fit(cap64 - cap_w[i, None, None] * err, captured=cap64, shot=caches.evaluate_frames(obj, FRAMES))  # "auto"
    captured = caches.evaluate_frames(obj, HELD)
    want = reg.predict(captured.astype(np.float64))
    got = caches.evaluate_frames(obj, HELD, mute_shape_keys_prefix=())
    assert np.abs(got - want).max() < 1e-5 + 1e-6
    # and that is a real correction: closer to the truth than the capture
    truth = captured - cap_w[np.searchsorted(FRAMES, HELD), None, None] * err
    err_of = lambda X: np.linalg.norm(X - truth, axis=2)[:, lips].mean()  # noqa: E731
    assert err_of(got) < 0.5 * err_of(captured)
