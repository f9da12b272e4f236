"""PC2 / MDD files and the Mesh Cache modifier's sample mapping (no Blender).

Byte layouts are checked against hand-packed ``struct`` data; the modifier
semantics against hand-computed cases (the Blender cross-check is in
``tests/blender/test_caches.py``).
"""

import struct

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from facelab_addon.core.capture import integrate, meshcache, pointcache, pointcache_writer
from facelab_addon.core.errors import CacheFileError, CacheVertexCountError, FaceLabError, MeshError


@pytest.fixture
def seq():
    rng = np.random.default_rng(7)
    return rng.normal(size=(6, 5, 3))  # float64 on purpose


# --------------------------------------------------------------------------- bytes


def test_pc2_exact_bytes(tmp_path):
    frames = np.array([[[1.0, 2.0, 3.0]], [[4.0, 5.0, 6.5]]])  # T=2, V=1
    p = pointcache_writer.write_pc2(tmp_path / "a.pc2", frames, start=10.0, sample_rate=0.5)
    expect = b"POINTCACHE2\0" + struct.pack("<iiffi", 1, 1, 10.0, 0.5, 2) + struct.pack("<6f", 1, 2, 3, 4, 5, 6.5)
    assert p.read_bytes() == expect
    assert len(expect) == 32 + 24


def test_hand_made_pc2_is_read(tmp_path):
    raw = b"POINTCACHE2\0" + struct.pack("<iiffi", 1, 2, -3.0, 2.0, 1) + struct.pack("<6f", 0, 1, 2, 3, 4, 5)
    (tmp_path / "h.pc2").write_bytes(raw)
    data, start, rate = pointcache.read_pc2(tmp_path / "h.pc2")
    assert data.dtype == np.float32 and data.shape == (1, 2, 3)
    np.testing.assert_array_equal(data.ravel(), np.arange(6))
    assert (start, rate) == (-3.0, 2.0)


def test_mdd_exact_bytes(tmp_path):
    frames = np.array([[[1.0, 2.0, 3.0]], [[4.0, 5.0, 6.0]]])
    p = pointcache_writer.write_mdd(tmp_path / "a.mdd", frames, fps=25.0, start_frame=1)
    expect = struct.pack(">ii", 2, 1) + struct.pack(">2f", 1 / 25, 2 / 25) + struct.pack(">6f", 1, 2, 3, 4, 5, 6)
    assert p.read_bytes() == expect
    data, times = pointcache.read_mdd(p)
    np.testing.assert_array_equal(data, frames.astype(np.float32))
    np.testing.assert_allclose(times, [0.04, 0.08], rtol=1e-7)


# --------------------------------------------------------------------------- round trips, subsets, mmap


@pytest.mark.parametrize("fmt", ["PC2", "MDD"])
def test_round_trip_subset_and_mmap(tmp_path, seq, fmt):
    path = tmp_path / f"s.{fmt.lower()}"
    if fmt == "PC2":
        pointcache_writer.write_pc2(path, seq, start=3.0, sample_rate=1.0)
        full, start, rate = pointcache.read_pc2(path)
        assert (start, rate) == (3.0, 1.0)
        sub, _, _ = pointcache.read_pc2(path, frames=[4, 0, -1, 4])
        mm, _, _ = pointcache.read_pc2(path, mmap=True)
    else:
        pointcache_writer.write_mdd(path, seq, fps=24.0, start_frame=3)
        full, times = pointcache.read_mdd(path)
        np.testing.assert_allclose(times, (3 + np.arange(6)) / 24.0, rtol=1e-6)
        sub, t_sub = pointcache.read_mdd(path, frames=[4, 0, -1, 4])
        np.testing.assert_array_equal(t_sub, times[[4, 0, 5, 4]])
        mm, _ = pointcache.read_mdd(path, mmap=True)
    f32 = seq.astype(np.float32)
    assert full.dtype == np.float32 and full.dtype.isnative and full.shape == seq.shape
    np.testing.assert_array_equal(full, f32)
    np.testing.assert_array_equal(sub, f32[[4, 0, 5, 4]])
    assert sub.dtype == np.float32 and sub.dtype.isnative
    assert isinstance(mm, np.memmap) and not mm.flags.writeable
    np.testing.assert_array_equal(np.asarray(mm, dtype=np.float32), f32)
    np.testing.assert_array_equal(pointcache.read_cache(path), f32)  # format sniffed
    info = pointcache.cache_info(path)
    assert (info.format, info.num_samples, info.num_points) == (fmt, 6, 5)


