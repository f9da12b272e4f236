"""PC2 and MDD point-cache files: formats, headers and reading.

A captured facial performance often reaches Blender as a vertex cache: a file
that stores every vertex position of every frame, played back by a *Mesh Cache*
modifier. This module reads the two formats that modifier reads, so
the captured sequence ``(T,V,3)`` can be read straight from the file instead of
evaluating Blender frame by frame (the modifier's frame-to-sample mapping is
:mod:`.meshcache`).

Formats (exactly what Blender's ``MOD_meshcache_pc2.cc`` / ``_mdd.cc`` read)
-------------------------------------------------------------------------
PC2 (3ds Max *Point Cache 2*), little-endian::

    char[12]  b"POINTCACHE2\\0"
    int32     version (1)
    int32     numPoints
    float32   startFrame      (frames)
    float32   sampleRate      (frames between samples)
    int32     numSamples
    float32   xyz[numSamples][numPoints][3]

MDD (LightWave *Motion Designer*), big-endian, no magic number::

    int32     numFrames
    int32     numPoints
    float32   times[numFrames]   (seconds)
    float32   xyz[numFrames][numPoints][3]

Positions are object-local, scene units. Reading never converts to float64:
``mmap=True`` returns a read-only ``np.memmap`` view of the file, and
``frames=`` reads only the requested samples, so 1000 frames of a
26,719-vertex face (320 MB of float32) need not be loaded at once. Files are
written by :mod:`.pointcache_writer`.

No bpy in this module.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import CacheFileError, CacheVertexCountError

__all__ = [
    "CacheInfo",
    "PC2_MAGIC",
    "pc2_info",
    "mdd_info",
    "detect_format",
    "cache_info",
    "check_vertex_count",
    "check_finite_samples",
    "read_pc2",
    "read_mdd",
    "read_cache",
]

PC2_MAGIC = b"POINTCACHE2\0"
PC2_HEADER_BYTES = 32
PC2_HEADER = np.dtype(
    [
        ("magic", "S12"),
        ("version", "<i4"),
        ("num_points", "<i4"),
        ("start_frame", "<f4"),
        ("sample_rate", "<f4"),
        ("num_samples", "<i4"),
    ]
)


@dataclass(frozen=True)
class CacheInfo:
    """Header of a point-cache file.

    Attributes
    ----------
    path : str
    format : str
        ``"PC2"`` or ``"MDD"``.
    num_points : int
        V, points per sample.
    num_samples : int
        T, samples in the file.
    start_frame : float or None
        PC2 only: frame of sample 0 (frames).
    sample_rate : float or None
        PC2 only: frames between two samples.
    times : (T,) float32 ndarray or None
        MDD only: time of every sample, seconds.
    data_offset : int
        Byte offset of the first coordinate.
    dtype : numpy.dtype
        On-disk dtype of the coordinates (``<f4`` for PC2, ``>f4`` for MDD).
    """

    path: str
    format: str
    num_points: int
    num_samples: int
    start_frame: float | None
    sample_rate: float | None
    times: np.ndarray | None
    data_offset: int
    dtype: np.dtype

    @property
    def nbytes(self) -> int:
        """Bytes of coordinate data, ``T * V * 12``."""
        return self.num_samples * self.num_points * 12


# --------------------------------------------------------------------------- headers


def _open_size(path, what):
    p = Path(os.fspath(path))
    if not p.is_file():
        raise CacheFileError(
            f"{what} file not found: '{p}'. Check the path (a Mesh Cache modifier's path is "
            "relative to the .blend when it starts with //)."
        )
    return p, p.stat().st_size


def _check_data_size(p, size, offset, T, V, what):
    need = offset + T * V * 12
    if size < need:
        have = max(size - offset, 0) // (V * 12) if V > 0 else 0
        raise CacheFileError(
            f"{what} file '{p}' is truncated: its header announces {T} samples of {V} points "
            f"({need} bytes) but the file has {size} bytes (about {have} whole samples). "
            "Re-export or re-copy the cache."
        )


def pc2_info(path) -> CacheInfo:
    """Read and check the header of a PC2 file.

    Parameters
    ----------
    path : str or os.PathLike

    Returns
    -------
    CacheInfo

    Raises
    ------
    CacheFileError
        Missing file, wrong magic (not ``b"POINTCACHE2\\0"``), a non-positive
        point or sample count, a non-finite start frame or a non-positive
        sample rate, or a file shorter than its header announces.
    """
    p, size = _open_size(path, "PC2")
    if size < PC2_HEADER_BYTES:
        raise CacheFileError(
            f"PC2 file '{p}' is truncated: {size} bytes, shorter than the 32-byte header. "
            "Re-export the cache."
        )
    with open(p, "rb") as f:
        raw = f.read(PC2_HEADER_BYTES)
    if raw[:12] != PC2_MAGIC:
        hint = ""
        if raw[:11] == PC2_MAGIC[:11]:
            hint = " (the magic is not NUL-terminated)"
        raise CacheFileError(
            f"'{p}' is not a PC2 file: it starts with {raw[:12]!r} instead of {PC2_MAGIC!r}{hint}. "
            "Pick a .pc2 point cache, or set the Mesh Cache format to MDD if it is an MDD file."
        )
    h = np.frombuffer(raw, dtype=PC2_HEADER)[0]
    V, T = int(h["num_points"]), int(h["num_samples"])
    if V <= 0 or T <= 0:
        raise CacheFileError(
            f"PC2 file '{p}' has {V} points and {T} samples in its header; a cache needs at least "
            "one of each. Re-export the cache."
        )
    start, rate = float(h["start_frame"]), float(h["sample_rate"])
    if not (np.isfinite(start) and np.isfinite(rate) and rate > 0):
        raise CacheFileError(
            f"PC2 file '{p}' has start frame {start:g} and sample rate {rate:g} in its header; the start must "
            "be a finite frame and the sample rate a positive number of frames. Re-export the cache."
        )
    _check_data_size(p, size, PC2_HEADER_BYTES, T, V, "PC2")
    return CacheInfo(
        path=str(p),
        format="PC2",
        num_points=V,
        num_samples=T,
        start_frame=start,
        sample_rate=rate,
        times=None,
        data_offset=PC2_HEADER_BYTES,
        dtype=np.dtype("<f4"),
    )


def mdd_info(path) -> CacheInfo:
    """Read and check the header (counts and time table) of an MDD file.

    Parameters
    ----------
    path : str or os.PathLike

    Returns
    -------
    CacheInfo
        ``times`` holds the (T,) float32 sample times in seconds.

    Raises
    ------
    CacheFileError
        Missing file, a PC2 file given as MDD, implausible counts (for
        example a little-endian file) or a file shorter than announced.
    """
    p, size = _open_size(path, "MDD")
    if size < 8:
        raise CacheFileError(f"MDD file '{p}' is truncated: {size} bytes, shorter than the 8-byte header.")
    with open(p, "rb") as f:
        head = f.read(12)
    if head == PC2_MAGIC:
        raise CacheFileError(
            f"'{p}' is a PC2 file, not an MDD file. Set the Mesh Cache format to PC2 (or read it with read_pc2)."
        )
    T, V = (int(x) for x in np.frombuffer(head[:8], dtype=">i4"))
    if T <= 0 or V <= 0:
        raise CacheFileError(
            f"MDD file '{p}' has {T} frames and {V} points in its header; a cache needs at least one "
            "of each. Is it really an MDD file (big-endian)? Re-export the cache."
        )
    offset = 8 + 4 * T
    need = offset + T * V * 12
    if size < need and size >= 8:
        # A little-endian writer produces absurd counts; say so instead of "truncated".
        Tl, Vl = (int(x) for x in np.frombuffer(head[:8], dtype="<i4"))
        if Tl > 0 and Vl > 0 and 8 + 4 * Tl + 12 * Tl * Vl == size:
            raise CacheFileError(
                f"MDD file '{p}' is little-endian ({Tl} frames, {Vl} points); MDD must be big-endian. "
                "Re-export it with an MDD writer that follows the format (Blender's, or FaceLab's write_mdd)."
            )
    _check_data_size(p, size, offset, T, V, "MDD")
    times = np.fromfile(p, dtype=">f4", count=T, offset=8).astype(np.float32)
    if not np.isfinite(times).all():
        bad = int(np.flatnonzero(~np.isfinite(times))[0])
        raise CacheFileError(
            f"MDD file '{p}' has a NaN or infinite time for sample {bad} in its header. Re-export the cache."
        )
    return CacheInfo(
        path=str(p),
        format="MDD",
        num_points=V,
        num_samples=T,
        start_frame=None,
        sample_rate=None,
        times=times,
        data_offset=offset,
        dtype=np.dtype(">f4"),
    )


def detect_format(path) -> str:
    """``"PC2"`` or ``"MDD"``: the format a point-cache file must be read as.

    The extension decides (``.pc2`` / ``.mdd``, any case); a file with another
    extension is PC2 when it starts with the PC2 magic and MDD otherwise,
    except that a file starting like a PC2 header whose magic is damaged is
    refused rather than read as MDD.

    Parameters
    ----------
    path : str or os.PathLike

    Returns
    -------
    str

    Raises
    ------
    CacheFileError
        Missing file, or a damaged PC2 magic in a file of another extension.
    """
    p, size = _open_size(path, "Point cache")
    ext = p.suffix.lower()
    if ext == ".pc2":
        return "PC2"
    if ext == ".mdd":
        return "MDD"
    with open(p, "rb") as f:
        raw = f.read(PC2_HEADER_BYTES)
    head = raw[:12]
    if head == PC2_MAGIC:
        return "PC2"
    like_magic = sum(a == b for a, b in zip(head.upper(), PC2_MAGIC)) >= 6
    like_header = False
    if len(raw) == PC2_HEADER_BYTES:
        h = np.frombuffer(raw, dtype=PC2_HEADER)[0]
        V, T = int(h["num_points"]), int(h["num_samples"])
        like_header = int(h["version"]) == 1 and V > 0 and T > 0 and PC2_HEADER_BYTES + 12 * V * T == size
    if like_magic or like_header:
        raise CacheFileError(
            f"'{p}' starts like a PC2 point cache but its magic is damaged ({head!r} instead of "
            f"{PC2_MAGIC!r}). Re-export the cache (or repair its first 12 bytes)."
        )
    return "MDD"


def cache_info(path, fmt: str | None = None) -> CacheInfo:
    """Header of a PC2 or MDD file.

    Parameters
    ----------
    path : str or os.PathLike
    fmt : {"PC2", "MDD"}, optional
        Default: :func:`detect_format` (the extension, else the header); a
        damaged file is refused, never read as the other format.

    Returns
    -------
    CacheInfo

    Raises
    ------
    CacheFileError
        See :func:`pc2_info`, :func:`mdd_info` and :func:`detect_format`.
    """
    if fmt is None:
        fmt = detect_format(path)
    fmt = str(fmt).upper()
    if fmt == "PC2":
        return pc2_info(path)
    if fmt == "MDD":
        return mdd_info(path)
    raise CacheFileError(f"Unknown point-cache format '{fmt}'; use 'PC2' or 'MDD'.")


def check_vertex_count(info: CacheInfo, num_vertices: int, *, name: str = "the mesh") -> CacheInfo:
    """Raise unless the cache has one point per mesh vertex.

    Parameters
    ----------
    info : CacheInfo
    num_vertices : int
        V of the mesh the cache is played on.
    name : str
        The mesh/object name, for the message.

    Returns
    -------
    CacheInfo
        ``info``, unchanged.

    Raises
    ------
    CacheVertexCountError
        (a ``CacheFileError`` and a ``MeshError``) when the counts differ.
    """
    if info.num_points != int(num_vertices):
        raise CacheVertexCountError(
            f"{info.format} cache '{info.path}' has {info.num_points} points but {name} has "
            f"{int(num_vertices)} vertices. Use the cache exported from this mesh (same topology, "
            "no modifiers that add or remove vertices), or re-export it."
        )
    return info


# --------------------------------------------------------------------------- reading


def _sample_index(frames, T, path):
    idx = np.asarray(frames)
    if idx.dtype == bool:
        raise CacheFileError("frames= must be sample indices (ints), not a mask; use np.flatnonzero(mask).")
    if not np.issubdtype(idx.dtype, np.integer):
        raise CacheFileError(
            f"frames= must be integer sample indices (0-based), got dtype {idx.dtype}; "
            "convert scene frames with mesh_cache_samples first."
        )
    idx = idx.astype(np.int64).reshape(-1)
    bad = (idx < -T) | (idx >= T)
    if bad.any():
        raise CacheFileError(
            f"Sample indices {idx[bad][:5].tolist()} are outside the {T} samples of '{path}' "
            f"(valid: 0..{T - 1}); ask for samples the cache has."
        )
    return np.where(idx < 0, idx + T, idx)


def gather_f32(source, idx=None) -> np.ndarray:
    """Samples ``source[idx]`` (all when None) as a new native float32 (k,V,3) array.

    Copies one sample at a time, so a memmap (any byte order) is read once
    and no temporary of the whole selection is made.
    """
    n = len(source) if idx is None else len(idx)
    out = np.empty((n,) + tuple(source.shape[1:]), dtype=np.float32)
    for k in range(n):
        out[k] = source[k if idx is None else int(idx[k])]
    return out


def check_finite_samples(info: CacheInfo, samples, sample_index=None) -> None:
    """Raise unless every position read from a cache file is finite.

    Parameters
    ----------
    info : CacheInfo
    samples : (k,V,3) float ndarray
        Positions read from ``info.path``.
    sample_index : (k,) int array_like, optional
        The file's sample of each row (for the message); default ``0..k-1``.

    Raises
    ------
    CacheFileError
        Naming the file and the first sample with a NaN or infinite position.
    """
    for k in range(len(samples)):
        if not np.isfinite(samples[k]).all():
            s = k if sample_index is None else int(np.asarray(sample_index).reshape(-1)[k])
            raise CacheFileError(
                f"{info.format} cache '{info.path}' has NaN or infinite positions in sample {s}; the file is "
                "damaged or was exported from a broken mesh. Re-export the cache."
            )


def _read_samples(info: CacheInfo, frames, mmap: bool) -> np.ndarray:
    shape = (info.num_samples, info.num_points, 3)
    mm = np.memmap(info.path, dtype=info.dtype, mode="r", offset=info.data_offset, shape=shape)
    if frames is None:
        if mmap:
            return mm
        out = gather_f32(mm)
        check_finite_samples(info, out)
        return out
    idx = _sample_index(frames, info.num_samples, info.path)
    out = gather_f32(mm, idx)
    check_finite_samples(info, out, idx)
    return out


def read_pc2(path, frames=None, *, mmap: bool = False):
    """Read a PC2 point cache.

    Parameters
    ----------
    path : str or os.PathLike
    frames : array_like of int, optional
        0-based sample indices to read (in any order, repeats allowed). Only
        these samples are read from disk. Default: all samples.
    mmap : bool
        With ``frames=None``, return a read-only ``np.memmap`` of shape
        (T,V,3) (dtype ``<f4``, native on little-endian machines) instead of
        loading the file: nothing is copied until it is indexed.

    Returns
    -------
    frames : (T,V,3) float32 ndarray (or np.memmap)
        Object-local positions, scene units. T is ``len(frames)`` when given.
    start_frame : float
        Header start frame (frames).
    sample_rate : float
        Header sample rate (frames between samples).

    Raises
    ------
    CacheFileError
        See ``pc2_info``; also for out-of-range ``frames``.
    """
    info = pc2_info(path)
    return _read_samples(info, frames, mmap), info.start_frame, info.sample_rate


def read_mdd(path, frames=None, *, mmap: bool = False):
    """Read an MDD point cache.

    Parameters
    ----------
    path : str or os.PathLike
    frames : array_like of int, optional
        0-based sample indices to read. Default: all samples.
    mmap : bool
        With ``frames=None``, return a read-only ``np.memmap`` of shape
        (T,V,3) with the on-disk big-endian dtype ``>f4`` (NumPy computes
        with it transparently; ``np.asarray(x, np.float32)`` converts).

    Returns
    -------
    frames : (T,V,3) float32 ndarray (or np.memmap)
        Object-local positions, scene units.
    times : (T,) float32 ndarray
        Sample times in seconds (of the returned samples when ``frames`` is
        given).

    Raises
    ------
    CacheFileError
        See ``mdd_info``; also for out-of-range ``frames``.
    """
    info = mdd_info(path)
    data = _read_samples(info, frames, mmap)
    times = info.times if frames is None else info.times[_sample_index(frames, info.num_samples, info.path)]
    return data, times


def read_cache(path, frames=None, *, fmt: str | None = None, mmap: bool = False):
    """Positions of a PC2 or MDD file, whichever it is.

    Parameters
    ----------
    path : str or os.PathLike
    frames : array_like of int, optional
        0-based sample indices. Default: all.
    fmt : {"PC2", "MDD"}, optional
        Default: detected from the file.
    mmap : bool
        See ``read_pc2``.

    Returns
    -------
    (T,V,3) float32 ndarray
        Object-local positions, scene units.
    """
    info = cache_info(path, fmt)
    return _read_samples(info, frames, mmap)
