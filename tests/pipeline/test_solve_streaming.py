"""Solve Performance streams its per-frame corrective: each solved frame's object-local corrective goes to
the CorrectionWriter a chunk at a time (the core keeps no (T,V,3) array), equal value for value to the
whole-shot path (the core's (T,V,3) correctives mapped to object-local), whatever the chunk size."""

import numpy as np
import pytest

from facelab_addon.blender.tracking import View
from facelab_addon.core.solve import performance
from facelab_addon.names import SOLVE_PREFIX
from facelab_addon.pipeline import correctives, streaming
from facelab_addon.pipeline import solve as psolve
from facelab_addon.pipeline.solve import BindSettings, SolveSettings, bind_tracks, solve_performance

from ..blender.test_solve_operator import T, build

pytestmark = pytest.mark.blender


def test_streamed_correctives_equal_the_whole_shot(ict, addon, tmp_path, monkeypatch):
    scene, obj, cams, markers, truth, views = build(ict, tmp_path)
    vs = [View(cam_obj, clip) for cam_obj, clip, _ in views]
    bind_tracks(scene, obj, 0, BindSettings(views=vs))
    got = {"frames": [], "deltas": [], "chunks": []}
    real_add, real_solve, real_gather = correctives.CorrectionWriter.add, performance.solve_performance, psolve._gather

    def add(self, frames, deltas):
        got["frames"].append(np.array(frames, dtype=np.float64))
        got["deltas"].append(np.array(deltas))
        got["chunks"].append(len(frames))
        return real_add(self, frames, deltas)

    def gather(*a, **k):
        got["g"] = real_gather(*a, **k)
        return got["g"]

    def core(solver, corr, *a, corrective_sink=None, **k):
        assert corrective_sink is not None  # the pipeline streams
        res = real_solve(solver, corr, *a, corrective_sink=corrective_sink, **k)
        assert res.correctives is None
        got["whole"] = real_solve(solver, corr, *a, **k)  # the whole-shot path of the same solve
        return res

    monkeypatch.setattr(correctives.CorrectionWriter, "add", add)
    monkeypatch.setattr(performance, "solve_performance", core)
    monkeypatch.setattr(psolve, "_gather", gather)
    monkeypatch.setattr(streaming, "CHUNK_BYTES", 2 * 24 * len(obj.data.vertices))  # 2 frames a chunk
    r = solve_performance(scene, obj, SolveSettings(views=vs, use_contours=False))
    assert list(r.solved) == list(range(T)) and got["chunks"] == [2, 2, 1]
    np.testing.assert_array_equal(np.concatenate(got["frames"]), np.arange(T))
    whole = got["whole"]
    want = whole.correctives @ np.linalg.inv(got["g"].A).T  # what the whole-shot pipeline stored
    D = np.concatenate(got["deltas"])
    print(f"streamed vs whole-shot largest difference {np.abs(D - want).max():.3g} (largest corrective "
          f"{np.abs(want).max():.3g})")
    np.testing.assert_array_equal(D, want)
    assert np.abs(D[3:]).max() > 1e-4  # frames 3-4 leave the rig's span: a real corrective
    np.testing.assert_array_equal(r.core.weights, whole.weights)
    assert r.keys and r.keys.storage.mode == "keys" and all(k.startswith(SOLVE_PREFIX) for k in r.keys)

    # the stored keys do not depend on the chunk size
    monkeypatch.setattr(performance, "solve_performance", real_solve)
    kb = obj.data.shape_keys.key_blocks
    stored = []
    for chunk in (1, 1000):
        monkeypatch.setattr(streaming, "CHUNK_BYTES", chunk * 24 * len(obj.data.vertices))
        r = solve_performance(scene, obj, SolveSettings(views=vs, use_contours=False))
        co = np.stack([np.array([v.co[:] for v in kb[n].data]) for n in r.keys])
        vals = []
        for f in range(T):
            scene.frame_set(f)
            vals.append([kb[n].value for n in r.keys])
        stored.append((list(r.keys), co, np.array(vals)))
    assert stored[0][0] == stored[1][0]
    np.testing.assert_array_equal(stored[0][1], stored[1][1])
    np.testing.assert_array_equal(stored[0][2], stored[1][2])