def test_single_frame_and_streaming_writer(tmp_path, seq):
    pointcache_writer.write_pc2(tmp_path / "one.pc2", seq[0])
    np.testing.assert_array_equal(pointcache.read_pc2(tmp_path / "one.pc2")[0], seq[:1].astype(np.float32))
    with pointcache_writer.PointCacheWriter(tmp_path / "w.mdd", "MDD", 5, 6, times=np.arange(6) / 30.0) as w:
        for s in seq:
            w.write(s)
    np.testing.assert_array_equal(pointcache.read_mdd(tmp_path / "w.mdd")[0], seq.astype(np.float32))
    assert not (tmp_path / "w.mdd.tmp").exists()


# --------------------------------------------------------------------------- bad files


def test_missing_file(tmp_path):
    with pytest.raises(CacheFileError, match="not found"):
        pointcache.read_pc2(tmp_path / "nope.pc2")


def test_wrong_header(tmp_path, seq):
    p = pointcache_writer.write_pc2(tmp_path / "a.pc2", seq)
    raw = bytearray(p.read_bytes())
    raw[:12] = b"POINTCACHE3\0"
    p.write_bytes(bytes(raw))
    with pytest.raises(CacheFileError, match="not a PC2 file"):
        pointcache.read_pc2(p)


def test_truncated(tmp_path, seq):
    p = pointcache_writer.write_pc2(tmp_path / "a.pc2", seq)
    p.write_bytes(p.read_bytes()[:-7])
    with pytest.raises(CacheFileError, match="truncated.*6 samples of 5 points"):
        pointcache.read_pc2(p)
    p.write_bytes(b"POINTCACHE2\0\1\0")
    with pytest.raises(CacheFileError, match="shorter than the 32-byte header"):
        pointcache.pc2_info(p)
    m = pointcache_writer.write_mdd(tmp_path / "a.mdd", seq)
    m.write_bytes(m.read_bytes()[:-1])
    with pytest.raises(CacheFileError, match="truncated"):
        pointcache.read_mdd(m)


def test_bad_counts_and_wrong_format(tmp_path, seq):
    raw = b"POINTCACHE2\0" + struct.pack("<iiffi", 1, 3, 0.0, 1.0, 0)
    (tmp_path / "z.pc2").write_bytes(raw)
    with pytest.raises(CacheFileError, match="0 samples"):
        pointcache.read_pc2(tmp_path / "z.pc2")
    p = pointcache_writer.write_pc2(tmp_path / "a.pc2", seq)
    with pytest.raises(CacheFileError, match="is a PC2 file, not an MDD"):
        pointcache.read_mdd(p)
    # an MDD written little-endian by mistake
    le = struct.pack("<ii", 6, 5) + np.zeros(6, "<f4").tobytes() + seq.astype("<f4").tobytes()
    (tmp_path / "le.mdd").write_bytes(le)
    with pytest.raises(CacheFileError, match="little-endian"):
        pointcache.read_mdd(tmp_path / "le.mdd")
    with pytest.raises(CacheFileError, match="outside the 6 samples"):
        pointcache.read_pc2(p, frames=[6])


def test_vertex_count_mismatch(tmp_path, seq):
    info = pointcache.pc2_info(pointcache_writer.write_pc2(tmp_path / "a.pc2", seq))
    assert pointcache.check_vertex_count(info, 5) is info
    with pytest.raises(CacheVertexCountError, match="5 points but 'Face' has 7 vertices") as e:
        pointcache.check_vertex_count(info, 7, name="'Face'")
    assert isinstance(e.value, MeshError) and isinstance(e.value, FaceLabError)


