"""Correction caches in core: the samples a stored correction's cache holds (correction_layout) and the block
writer (write_offset_cache) give fixed positions plus the correction on every stored frame, the positions alone
on a skipped whole frame, and the MDD times of the scene's clock."""

import numpy as np
import pytest

from facelab_addon.core.capture.pointcache import read_mdd, read_pc2
from facelab_addon.core.capture.pointcache_writer import correction_layout, write_offset_cache
from facelab_addon.core.errors import FaceLabError


def _reader(D, calls=None):
    def read(i, j):
        if calls is not None:
            calls.append((i, j))
        return D[i:j]

    return read


def test_pc2_of_base_plus_the_correction_on_a_subset_with_a_skipped_frame(tmp_path):
    rng = np.random.default_rng(0)
    base = rng.standard_normal((7, 3)).astype(np.float32)
    verts = np.array([1, 4, 6])
    frames = np.array([6.0, 3.0, 4.0])  # stored out of order, frame 5 skipped
    D = rng.standard_normal((3, 3, 3)).astype(np.float32)
    layout = correction_layout(frames, "pc2", fps=24.0)
    assert layout.format == "PC2" and layout.span.tolist() == [3.0, 4.0, 5.0, 6.0]
    assert [layout.row(f) for f in layout.span] == [1, 2, None, 0]
    write_offset_cache(tmp_path / "c.pc2", layout, _reader(D), base, verts)
    got, start, rate = read_pc2(tmp_path / "c.pc2")
    assert (start, rate) == (3.0, 1.0) and got.shape == (4, 7, 3)
    want = np.repeat(base[None], 4, axis=0)
    want[0, verts] += D[1]
    want[1, verts] += D[2]
    want[3, verts] += D[0]  # frame 5 holds the base alone
    np.testing.assert_array_equal(got, want)


def test_consecutive_rows_are_read_as_one_block_and_mdd_keeps_the_scene_clock(tmp_path):
    D = np.arange(5 * 4 * 3, dtype=np.float32).reshape(5, 4, 3)
    frames = 10.0 + 0.5 * np.arange(5)  # evenly spaced sub-frames
    layout = correction_layout(frames, "MDD", fps=25.0)
    calls = []
    write_offset_cache(tmp_path / "c.mdd", layout, _reader(D, calls), np.zeros((4, 3), np.float32))
    assert calls == [(0, 5)]  # one read for the whole run of rows
    got, times = read_mdd(tmp_path / "c.mdd")
    np.testing.assert_array_equal(got, D)
    np.testing.assert_allclose(times, frames / 25.0, rtol=1e-6)


def test_uneven_sub_frames_are_refused():
    with pytest.raises(FaceLabError, match="whole or evenly spaced frames"):
        correction_layout([1.0, 1.5, 2.25], "PC2", fps=24.0)
