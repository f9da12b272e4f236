"""The Retarget pipeline called directly (no operators, no scene settings), after a solve of the ICT rig of
test_solve_operator: a creature that is the actor moved elsewhere gets the actor's shape keys and weights
back; hand-set lip end points reach the core on every frame; a topology mismatch raises before writing."""

import numpy as np
import pytest

from facelab_addon.blender.actions import curve_values
from facelab_addon.blender.scene import new_mesh_object
from facelab_addon.blender.tracking import View
from facelab_addon.core.errors import FaceLabError
from facelab_addon.names import RETARGET_ACTION, RETARGET_PREFIX
from facelab_addon.pipeline.retarget import RetargetSettings, retarget
from facelab_addon.pipeline.solve import (
    BindSettings,
    SolveSettings,
    bind_tracks,
    solve_performance,
)

from ..blender.test_solve_operator import EXPR, T, build

pytestmark = pytest.mark.blender


@pytest.fixture(scope="module")
def solved(ict, addon, tmp_path_factory):
    """The test_solve_operator shot, bound and solved (markers + corrective) through the pipelines."""
    scene, obj, cams, markers, truth, views = build(ict, tmp_path_factory.mktemp("retarget"))
    vs = [View(cam_obj, clip) for cam_obj, clip, _ in views]
    bind_tracks(scene, obj, 0, BindSettings(views=vs))
    solve_performance(scene, obj, SolveSettings(views=vs, use_contours=False))
    return scene, obj, truth, vs


def _key_deltas(obj, names):
    key = obj.data.shape_keys
    n = len(obj.data.vertices)

    def co(kb):
        a = np.empty(3 * n)
        kb.data.foreach_get("co", a)
        return a.reshape(n, 3)

    return np.stack([co(key.key_blocks[k]) - co(key.reference_key) for k in names])


@pytest.mark.slow
def test_retarget_to_the_actor_itself_gives_the_actor_back(ict, solved):
    scene, obj, truth, vs = solved
    twin = new_mesh_object("Twin", truth[0], poly_verts=ict.poly_verts, poly_offsets=ict.poly_offsets)
    twin.location = (0.4, 0.0, 0.0)
    done = []
    r = retarget(scene, obj, twin, RetargetSettings(lip_sync=False, views=vs), progress=lambda d, n: done.append(n))
    assert r.correspondence == "same topology" and r.created == EXPR and r.kept == [] and done
    assert list(r.frames) == list(range(T))
    ck = twin.data.shape_keys
    assert ck.animation_data.action.name == RETARGET_ACTION
    # the keyed weights are the actor's
    np.testing.assert_allclose(curve_values(ck, EXPR, np.arange(T)),
                               curve_values(obj.data.shape_keys, EXPR, np.arange(T)), atol=1e-6)
    # deformation transfer onto an identical mesh reproduces the actor's shapes
    D_actor, D_twin = _key_deltas(obj, EXPR), _key_deltas(twin, EXPR)
    err = np.abs(D_twin - D_actor).max() / np.abs(D_actor).max()
    print(f"twin: largest shape-key difference {err:.2e} of the largest delta")
    assert err < 1e-9  # measured 5e-14
    # the actor's correctives are carried over and keyed
    assert r.keys and [kb.name for kb in ck.key_blocks if kb.name.startswith(RETARGET_PREFIX)] == r.keys
    assert np.abs(curve_values(ck, r.keys, np.arange(T))).max() > 0


def test_hand_set_end_points_and_bad_input(ict, solved):
    from facelab_addon.testing.creature import widen_mouth
    from facelab_addon.testing.synthetic import ICT_MOUTH_LOOP

    scene, obj, truth, vs = solved
    neutral = truth[0]
    cre = new_mesh_object("Wide", widen_mouth(neutral, neutral[ICT_MOUTH_LOOP].mean(0), factor=1.5),
                          poly_verts=ict.poly_verts, poly_offsets=ict.poly_offsets)
    upper = np.array([[0.2, 0.8]] * (T - 1) + [[0.3, 0.7]])  # one row per frame
    r = retarget(scene, obj, cre, RetargetSettings(end_points_upper=upper, end_points_lower=(0.25, 0.75), views=vs))
    eps = r.core.end_points
    for t in range(T):
        np.testing.assert_allclose(eps[t].upper, upper[t], atol=1e-12)
        np.testing.assert_allclose(eps[t].lower, [0.25, 0.75], atol=1e-12)
    # another topology with Correspondence = Topology: refused, the mesh is left as it was
    blob = new_mesh_object("Blob", [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]],
                           [[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]])
    with pytest.raises(FaceLabError, match="does not share the topology"):
        retarget(scene, obj, blob, RetargetSettings(correspondence="TOPOLOGY"))
    with pytest.raises(FaceLabError, match="no correspondence"):
        retarget(scene, obj, blob, RetargetSettings())
    assert blob.data.shape_keys is None
    with pytest.raises(FaceLabError, match="the face itself"):
        retarget(scene, obj, obj, RetargetSettings())
