"""Retarget streams its per-frame correctives: the actor's correctives are mixed from their keys a chunk of
frames at a time and each creature corrective goes to the CorrectionWriter a chunk at a time (no (T,V,3)
array of the shot), equal value for value to the core's whole-shot ``retarget_performance``."""

import numpy as np
import pytest

from facelab_addon.blender.mesh import mesh_triangles
from facelab_addon.blender.rig import rig_animation
from facelab_addon.blender.scene import new_mesh_object
from facelab_addon.blender.shapekeys import rest_vertices
from facelab_addon.core.solve.retarget import retarget_performance
from facelab_addon.names import RETARGET_PREFIX, SOLVE_PREFIX
from facelab_addon.pipeline import correctives, streaming
from facelab_addon.pipeline.retarget import RetargetSettings, retarget

from ..blender.test_solve_operator import T
from .test_retarget import solved  # noqa: F401  (the module fixture)

pytestmark = pytest.mark.blender


@pytest.mark.parametrize("lip_sync", [False, True])
def test_streamed_correctives_equal_the_whole_shot(ict, solved, monkeypatch, lip_sync):  # noqa: F811
    from facelab_addon.testing.creature import widen_mouth
    from facelab_addon.testing.synthetic import ICT_MOUTH_LOOP

    scene, obj, truth, vs = solved
    neutral = truth[0]
    cre = new_mesh_object(f"Wide{int(lip_sync)}", widen_mouth(neutral, neutral[ICT_MOUTH_LOOP].mean(0), factor=1.5),
                          poly_verts=ict.poly_verts, poly_offsets=ict.poly_offsets)
    got = {"frames": [], "deltas": [], "chunks": []}
    real_add = correctives.CorrectionWriter.add

    def add(self, frames, deltas):
        got["frames"].append(np.array(frames, dtype=np.float64))
        got["deltas"].append(np.array(deltas))
        got["chunks"].append(len(frames))
        return real_add(self, frames, deltas)

    monkeypatch.setattr(correctives.CorrectionWriter, "add", add)
    monkeypatch.setattr(streaming, "CHUNK_BYTES", 2 * 24 * len(cre.data.vertices))  # 2 frames a chunk
    r = retarget(scene, obj, cre, RetargetSettings(lip_sync=lip_sync))
    assert got["chunks"] == [2, 2, 1] and r.core.correctives is None
    np.testing.assert_array_equal(np.concatenate(got["frames"]), np.arange(T))
    # the whole-shot path: the actor's (T,V,3) correctives and the core's (T,W,3) result
    names, a_rest, a_deltas, W, C = rig_animation(obj, np.arange(T), SOLVE_PREFIX)
    assert C is not None and np.abs(C).max() > 1e-4
    ta = mesh_triangles(obj.data)
    whole = retarget_performance(a_rest, ta, a_deltas, W, rest_vertices(cre), ta, correctives=C, lip_sync=lip_sync)
    D = np.concatenate(got["deltas"])
    print(f"lip sync {lip_sync}: streamed vs whole-shot largest difference {np.abs(D - whole.correctives).max():.3g}"
          f" (largest corrective {np.abs(whole.correctives).max():.3g})")
    np.testing.assert_array_equal(D, whole.correctives)
    assert [e is None for e in r.core.end_points] == [e is None for e in whole.end_points]
    assert r.keys and all(k.startswith(RETARGET_PREFIX) for k in r.keys)
