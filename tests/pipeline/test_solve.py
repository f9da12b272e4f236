"""The Bind Tracks and Solve Performance pipelines called directly (no operators, no scene settings): the
ICT rig of test_solve_operator filmed by a helmet stereo pair whose tracks are the truth's projected surface
points -> bindings on the truth surface points, keyed weights equal to the truth in the rig's span, the
corrective where the truth leaves it; bad input raises before anything is written."""

import bpy
import numpy as np
import pytest

from facelab_addon.blender.actions import curve_values
from facelab_addon.blender.bindings import read_bindings
from facelab_addon.blender.tracking import View
from facelab_addon.core.capture.markers import SurfacePoints
from facelab_addon.core.errors import BundleError, CameraError, FaceLabError
from facelab_addon.core.solve.blendshape_solve import SolveParams
from facelab_addon.core.solve.corrective import CorrectiveParams
from facelab_addon.core.solve.performance import PerformanceParams
from facelab_addon.core.solve.retarget import RetargetParams
from facelab_addon.names import SOLVE_ACTION, SOLVE_PREFIX
from facelab_addon.pipeline.solve import (
    BindSettings,
    SolveSettings,
    bind_tracks,
    solve_params,
    solve_performance,
)
from facelab_addon.pipeline.retarget import RetargetSettings, retarget_params

from ..blender.test_solve_operator import EXPR, W_TRUTH, T, build

pytestmark = pytest.mark.blender


def _views(views):
    return [View(cam_obj, clip) for cam_obj, clip, _ in views]


def test_settings_map_onto_the_core_params_with_the_core_defaults():
    """The settings' defaults are the core's (one source) and every setting reaches its core parameter."""
    assert solve_params(SolveSettings()) == (SolveParams(), CorrectiveParams(), PerformanceParams())
    assert retarget_params(RetargetSettings()) == RetargetParams()
    fit, corr, passes = solve_params(SolveSettings(
        weight_min=0.0, weight_max=0.8, marker_weight=2.0, contour_weight=3.0, anchor_weight=4.0, sliding=False,
        contour_damping=0.05, lip_passes=1, lip_line_weight=6.0, lip_damping=0.2))
    assert fit == SolveParams(bounds=(0.0, 0.8), marker_weight=2.0, contour_weight=3.0, anchor_weight=4.0)
    assert corr == CorrectiveParams(region_damping=0.05, lip_contour_weight=6.0, lip_damping=0.2)
    assert passes == PerformanceParams(sliding=False, lip_passes=1)
    assert retarget_params(RetargetSettings(lip_sync=False, lip_threshold=0.002)) == RetargetParams(
        lip_sync=False, threshold=0.002)


def test_bind_and_solve_recover_the_truth(ict, addon, tmp_path):
    scene, obj, cams, markers, truth, views = build(ict, tmp_path)
    vs = _views(views)
    scene.frame_set(2)

    # ---- bind on the neutral frame: every track lands on its truth surface point, the views agree
    b = bind_tracks(scene, obj, 0, BindSettings(views=vs))
    names = [f"M{j:02d}" for j in range(len(markers))]
    assert b.frame == 0 and b.bound == names and b.bundles == 0
    assert b.missed == [] and b.untracked == [] and b.disagree == []
    print(f"bind: largest disagreement between the views {b.max_err_px:.2e} px")
    assert b.max_err_px < 0.01
    assert scene.frame_current == 2 and obj.facelab_solve.bind_frame == 0
    got_names, bv, bb = read_bindings(obj, "MARKER")
    assert got_names == names
    np.testing.assert_allclose(SurfacePoints(bv, bb).evaluate(truth[0]), markers.evaluate(truth[0]), atol=2e-6)

    # ---- markers only, no corrective: the rig's weights are the truth's in its span (frames 0-2)
    done = []
    r = solve_performance(scene, obj, SolveSettings(views=vs, use_contours=False, use_corrective=False),
                          progress=lambda d, n: done.append((d, n)))
    assert done == [(i + 1, T) for i in range(T)]
    assert list(r.frames) == list(range(T)) and list(r.solved) == list(range(T)) and r.skipped == {}
    assert r.rig_keys == EXPR and r.keys == [] and r.n_markers == len(markers) and r.n_views == 2
    assert r.missing == {} and r.curve_stats is None and r.action_note == ""
    key = obj.data.shape_keys
    assert key.animation_data.action.name == SOLVE_ACTION
    W = curve_values(key, EXPR, np.arange(T))
    print("markers only: weight error per frame", np.abs(W - W_TRUTH).max(axis=1))
    assert np.abs(W[:3] - W_TRUTH[:3]).max() < 1e-4
    rms = [f["marker_rms_px"] for f in r.core.info["frames"]]
    assert max(rms[:3]) < 0.01 and min(rms[3:]) > 0.1  # frames 3-4 leave the rig's span (cheekPuff_L)

    # ---- with the corrective: keyed where the truth leaves the span, and it brings the markers onto the truth
    r = solve_performance(scene, obj, SolveSettings(views=vs, use_contours=False))
    assert r.keys and all(k.startswith(SOLVE_PREFIX) for k in r.keys)
    assert [kb.name for kb in key.key_blocks if kb.name.startswith(SOLVE_PREFIX)] == r.keys
    assert np.abs(curve_values(key, r.keys, np.arange(T))[3:]).max() > 0.1
    from facelab_addon.blender.caches import evaluate_frames

    V = evaluate_frames(obj, np.arange(T), mute_shape_keys_prefix=())
    Vb = evaluate_frames(obj, np.arange(T), mute_shape_keys_prefix=(SOLVE_PREFIX,))
    for t in (3, 4):
        want = cams[0].project(markers.evaluate(truth[t]))
        e_with = np.linalg.norm(cams[0].project(markers.evaluate(V[t])) - want, axis=1).mean()
        e_without = np.linalg.norm(cams[0].project(markers.evaluate(Vb[t])) - want, axis=1).mean()
        print(f"frame {t}: marker px error without corrective {e_without:.3f}, with {e_with:.3f}")
        assert e_with < 0.5 * e_without


def test_bad_input_raises_before_writing(ict, addon, tmp_path):
    scene, obj, cams, markers, truth, views = build(ict, tmp_path)
    vs = _views(views)
    # nothing bound: no keys, no action
    with pytest.raises(FaceLabError, match="no track is bound"):
        solve_performance(scene, obj, SolveSettings(views=vs))
    assert obj.data.shape_keys.animation_data is None
    # a view without its clip, then bundles enabled with none in the scene: the bindings stay empty
    with pytest.raises(CameraError, match="has no Movie Clip"):
        bind_tracks(scene, obj, 0, BindSettings(views=[vs[0], View(vs[1].camera, None)]))
    with pytest.raises(BundleError, match="Bundles are set to Empties but there are none"):
        bind_tracks(scene, obj, 0, BindSettings(views=vs, bundles="EMPTIES"))
    assert len(obj.facelab_solve.bindings) == 0
    # an empty range
    with pytest.raises(FaceLabError, match="range 3-1 ends before it starts; set End >= Start"):
        solve_performance(scene, obj, SolveSettings(views=vs, frame_start=3, frame_end=1))
    assert not [kb for kb in obj.data.shape_keys.key_blocks if kb.name.startswith(SOLVE_PREFIX)]
    assert bpy.data.actions.get(SOLVE_ACTION) is None
