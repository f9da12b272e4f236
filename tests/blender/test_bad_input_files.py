"""Bad files FaceLab reads or writes (no Blender needed): every reader validates before use and names the
file, the problem and the fix; every writer refuses an unwritable destination with an OutputError and leaves
what was there untouched."""

import os

import numpy as np
import pytest

from facelab_addon.core.capture import obj as objfile
from facelab_addon.core.capture import pointcache, pointcache_writer
from facelab_addon.core.errors import CacheFileError, FaceLabError, MeshError, ObjFileError, OutputError

SEQ = np.arange(4 * 5 * 3, dtype=np.float32).reshape(4, 5, 3) / 7.0  # T=4 samples of V=5 points


def unwritable_folder(tmp_path):
    """A folder the process cannot write into: /sys for root (whom permission bits do not stop), else 0o555."""
    if os.geteuid() == 0:
        return "/sys/facelab_never"
    d = tmp_path / "ro"
    d.mkdir()
    d.chmod(0o555)
    return d


# --------------------------------------------------------------------------- PC2 / MDD readers


def test_damaged_pc2_is_never_read_as_mdd(tmp_path):
    good = pointcache_writer.write_pc2(tmp_path / "perf.pc2", SEQ)
    raw = bytearray(good.read_bytes())
    raw[3] = ord("X")  # b"POIXTCACHE2\0": one damaged byte of the magic
    bad = tmp_path / "damaged.pc2"
    bad.write_bytes(bytes(raw))
    assert pointcache.detect_format(bad) == "PC2"  # the extension decides
    with pytest.raises(CacheFileError, match=r"damaged\.pc2' is not a PC2 file.*Pick a \.pc2"):
        pointcache.read_cache(bad)
    # without a telling extension, a header that starts like PC2 is refused, not guessed as MDD
    other = tmp_path / "damaged.cache"
    other.write_bytes(bytes(raw))
    with pytest.raises(CacheFileError, match=r"starts like a PC2 point cache but its magic is damaged.*Re-export"):
        pointcache.cache_info(other)
    # the real thing still reads, with or without the extension
    np.testing.assert_array_equal(pointcache.read_cache(good), SEQ)
    (tmp_path / "plain.cache").write_bytes(good.read_bytes())
    assert pointcache.cache_info(tmp_path / "plain.cache").format == "PC2"
    mdd = pointcache_writer.write_mdd(tmp_path / "perf.mdd", SEQ)
    assert pointcache.cache_info(mdd).format == "MDD"


def test_pc2_header_and_nan_samples(tmp_path):
    p = pointcache_writer.write_pc2(tmp_path / "perf.pc2", SEQ, sample_rate=1.0)
    raw = bytearray(p.read_bytes())
    raw[24:28] = np.float32(0.0).tobytes()  # sample rate 0
    bad = tmp_path / "rate0.pc2"
    bad.write_bytes(bytes(raw))
    with pytest.raises(CacheFileError, match=r"rate0\.pc2' has start frame 1 and sample rate 0.*Re-export"):
        pointcache.pc2_info(bad)
    raw = bytearray(p.read_bytes())
    off = 32 + 2 * 5 * 12 + 4  # sample 2, point 0, y
    raw[off:off + 4] = np.float32(np.nan).tobytes()
    nan = tmp_path / "nan.pc2"
    nan.write_bytes(bytes(raw))
    with pytest.raises(CacheFileError, match=r"nan\.pc2' has NaN or infinite positions in sample 2"):
        pointcache.read_pc2(nan)
    with pytest.raises(CacheFileError, match="sample 2"):
        pointcache.read_cache(nan, frames=[3, 2])
    np.testing.assert_array_equal(pointcache.read_cache(nan, frames=[0, 1, 3]), SEQ[[0, 1, 3]])  # the rest is fine


def test_mdd_nan_time(tmp_path):
    p = pointcache_writer.write_mdd(tmp_path / "perf.mdd", SEQ)
    raw = bytearray(p.read_bytes())
    raw[8 + 4:8 + 8] = np.array([np.inf], ">f4").tobytes()
    p.write_bytes(bytes(raw))
    with pytest.raises(CacheFileError, match=r"NaN or infinite time for sample 1"):
        pointcache.mdd_info(p)


# --------------------------------------------------------------------------- OBJ reader


def write(path, text):
    path.write_text(text)
    return path