def test_bad_writes_leave_existing_file(tmp_path, seq):
    p = pointcache_writer.write_pc2(tmp_path / "a.pc2", seq)
    before = p.read_bytes()
    bad = seq.copy()
    bad[3, 2, 1] = np.nan
    with pytest.raises(MeshError, match="Sample 3 has NaN"):
        pointcache_writer.write_pc2(p, bad)
    assert p.read_bytes() == before and not (tmp_path / "a.pc2.tmp").exists()
    with pytest.raises(MeshError, match=r"\(T,V,3\)"):
        pointcache_writer.write_mdd(tmp_path / "b.mdd", np.zeros((2, 4)))
    w = pointcache_writer.PointCacheWriter(tmp_path / "c.pc2", "PC2", 5, 6)
    w.write(seq[:2])
    with pytest.raises(MeshError, match="Only 2 of 6"):
        w.close()
    assert not (tmp_path / "c.pc2").exists()


# --------------------------------------------------------------------------- Mesh Cache modifier semantics


def _info(fmt="PC2", T=10, start=1.0, rate=1.0, times=None):
    return pointcache.CacheInfo("x", fmt, 4, T, start, rate, times, 0, np.dtype("<f4"))


def test_frame_mode_mapping():
    info = _info()
    # default frame_start = 0: scene frame f plays sample f (sample 1 on frame 1)
    i0, i1, w = meshcache.mesh_cache_samples([0, 1, 2], info, fps=24)
    np.testing.assert_array_equal(i0, [0, 1, 2])
    np.testing.assert_array_equal(i1, i0)
    # frame_start = 1: frame 1 -> sample 0; halves blend; out of range clamps
    i0, i1, w = meshcache.mesh_cache_samples([1, 1.5, -3, 10.5, 11, 50], info, fps=24, frame_start=1.0)
    np.testing.assert_array_equal(i0, [0, 0, 0, 9, 9, 9])
    np.testing.assert_array_equal(i1, [0, 1, 0, 9, 9, 9])
    assert w[1] == np.float32(0.5)
    # frame_scale 2: sample = 2 f - frame_start
    i0, i1, _ = meshcache.mesh_cache_samples([1, 2], info, fps=24, frame_scale=2.0, frame_start=2.0)
    np.testing.assert_array_equal(i0, [0, 2])
    # fractions below 1e-4 snap to the lower sample
    i0, i1, _ = meshcache.mesh_cache_samples([3.00005], info, fps=24)
    assert i0[0] == i1[0] == 3


def test_no_interpolation_rounds_half_up():
    i0, i1, _ = meshcache.mesh_cache_samples([0.49, 0.5, 2.5, 30], _info(), fps=24, interpolation="NONE")
    np.testing.assert_array_equal(i0, [0, 1, 3, 9])
    np.testing.assert_array_equal(i1, i0)


def test_time_and_factor_modes():
    times = (1 + np.arange(10)) / 24.0
    mdd = _info("MDD", times=times.astype(np.float32))
    # TIME + MDD: scene frame f is at f / fps seconds; sample i has time (1 + i) / 24
    i0, i1, w = meshcache.mesh_cache_samples([1, 3, 3.5, 0, 40], mdd, fps=24, time_mode="TIME")
    np.testing.assert_array_equal(i0, [0, 2, 2, 0, 9])
    assert i1[2] == 3 and abs(w[2] - 0.5) < 1e-4
    # TIME + PC2: Blender divides by fps twice: sample = (f / fps / fps - start) / rate
    pc2 = _info("PC2", start=0.0, rate=1.0 / 576)
    i0, i1, w = meshcache.mesh_cache_samples([3], pc2, fps=24, time_mode="TIME")
    assert i0[0] == 3
    # FACTOR: sample = clamp(f / fps, 0, 1) * T
    i0, _, _ = meshcache.mesh_cache_samples([12, 24, 48], _info(), fps=24, time_mode="FACTOR")
    np.testing.assert_array_equal(i0, [5, 9, 9])
    # CUSTOM play mode ignores the scene frame
    i0, _, _ = meshcache.mesh_cache_samples([1, 7], _info(), fps=24, play_mode="CUSTOM", eval_frame=4.0)
    np.testing.assert_array_equal(i0, [4, 4])


