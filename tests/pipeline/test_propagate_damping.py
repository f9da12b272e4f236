"""Propagate's Damp Uncertain Frames (``PropagateSettings.damping``, issue 11): the keys show the core regressor's
damped prediction, each frame's correction no larger than without damping, the training frames untouched."""

import numpy as np
import pytest

from facelab_addon.blender import caches
from facelab_addon.blender.mesh import mesh_triangles, vertex_group_mask
from facelab_addon.blender.shapekeys import rest_vertices
from facelab_addon.core.lips.regressor import LipRegressor
from facelab_addon.core.lips.regions import faces_in_region
from facelab_addon.names import LIPS_GROUP, MOUTH_GROUP, PROPAGATE_PREFIX
from facelab_addon.pipeline.propagate import PropagateSettings, propagate, training_input

from ..blender.test_propagate_operator import FRAMES, TRAIN
from .test_propagate import corrected_scene

pytestmark = pytest.mark.blender


def test_damped_propagate_is_the_damped_regressor(ict, addon):
    scene, obj, err, cap_w = corrected_scene(ict, keyed=True)
    assert PropagateSettings().damping is True  # the default damps (benchmarks/artist_loop.py)
    corrected = caches.evaluate_frames(obj, TRAIN, mute_shape_keys_prefix=(PROPAGATE_PREFIX,))
    held = [f for f in FRAMES if f not in TRAIN]
    captured = caches.evaluate_frames(obj, held, mute_shape_keys_prefix=("FL_",)).astype(np.float64)
    got = {}
    for damping in (False, True):
        r = propagate(scene, obj, FRAMES, PropagateSettings(suggestions=0, damping=damping, ridge="none"))
        got[damping] = caches.evaluate_frames(obj, held, mute_shape_keys_prefix=()).astype(np.float64)
        np.testing.assert_allclose(caches.evaluate_frames(obj, TRAIN, mute_shape_keys_prefix=()), corrected, atol=1e-7)
    # the core regressor fitted here, damped
    tris = mesh_triangles(obj.data)
    reg = LipRegressor(rest_vertices(obj), tris, faces_in_region(tris, vertex_group_mask(obj, MOUTH_GROUP)),
                       faces_in_region(tris, vertex_group_mask(obj, LIPS_GROUP)), damping=True)
    cap_train = caches.evaluate_frames(obj, TRAIN, mute_shape_keys_prefix=("FL_",)).astype(np.float64)
    shot = caches.evaluate_frames(obj, FRAMES, mute_shape_keys_prefix=("FL_",))
    reg.fit(training_input(cap_train, corrected, reg.interior_vertices), captured=cap_train, shot=shot)
    assert reg.whole_weight == pytest.approx(r.whole_weight, abs=1e-5)
    assert np.abs(got[True] - reg.predict(captured)).max() < 1e-5 + 1e-6  # the 0.01 mm storage tolerance
    s = reg.damping_weights(captured)
    assert 0 < s.min() < 1 and s.max() <= 1
    size = {d: np.linalg.norm(got[d] - captured, axis=2).max(axis=1) for d in got}
    assert (size[True] <= size[False] + 2e-5).all()
    # some frame is really damped (measured: to 0.91 with the slopes through the origin; the slopes fitted with an
    # intercept, model_choice.error_model's a_*_growth, damp this scene's extrapolated frames by under 1 %)
    assert (size[True] < size[False] - 1e-6).any()