def test_obj_nan_and_inf_are_refused_with_the_line(tmp_path):
    p = write(tmp_path / "nan.obj", "# face\nv 0 0 0\nv 1 nan 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(ObjFileError, match=r"nan\.obj, line 3: NaN or infinite coordinate in 'v 1 nan 0'"):
        objfile.read_obj(p)
    with pytest.raises(ObjFileError, match="line 3"):
        objfile.read_obj_vertices(p)
    p = write(tmp_path / "inf.obj", "v 0 0 0\nv 1 0 0\nv 0 1 -inf\nf 1 2 3\n")
    with pytest.raises(MeshError, match=r"line 3: NaN or infinite"):  # a MeshError (and a ValueError)
        objfile.read_obj(p)


@pytest.mark.parametrize("text, message", [
    ("v 0 0\nv 1 0 0\n", r"line 1: a 'v' line needs 3 numbers, got 'v 0 0'"),
    ("v a b c\n", r"line 1: a 'v' line needs 3 numbers"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 7\n", r"line 4: a face names vertex 7 / UV 0, but the file has 3 vertices"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2\n", r"line 4: a face needs at least 3 corners"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 x 3\n", r"line 4: face corner 'x' is not"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 -9\n", r"line 4: face corner '-9' names vertex -9"),
])
def test_obj_malformed_lines(tmp_path, text, message):
    with pytest.raises(ObjFileError, match=message):
        objfile.read_obj(write(tmp_path / "bad.obj", text))


def test_obj_binary_garbage_and_a_good_file(tmp_path):
    garbage = tmp_path / "garbage.obj"
    garbage.write_bytes(bytes(range(256)) * 8)
    with pytest.raises(ObjFileError, match="binary file, not a Wavefront OBJ"):
        objfile.read_obj(garbage)
    good = write(tmp_path / "ok.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nvt 0 0\nvt 1 1\n"
                                      "usemtl skin\nf 1/1 2/2 -1/1\nf -3 4 3\n")
    m = objfile.read_obj(good)
    np.testing.assert_array_equal(m.poly_verts, [0, 1, 3, 1, 3, 2])  # -1 = the last vertex so far
    np.testing.assert_array_equal(m.poly_uv, [0, 1, 0, -1, -1, -1])
    assert m.parts == ["skin"] and m.poly_offsets.tolist() == [0, 3, 6]


# --------------------------------------------------------------------------- writers


def test_writer_refuses_unwritable_destinations_and_keeps_the_old_file(tmp_path):
    blocker = tmp_path / "shots"
    blocker.write_text("a file where a folder is expected")
    with pytest.raises(OutputError, match=r"Cannot write '.*shots/x\.pc2': '.*shots' is a file, not a folder"):
        pointcache_writer.write_pc2(blocker / "x.pc2", SEQ)
    with pytest.raises(OutputError, match="is a file, not a folder"):
        pointcache_writer.write_mdd(blocker / "deeper" / "x.mdd", SEQ)
    assert blocker.read_text() == "a file where a folder is expected"
    with pytest.raises(OutputError, match="it is a folder"):
        pointcache_writer.write_pc2(tmp_path, SEQ)
    ro = unwritable_folder(tmp_path)
    with pytest.raises(OutputError, match="(read-only|permission denied)"):
        pointcache_writer.write_pc2(os.path.join(ro, "x.pc2"), SEQ)
    assert issubclass(OutputError, FaceLabError)


def test_writer_failures_after_opening_are_output_errors(tmp_path, monkeypatch):
    old = pointcache_writer.write_pc2(tmp_path / "perf.pc2", SEQ)
    before = old.read_bytes()

    def full_disk(*a, **k):
        raise OSError(28, "No space left on device")

    w = pointcache_writer.PointCacheWriter(old, "PC2", 5, 4)
    w.write(SEQ[:2])
    real = w._f

    class Full:  # the open file, once the disk is full
        def write(self, b):
            full_disk()

        def close(self):
            real.close()
    w._f = Full()
    with pytest.raises(OutputError, match=r"perf\.pc2': the disk is full"):
        w.write(SEQ[2])
    assert old.read_bytes() == before and not (tmp_path / "perf.pc2.tmp").exists()
    w = pointcache_writer.PointCacheWriter(old, "PC2", 5, 4)
    w.write(SEQ)
    monkeypatch.setattr(pointcache_writer.os, "replace", lambda *a: (_ for _ in ()).throw(PermissionError(13, "x")))
    with pytest.raises(OutputError, match="permission denied"):
        w.close()
    assert old.read_bytes() == before and not (tmp_path / "perf.pc2.tmp").exists()


# --------------------------------------------------------------------------- generated file names


def test_one_sanitiser_keeps_letters_of_every_script_and_bounds_the_bytes():
    from facelab_addon.names import NAME_PART_BYTES, file_name_part

    assert file_name_part("visage é") == "visage_é"  # 'é' is a letter, as Cyrillic is
    assert file_name_part("Лицо.001/x") == "Лицо_001_x"
    assert file_name_part("visage e\u0301") == "visage_é"  # decomposed accent: one letter (NFC)
    assert file_name_part("") == "_" and file_name_part("a b:c*?") == "a_b_c__"
    long_a, long_b = "Л" * 150, "Л" * 149 + "Ж"
    a, b = file_name_part(long_a), file_name_part(long_b)
    assert len(a.encode()) <= NAME_PART_BYTES and len(b.encode()) <= NAME_PART_BYTES
    assert a != b and a.startswith("Л" * 30) and "~" in a  # cut on a letter, told apart by a hash


def test_a_name_the_file_system_cannot_hold_is_an_output_error(tmp_path):
    name = "Л" * 126 + ".pc2"  # 256 bytes
    with pytest.raises(OutputError, match=r"is 256 bytes long in UTF-8.*more than the file system's limit of 255"):
        pointcache_writer.check_writable(tmp_path / name)
    with pytest.raises(OutputError, match=r"more than the file system's limit"):  # with the writer's '.tmp'
        pointcache_writer.PointCacheWriter(tmp_path / ("x" * 252 + ".pc2"), "PC2", 5, 4)
    with pytest.raises(OutputError, match="the path is"):
        pointcache_writer.check_writable(tmp_path / "/".join(["d" * 200] * 25) / "x.pc2")
    assert not list(tmp_path.iterdir())
    ok = pointcache_writer.write_pc2(tmp_path / ("Л" * 120 + ".pc2"), SEQ)  # 244 bytes: fits
    assert pointcache.read_pc2(ok)[0].shape == SEQ.shape
