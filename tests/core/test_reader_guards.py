"""Point-cache readers refuse damaged data instead of returning it (issue 13)."""

import struct

import numpy as np
import pytest

from facelab_addon.core.capture import pointcache, pointcache_writer
from facelab_addon.core.errors import CacheFileError


@pytest.fixture
def seq():
    rng = np.random.default_rng(1)
    return rng.normal(size=(6, 5, 3)).astype(np.float32)


def _poke_float(p, offset, value, fmt="<f"):
    raw = bytearray(p.read_bytes())
    raw[offset : offset + 4] = struct.pack(fmt, value)
    p.write_bytes(bytes(raw))


def test_pc2_with_nan_positions_is_refused_naming_the_file_and_sample(tmp_path, seq):
    p = pointcache_writer.write_pc2(tmp_path / "a.pc2", seq)
    _poke_float(p, 32 + (4 * 5 * 3 + 2 * 3 + 1) * 4, float("nan"))  # sample 4, point 2, y
    with pytest.raises(CacheFileError, match=r"a\.pc2' has NaN or infinite positions in sample 4.*Re-export"):
        pointcache.read_pc2(p)
    with pytest.raises(CacheFileError, match=r"in sample 4;"):
        pointcache.read_cache(p, [0, 4])
    good = pointcache.read_cache(p, [0, 1, 5])  # the undamaged samples still read, exactly
    np.testing.assert_array_equal(good, seq[[0, 1, 5]])


def test_pc2_header_with_a_zero_or_nan_sample_rate_is_refused(tmp_path, seq):
    for rate in (0.0, float("nan")):
        p = pointcache_writer.write_pc2(tmp_path / "b.pc2", seq)
        _poke_float(p, 24, rate)  # header: magic(12) version(4) points(4) start(4) rate(4) samples(4)
        with pytest.raises(CacheFileError, match="the sample rate a positive number of frames"):
            pointcache.pc2_info(p)


def test_mdd_with_nan_times_or_positions_is_refused(tmp_path, seq):
    p = pointcache_writer.write_mdd(tmp_path / "c.mdd", seq)
    _poke_float(p, 8 + 4 * 2, float("inf"), ">f")  # time of sample 2
    with pytest.raises(CacheFileError, match=r"c\.mdd' has a NaN or infinite time for sample 2"):
        pointcache.read_mdd(p)
    p = pointcache_writer.write_mdd(tmp_path / "d.mdd", seq)
    info = pointcache.mdd_info(p)
    _poke_float(p, info.data_offset + (1 * 5 * 3) * 4, float("nan"), ">f")  # sample 1, point 0, x
    with pytest.raises(CacheFileError, match=r"MDD cache .*positions in sample 1;"):
        pointcache.read_cache(p)


@pytest.mark.parametrize("text, match", [
    ("v 0 0 0\nv 1 0 nan\nv 0 1 0\nf 1 2 3\n", r"line 2: NaN or infinite coordinate in 'v 1 0 nan'"),
    ("v 0 0 0\nv 1 0\nv 0 1 0\nf 1 2 3\n", r"line 2: a 'v' line needs 3 numbers, got 'v 1 0'"),
    ("v 0 0 0\nv 1 0 x\nf 1 2 3\n", r"line 2: a 'v' line needs 3 numbers, got 'v 1 0 x'"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n", r"line 4: a face names vertex 9 / UV 0, but the file has 3 vertices"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 a 3\n", r"line 4: face corner 'a' is not 'v', 'v/vt'"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n", r"line 4: face corner '0' names vertex 0 .*indices start at 1"),
    ("v 0 0 0\nv 1 0 0\nf 1 2\n", r"line 3: a face needs at least 3 corners, got 'f 1 2'"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1/4 2/4 3/4\n", r"line 4: a face names vertex 1 / UV 4, but the file has 3 vertices and 0 UVs"),
])
def test_garbage_obj_is_refused_naming_the_file_and_line(tmp_path, text, match):
    from facelab_addon.core.capture.obj import read_obj
    from facelab_addon.core.errors import MeshError, ObjFileError

    p = tmp_path / "bad.obj"
    p.write_text(text)
    with pytest.raises(ObjFileError, match=match) as ei:
        read_obj(p)
    assert "bad.obj" in str(ei.value) and "re-export" in str(ei.value).lower()
    assert isinstance(ei.value, MeshError) and isinstance(ei.value, ValueError)  # the CLI maps ValueError to exit 3


def test_obj_reader_reads_a_good_file_exactly(tmp_path):
    from facelab_addon.core.capture.obj import read_obj, read_obj_vertices

    p = tmp_path / "ok.obj"
    p.write_text("v 0 0 0\nv 1 0 0.5\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 0 1\nusemtl skin\nf 1/1 2/2 3/3\nf -3 -2 -1\n")
    m = read_obj(p)
    np.testing.assert_array_equal(m.vertices, [[0, 0, 0], [1, 0, 0.5], [0, 1, 0]])
    np.testing.assert_array_equal(m.poly_verts, [0, 1, 2, 0, 1, 2])
    np.testing.assert_array_equal(m.poly_uv, [0, 1, 2, -1, -1, -1])
    assert m.parts == ["skin"]
    np.testing.assert_array_equal(read_obj_vertices(p), m.vertices)
