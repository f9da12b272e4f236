"""Reconstruct from Bundles streams its per-frame result: each frame's displacement goes to the
CorrectionWriter a chunk at a time (no (T,V,3) array of the shot), equal value for value to the core's
whole-shot reconstruction, the same stored keys whatever the chunk size, and memory flat in frames."""

import tracemalloc

import numpy as np
import pytest

from facelab_addon.core.geometry import compress
from facelab_addon.core.lgi.fit_residual import FitResidual
from facelab_addon.core.lgi.indexing.indexer import GeometricIndexer
from facelab_addon.names import RECONSTRUCT_PREFIX
from facelab_addon.pipeline import correctives, streaming
from facelab_addon.pipeline.reconstruct import ReconstructSettings, reconstruct_from_bundles

from ..blender.test_reconstruct_operator import EXPR
from .test_reconstruct import _shot

pytestmark = pytest.mark.blender


def _poses(T):
    """T frames of smooth, varied weights of the first 6 expressions (frame 0 neutral)."""
    t = np.arange(T)[:, None]
    W = 0.5 * (1 - np.cos(2 * np.pi * t * np.array([1, 2, 3, 5, 7, 11]) / (T + 3)))
    W[0] = 0.0
    return [dict(zip(EXPR[:6], w)) for w in W]


def _spy(monkeypatch, cls):
    """Record what reaches the writer, and the core's whole-shot reconstruction of the same call."""
    got = {"frames": [], "deltas": [], "chunks": []}
    real_add = correctives.CorrectionWriter.add
    real_stream = cls.reconstruct_stream

    def add(self, frames, deltas):
        got["frames"].append(np.array(frames, dtype=np.float64))
        got["deltas"].append(np.array(deltas))
        got["chunks"].append(len(frames))
        return real_add(self, frames, deltas)

    def stream(self, *a, **k):
        if got.get("inside"):  # reconstruct_sequence's own call
            return real_stream(self, *a, **k)
        skipped = real_stream(self, *a, **k)
        got["inside"] = True
        whole_a = [x for x in a if not callable(x)]  # the sink is the only callable argument
        k.pop("progress", None)
        if cls is FitResidual:
            k["noise"] = self.noise  # the noise the stream estimated
        got["whole"], got["whole_skipped"] = self.reconstruct_sequence(*whole_a, **k)
        got["neutral"] = (self.neutral if cls is FitResidual else self.dataset.neutral).copy()
        return skipped

    monkeypatch.setattr(correctives.CorrectionWriter, "add", add)
    monkeypatch.setattr(cls, "reconstruct_stream", stream)
    return got


@pytest.mark.parametrize("method", ["FIT_RESIDUAL", pytest.param("INDEXING", marks=pytest.mark.slow)])
def test_streamed_frames_equal_the_whole_shot(ict, addon, monkeypatch, method):
    """Chunks of 3 frames, smoothing over 3 frames and a lost bundle on frame 4: the writer receives every
    frame once, in order, each equal to the whole-shot reconstruction minus the Basis (the lost frame: zero)."""
    poses = _poses(11)
    scene, obj, empties, truth, pts = _shot(ict, EXPR[:6], poses)
    lost = empties[5]
    lost.hide_render = False
    lost.keyframe_insert("hide_render", frame=3)
    lost.hide_render = True
    lost.keyframe_insert("hide_render", frame=4)
    lost.hide_render = False
    lost.keyframe_insert("hide_render", frame=5)
    V = len(obj.data.vertices)
    monkeypatch.setattr(streaming, "CHUNK_BYTES", 3 * 24 * V)  # 3 frames a chunk
    got = _spy(monkeypatch, FitResidual if method == "FIT_RESIDUAL" else GeometricIndexer)
    r = reconstruct_from_bundles(scene, obj, ReconstructSettings(bind_frame=0, selected=empties, smooth=3,
                                                                 method=method))
    assert r.skipped == [4] and got["whole_skipped"] == [4]
    assert got["chunks"] == [3, 3, 3, 2]
    frames = np.concatenate(got["frames"])
    D = np.concatenate(got["deltas"])
    np.testing.assert_array_equal(frames, np.arange(11))
    want = got["whole"] - got["neutral"][None]
    assert np.isnan(want[4]).all()
    want[4] = 0.0
    print(f"{method}: streamed vs whole-shot largest difference {np.abs(D - want).max():.3g}")
    np.testing.assert_array_equal(D, want)
    assert np.abs(D).max() > 1e-3  # a real reconstruction, not zeros
    assert r.keys and r.keys.storage.mode == "keys"


@pytest.mark.slow
def test_stored_keys_do_not_depend_on_the_chunk_size(ict, addon, monkeypatch):
    scene, obj, empties, truth, pts = _shot(ict, EXPR[:6], _poses(9))
    V = len(obj.data.vertices)
    stored = []
    for chunk in (1, 4, 1000):
        monkeypatch.setattr(streaming, "CHUNK_BYTES", chunk * 24 * V)
        r = reconstruct_from_bundles(scene, obj, ReconstructSettings(bind_frame=0, selected=empties))
        kb = obj.data.shape_keys.key_blocks
        co = np.stack([np.array([v.co[:] for v in kb[n].data]) for n in r.keys])
        vals = []
        for f in range(9):
            scene.frame_set(f)
            vals.append([kb[n].value for n in r.keys])
        stored.append((list(r.keys), co, np.array(vals)))
    for names, co, vals in stored[1:]:
        assert names == stored[0][0] and all(n.startswith(RECONSTRUCT_PREFIX) for n in names)
        np.testing.assert_array_equal(co, stored[0][1])
        np.testing.assert_array_equal(vals, stored[0][2])
    assert np.abs(stored[0][2]).max() > 0.1


@pytest.mark.slow
def test_memory_is_flat_in_frames(ict, addon, monkeypatch):
    """Python-heap peak (tracemalloc, numpy included) from the reconstructor's setup to the stored result,
    40 vs 80 frames with 4-frame chunks (and 4-frame blocks in the compression, whose sketch of 34 shapes
    is full from 34 frames on): 40 more frames of the whole shot would be 40 x V x 3 float64 (26 MB at
    26.7k) for each (T,V,3) array held."""
    V = len(ict.neutral)
    monkeypatch.setattr(streaming, "CHUNK_BYTES", 4 * 24 * V)
    monkeypatch.setattr(compress, "_BLOCK_VALUES", 4 * 3 * V)  # the storage policy's blocks: 4 frames too
    real_init = FitResidual.__init__

    def init(self, *a, **k):  # the peak from here on: the reconstruction and its storage, not the setup
        real_init(self, *a, **k)
        tracemalloc.reset_peak()

    monkeypatch.setattr(FitResidual, "__init__", init)
    peaks = {}
    for T in (40, 80):
        scene, obj, empties, truth, pts = _shot(ict, EXPR[:6], _poses(T))
        tracemalloc.start()
        try:
            r = reconstruct_from_bundles(scene, obj, ReconstructSettings(bind_frame=0, selected=empties))
            peaks[T] = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        assert len(r.frames) == T and r.keys
    shot = 40 * V * 3 * 8
    print(f"tracemalloc peak: 40 frames {peaks[40] / 1e6:.1f} MB, 80 frames {peaks[80] / 1e6:.1f} MB "
          f"(one (40,V,3) float64 array: {shot / 1e6:.1f} MB)")
    assert peaks[80] - peaks[40] < 0.25 * shot