def test_blend_samples():
    s = np.arange(3 * 2 * 3, dtype=np.float32).reshape(3, 2, 3)
    out = meshcache.blend_samples(s, [0, 1, 2], [1, 1, 2], np.float32([0.25, 1, 1]))
    np.testing.assert_allclose(out[0], 0.75 * s[0] + 0.25 * s[1])
    np.testing.assert_array_equal(out[1:], s[1:])
    calls = []
    meshcache.blend_samples(lambda idx: calls.append(list(idx)) or s[idx], [2, 2], [2, 2], [1, 1])
    assert calls == [[2]]  # only the needed sample is read


def test_axis_conversion_matrix():
    np.testing.assert_array_equal(meshcache.axis_conversion_matrix(), np.eye(3))
    np.testing.assert_array_equal(meshcache.axis_conversion_matrix("POS_Z", "NEG_Z"), np.eye(3))  # invalid: ignored
    M = meshcache.axis_conversion_matrix("NEG_Z", "POS_Y")
    np.testing.assert_array_equal(M @ [0, 1, 0], [0, 0, -1])  # cache +Y -> forward
    np.testing.assert_array_equal(M @ [0, 0, 1], [0, 1, 0])  # cache +Z -> up
    for fw in meshcache._AXES:
        for up in meshcache._AXES:
            A = meshcache.axis_conversion_matrix(fw, up)
            np.testing.assert_allclose(A @ A.T, np.eye(3))
            assert np.isclose(np.linalg.det(A), 1.0)
    F = meshcache.axis_conversion_matrix("NEG_Z", "POS_Y", (False, True, False))
    np.testing.assert_array_equal(F, np.diag([1, -1, 1]) @ M)  # flips after the conversion


def _tet():
    rest = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [5, 5, 5]], float)  # last one loose
    faces = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    return rest, np.arange(0, 13, 3), faces.ravel()


def test_integrate_matrices_identities():
    rest, off, cv = _tet()
    M = integrate.integrate_matrices(rest, rest + [0.3, -1, 2], off, cv)
    np.testing.assert_allclose(M[:4], np.broadcast_to(np.eye(3), (4, 3, 3)), atol=1e-12)
    np.testing.assert_array_equal(M[4], 0)  # loose vertex: Blender drops the offset
    R = Rotation.from_euler("xyz", [0.3, -0.5, 1.1]).as_matrix()
    M = integrate.integrate_matrices(rest, rest @ R.T * 2.0, off, cv)
    np.testing.assert_allclose(M[:4], np.broadcast_to(2.0 * R, (4, 3, 3)), atol=1e-12)
    rng = np.random.default_rng(0)
    M = integrate.integrate_matrices(rest, rest + rng.normal(size=rest.shape) * 0.1, off, cv)
    want = rng.normal(size=(5, 3))
    key = integrate.integrate_offsets_to_key(M, want)
    np.testing.assert_allclose(np.einsum("vij,vj->vi", M[:4], key[:4]), want[:4], atol=1e-12)
    np.testing.assert_array_equal(key[4], 0)


def test_large_read_is_float32_and_subset_reads_only_samples(tmp_path):
    """1000 x 2000 points: reads stay float32; a subset of 3 samples is 3 samples big."""
    T_, V_ = 1000, 2000
    with pointcache_writer.PointCacheWriter(tmp_path / "big.pc2", "PC2", V_, T_) as w:
        for t in range(T_):
            w.write(np.full((V_, 3), t, dtype=np.float32))
    mm, _, _ = pointcache.read_pc2(tmp_path / "big.pc2", mmap=True)
    assert isinstance(mm, np.memmap) and mm.shape == (T_, V_, 3)
    sub, _, _ = pointcache.read_pc2(tmp_path / "big.pc2", frames=[999, 0, 500])
    assert sub.dtype == np.float32 and sub.nbytes == 3 * V_ * 12
    np.testing.assert_array_equal(sub[:, 0, 0], [999, 0, 500])
    out = meshcache.blend_samples(mm, [10, 20], [11, 20], np.float32([0.5, 1]))
    np.testing.assert_array_equal(out[:, 0, 0], [10.5, 20])
