"""Retarget streams its per-frame correctives through the core's ``retarget_performance(corrective_sink=...)``:
the actor's correctives are mixed from their keys one frame at a time and each creature corrective goes to
the CorrectionWriter a chunk at a time (no (T,V,3) array of the shot), equal value for value to the core's
whole-shot result, with memory flat in frames."""

import tracemalloc

import numpy as np
import pytest

from facelab_addon.blender.mesh import mesh_triangles
from facelab_addon.blender.rig import rig_animation
from facelab_addon.blender.scene import new_mesh_object
from facelab_addon.blender.shapekeys import rest_vertices
from facelab_addon.core.geometry import compress
from facelab_addon.core.solve import retarget as core_retarget
from facelab_addon.core.solve.retarget import RetargetParams, Retargeter, retarget_performance
from facelab_addon.names import RETARGET_PREFIX, SOLVE_PREFIX
from facelab_addon.pipeline import correctives, streaming
from facelab_addon.pipeline.retarget import RetargetSettings, retarget

from ..blender.test_solve_operator import EXPR, T
from .test_retarget import solved  # noqa: F401  (the module fixture)

pytestmark = pytest.mark.blender


@pytest.mark.parametrize("lip_sync", [False, pytest.param(True, marks=pytest.mark.slow)])
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
    rt = Retargeter(a_rest, ta, a_deltas, rest_vertices(cre), ta, params=RetargetParams(lip_sync=lip_sync))
    whole = retarget_performance(rt, W, correctives=C)
    D = np.concatenate(got["deltas"])
    print(f"lip sync {lip_sync}: streamed vs whole-shot largest difference {np.abs(D - whole.correctives).max():.3g}"
          f" (largest corrective {np.abs(whole.correctives).max():.3g})")
    np.testing.assert_array_equal(D, whole.correctives)
    assert [e is None for e in r.core.end_points] == [e is None for e in whole.end_points]
    assert r.keys and all(k.startswith(RETARGET_PREFIX) for k in r.keys)


def _keyed_actor(ict, n_frames):
    """The ICT face (metres) with 6 expression keys and 2 FL_Solve_ corrective keys, all keyed on
    ``n_frames`` frames of smooth, varied values; a creature with a widened mouth (same topology)."""
    from facelab_addon.testing.creature import widen_mouth
    from facelab_addon.testing.scenes import build_ict_face_scene
    from facelab_addon.testing.synthetic import ICT_MOUTH_LOOP

    n = ict.neutral
    g = np.exp(-np.sum((n - n[ICT_MOUTH_LOOP].mean(0)) ** 2, 1) / 2.0**2)[:, None]  # model units (cm)
    shapes = {f"{SOLVE_PREFIX}00": n + 0.2 * g * [0, 0, 1], f"{SOLVE_PREFIX}01": n + 0.1 * g * [1, 0, 0]}
    t = np.arange(n_frames)[:, None]
    values = 0.5 * (1 - np.cos(2 * np.pi * t * np.array([1, 2, 3, 5, 7, 11, 4, 6]) / (n_frames + 3)))
    fs = build_ict_face_scene(ict, EXPR, shapes=shapes, weights=values, frames=np.arange(n_frames))
    cre = new_mesh_object("Wide", widen_mouth(fs.neutral, fs.neutral[ICT_MOUTH_LOOP].mean(0), factor=1.5),
                          poly_verts=ict.poly_verts, poly_offsets=ict.poly_offsets)
    return fs.scene, fs.obj, cre


@pytest.mark.slow
def test_memory_is_flat_in_frames(ict, addon, monkeypatch):
    """Python-heap peak (tracemalloc, numpy included) from the Retargeter's set-up to the stored result, 40 vs 80
    frames with 4-frame chunks (and 4-frame blocks in the compression): 40 more frames of the whole shot would
    be 40 x V x 3 float64 (26 MB at 26.7k) for the actor's mixed correctives, or half that for the core's
    float32 (T,W,3) result."""
    V = len(ict.neutral)
    monkeypatch.setattr(streaming, "CHUNK_BYTES", 4 * 24 * V)
    monkeypatch.setattr(compress, "_BLOCK_VALUES", 4 * 3 * V)
    real_init = core_retarget.Retargeter.__init__

    def init(self, *a, **k):  # the peak from here on: the frames and their storage, not the set-up
        real_init(self, *a, **k)
        tracemalloc.reset_peak()

    monkeypatch.setattr(core_retarget.Retargeter, "__init__", init)
    peaks = {}
    for n_frames in (40, 80):
        scene, obj, cre = _keyed_actor(ict, n_frames)
        tracemalloc.start()
        try:
            r = retarget(scene, obj, cre, RetargetSettings(lip_sync=False))
            peaks[n_frames] = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        assert len(r.frames) == n_frames and r.keys and r.core.correctives is None and r.core.info["nonzero"]
    shot = 40 * V * 3 * 8
    print(f"tracemalloc peak: 40 frames {peaks[40] / 1e6:.1f} MB, 80 frames {peaks[80] / 1e6:.1f} MB "
          f"(one (40,V,3) float64 array: {shot / 1e6:.1f} MB)")
    assert peaks[80] - peaks[40] < 0.25 * shot
