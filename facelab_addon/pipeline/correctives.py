"""How per-frame corrections are stored: a few corrective shape keys, or a point cache.

Every feature that produces a correction per frame (Propagate, Solve's out-of-subspace
corrective, Retarget, Reconstruct) stores it through one policy, :class:`CorrectionWriter`:

- the correction is streamed in chunks (``add``) to a float32 spool file, so memory is bounded
  by the chunk, not the shot; a correction measured on the evaluated mesh is first mapped back
  through the deforming modifiers to rest space (``blender.rest_space``);
- ``finish`` compresses it (:func:`facelab_addon.core.geometry.compress.compress_streamed`) to
  at most ``key_budget`` shapes keeping every vertex of every frame within the tolerance,
  a length in mm of the object's world space (scene unit scale and object scale included);
- when it fits, each shape becomes a key ``<prefix>NN`` with its weights keyed on the timeline;
  when it does not (a dense, full-rank correction), it is written as a PC2 (or MDD) point cache
  beside the .blend and played by a Mesh Cache modifier FaceLab adds at the top of the stack, and
  the result says so.

Re-running replaces only FaceLab's own output (keys: the registry of ``blender.shapekeys``;
caches: the modifier and files recorded by ``blender.bakes``); Review's *Show Capture* ends then, so
the face shows the new output with every other correction. :func:`write_corrective_keys` is
the one-call form for a whole (T,n,3) array.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from dataclasses import dataclass, field

import bpy
import numpy as np

from ..blender import bakes, cache_write, rest_space, review
from ..blender.objects import local_length, tolerance_length
from ..blender.ownership import correction_cache_factor, owned_keys
from ..blender.shapekeys import (
    add_keys_from_deltas,
    key_values_bulk,
    remove_keys,
    zero_on_frame,
)
from ..core.capture.pointcache_writer import correction_layout, write_offset_cache
from ..core.errors import FaceLabError, MeshError, OutputError
from ..core.geometry.compress import StorageOutcome, compress, compress_streamed, low_rank_reader
from ..names import STORE_SETTINGS_ATTR
from .settings import setting, stored

__all__ = ["StorageSettings", "CorrectionResult", "CorrectionWriter", "StoredKeys", "write_corrective_keys",
           "silence_correction"]

@dataclass
class StorageSettings:
    """How corrections are stored.

    Attributes
    ----------
    key_budget : int
        Most corrective shape keys a correction may use; past that it becomes a point cache.
    tolerance_mm : float
        Largest error of any vertex on any frame, mm of the object's world space.
    cache_format : str
        ``"PC2"`` or ``"MDD"``, both played by a Mesh Cache modifier.
    cache_directory : str
        Folder of the cache files; empty: the .blend's folder.
    """

    key_budget: int = setting(24, label="Key Budget", min=1, max=256, soft_max=64,
                              description="Most corrective shape keys one correction may use; a correction that "
                                          "needs more is written as a point cache beside the .blend")
    tolerance_mm: float = setting(0.01, label="Storage Tolerance", min=1e-5, soft_max=1.0, unit="mm",
                                  description="Largest error of any vertex on any frame when a correction is "
                                              "compressed into keys, in mm of the object's world space")
    cache_format: str = setting("PC2", label="Cache Format",
                                choices=(("PC2", "PC2", "Point cache read by a Mesh Cache modifier"),
                                         ("MDD", "MDD", "MDD point cache read by a Mesh Cache modifier")),
                                description="File format of a correction that does not fit the key budget")
    cache_directory: str = setting("", label="Cache Folder",
                                   description="Where dense corrections are written; empty: beside the .blend")


@dataclass
class CorrectionResult:
    """How a correction was stored.

    Attributes
    ----------
    outcome : StorageOutcome
        Keys (within the budget, or over it for want of a cache folder), a point cache (of the whole mesh, or a
        patch of the corrected vertices after the capture), or nothing (every frame's correction is below the
        tolerance).
    keys : list of str
        Shape keys written.
    cache_path : str
        The point cache written (empty unless ``mode == "cache"``).
    modifier : str
        The Mesh Cache modifier playing it.
    rank : int
        Shapes needed (keys), or the budget the correction did not fit in (cache).
    frames : int
        Frames stored.
    max_error_mm : float
        Largest vertex error of the stored correction, mm of world space (NaN if unmeasured).
    tolerance_mm : float
    note : str
        One sentence for the operator's report.
    """

    outcome: StorageOutcome
    keys: list = field(default_factory=list)
    cache_path: str = ""
    modifier: str = ""
    rank: int = 0
    frames: int = 0
    max_error_mm: float = 0.0
    tolerance_mm: float = 0.01
    note: str = ""

    @property
    def mode(self) -> str:
        """``"keys"``, ``"cache"`` or ``"none"``: what the scene holds (``StorageOutcome.mode``)."""
        return self.outcome.mode


class StoredKeys(list):
    """The names of the keys :func:`write_corrective_keys` wrote, with ``storage``: the :class:`CorrectionResult`."""

    storage: CorrectionResult

    @classmethod
    def of(cls, result: CorrectionResult) -> StoredKeys:
        """The key names of ``result`` (a :meth:`CorrectionWriter.finish`), with ``result`` as ``.storage``."""
        out = cls(result.keys)
        out.storage = result
        return out


class CorrectionWriter:
    """Stream a per-frame correction, then store it as keys or as a point cache (:meth:`finish`).

    Parameters
    ----------
    scene : bpy.types.Scene
    obj : bpy.types.Object
        The mesh that receives the correction.
    prefix : str
        Key prefix (one of :mod:`facelab_addon.names`); FaceLab's previous output with this prefix
        (keys, correction cache) is replaced by :meth:`finish`, nothing else.
    vertices : (n,) int array_like, optional
        Vertex ids the deltas cover (default: every vertex); other vertices get 0.
    settings : StorageSettings, optional
    measured_on : {"evaluated", "rest"}
        ``"evaluated"``: the deltas are wanted displacements of the evaluated mesh (after the
        modifiers) and are mapped to rest space per chunk (``blender.rest_space.to_rest_space``);
        ``"rest"``: they are shape-key offsets already.
    after_capture : bool
        The deltas are displacements of the captured mesh as the capture cache gives it (a dense
        correction over a Mesh Cache, which as keys would ride on the cache surface and not
        compress): :meth:`finish` writes them, never as keys, to a point cache of the ``vertices``
        only, added right after the capture by a Geometry Nodes modifier
        (``blender.bakes.add_correction_patch``). ``measured_on`` is then ignored.

    Raises
    ------
    MeshError
        The modifier stack changes the vertex count (``measured_on="evaluated"``).

    Examples
    --------
    >>> with CorrectionWriter(scene, obj, PROPAGATE_PREFIX, vertices=lips) as w:  # doctest: +SKIP
    ...     for frames, deltas in chunks:
    ...         w.add(frames, deltas)          # (c,), (c,n,3) object-local
    ...     result = w.finish()
    """

    def __init__(self, scene, obj, prefix: str, *, vertices=None, settings: StorageSettings | None = None,
                 measured_on: str = "evaluated", after_capture: bool = False):
        self.scene, self.obj, self.prefix = scene, obj, prefix
        self.settings = settings or stored(scene, STORE_SETTINGS_ATTR, StorageSettings)
        if int(self.settings.key_budget) < 1:
            raise FaceLabError(f"The key budget must be at least 1, got {self.settings.key_budget}.")
        if not self.settings.tolerance_mm > 0:
            raise FaceLabError(f"The storage tolerance must be a positive length in mm, got "
                               f"{self.settings.tolerance_mm}.")
        if str(self.settings.cache_format).upper() not in ("PC2", "MDD"):
            raise FaceLabError(f"Unknown cache format '{self.settings.cache_format}'; use 'PC2' or 'MDD'.")
        if measured_on not in ("evaluated", "rest"):
            raise FaceLabError(f"measured_on must be 'evaluated' or 'rest', not {measured_on!r}.")
        self.V = len(obj.data.vertices)
        self.vertices = None if vertices is None else np.asarray(vertices, dtype=np.int64)
        self.n = self.V if self.vertices is None else len(self.vertices)
        self.after_capture = bool(after_capture)
        self.map_to_rest = measured_on == "evaluated" and not self.after_capture \
            and bool(rest_space.deforming_modifiers(obj))
        if self.map_to_rest:
            rest_space.require_same_vertex_count(obj)
        # object-local units; on a face far smaller than life, a share of its size (blender.objects.tolerance_length)
        self.tol = tolerance_length(scene, obj, self.settings.tolerance_mm * 1e-3)
        self._to_mm = self.settings.tolerance_mm / local_length(scene, obj, self.settings.tolerance_mm * 1e-3)
        self._frames: list = []
        self._low = None
        self._dir = tempfile.mkdtemp(prefix="facelab-spool-")
        self._path = os.path.join(self._dir, "corrections.f32")
        self._f = open(self._path, "wb")
        self._closed = False

    # ------------------------------------------------------------------ input
    def add(self, frames, deltas) -> None:
        """Append a chunk: ``deltas`` (c,n,3) object-local scene units on scene ``frames`` (c,)."""
        if self._low is not None:
            raise FaceLabError("This writer holds a low-rank correction already; use one writer per correction.")
        f = np.atleast_1d(np.asarray(frames, dtype=np.float64))
        D = np.asarray(deltas)
        if D.shape != (len(f), self.n, 3):
            raise MeshError(f"A chunk of corrections must be ({len(f)},{self.n},3), got {D.shape}.")
        if not np.isfinite(D).all():
            bad = f[~np.isfinite(D).all(axis=(1, 2))][:5]
            raise MeshError(f"The corrections of frames {bad.tolist()} have NaN or infinite values; fix those frames.")
        if self.map_to_rest:
            D = rest_space.to_rest_space(self.obj, f, D, self.vertices)
        self._f.write(np.ascontiguousarray(D, dtype="<f4").tobytes())
        self._frames.extend(f.tolist())

    def add_low_rank(self, frames, basis, weights) -> None:
        """The whole correction as ``weights @ basis``: basis (r,n,3) scene units, weights (T,r).

        Kept as is (no spool) unless it must be mapped through deforming modifiers per frame.
        """
        f = np.atleast_1d(np.asarray(frames, dtype=np.float64))
        B = np.asarray(basis, dtype=np.float64)
        W = np.asarray(weights, dtype=np.float64)
        if B.ndim != 3 or B.shape[1:] != (self.n, 3) or W.shape != (len(f), len(B)):
            raise MeshError(f"A low-rank correction needs basis (r,{self.n},3) and weights ({len(f)},r); got "
                            f"{B.shape} and {W.shape}.")
        if self._frames or self._low is not None:
            raise FaceLabError("add_low_rank takes the whole correction; this writer already holds frames.")
        if self.map_to_rest:
            read = low_rank_reader(B, W)
            for i in range(0, len(f), 64):
                self.add(f[i:i + 64], read(i, min(len(f), i + 64)))
            return
        self._low = (B, W)
        self._frames = f.tolist()

    # ------------------------------------------------------------------ output
    def _reader(self):
        T = len(self._frames)
        if self._low is not None:
            return low_rank_reader(*self._low)
        self._f.flush()
        size = 3 * self.n  # read, not memory-mapped: mapped pages would count in the process' memory (RSS)

        def read(i, j):
            j = min(j, T)
            if j <= i:
                return np.zeros((0, self.n, 3), dtype="<f4")
            a = np.fromfile(self._path, dtype="<f4", count=(j - i) * size, offset=4 * i * size)
            return a.reshape(j - i, self.n, 3)

        return read

    def finish(self) -> CorrectionResult:
        """Replace FaceLab's previous output of this prefix with the correction; what was written.

        Raises
        ------
        OutputError
            The cache folder cannot be written (nothing in the scene changed then).
        """
        try:
            return self._finish()
        finally:
            self.close()

    def _finish(self) -> CorrectionResult:
        s, obj, prefix = self.settings, self.obj, self.prefix
        T = len(self._frames)
        frames = np.asarray(self._frames, dtype=np.float64)
        read = self._reader()
        budget = int(s.key_budget)
        if self.after_capture:
            path = bakes.correction_cache_path(obj, prefix, s.cache_format.upper(), s.cache_directory or None)
            return self._write_patch(path, read, frames)
        fit = compress_streamed(read, T, self.n, self.tol, budget, low_rank=self._low)
        tol_mm = float(s.tolerance_mm)
        if fit.fits:
            r = fit.basis.shape[0]
            self._remove_previous()
            if r == 0:
                return CorrectionResult(StorageOutcome.NONE, frames=T, max_error_mm=fit.max_error * self._to_mm,
                                        tolerance_mm=tol_mm, note=f"No correction above {tol_mm:g} mm; nothing stored.")
            names = self._write_keys(fit.basis, fit.weights, frames)
            return CorrectionResult(StorageOutcome.KEYS, keys=names, rank=r, frames=T,
                                    max_error_mm=fit.max_error * self._to_mm,
                                    tolerance_mm=tol_mm,
                                    note=f"{len(names)} corrective keys ({prefix}*), every vertex within "
                                         f"{tol_mm:g} mm.")
        try:
            path = bakes.correction_cache_path(obj, prefix, s.cache_format.upper(), s.cache_directory or None)
        except OutputError as e:  # no place for a cache (unsaved .blend): as many keys as it takes
            if T > 4000 or T * self.n > 50_000_000:  # past that, keys are no answer: the cache is needed
                raise OutputError(f"{e} (a correction of {T} frames of {self.n} vertices does not fit in "
                                  f"{budget} keys).") from None
            basis, weights = compress(read(0, T), tol=self.tol)  # block by block from the spool
            self._remove_previous()
            names = self._write_keys(basis, weights, frames)
            return CorrectionResult(StorageOutcome.KEYS_OVER_BUDGET, keys=names, rank=len(names), frames=T,
                                    max_error_mm=float("nan"),
                                    tolerance_mm=tol_mm,
                                    note=f"{len(names)} corrective keys, more than the budget of {budget}: {e}")
        return self._write_cache(path, read, frames, budget)

    def _remove_previous(self) -> None:
        review.show_corrected(self.obj)  # never the capture shown with FaceLab's newest correction alone
        remove_keys(self.obj, self.prefix)
        bakes.remove_correction_cache(self.obj, self.prefix)

    def _write_keys(self, basis, weights, frames) -> list:
        obj = self.obj
        if self.vertices is None:
            full = basis
        else:
            full = np.zeros((len(basis), self.V, 3))
            full[:, self.vertices] = basis
        names = add_keys_from_deltas(obj, self.prefix, full)
        key_values_bulk(obj, names, frames, weights)
        obj.data.update()
        return names

    def _layout(self, frames):
        fps = float(self.scene.render.fps) / float(self.scene.render.fps_base)
        return correction_layout(frames, self.settings.cache_format, fps)

    def _write_cache(self, path, read, frames, budget) -> CorrectionResult:
        obj, s = self.obj, self.settings
        layout = self._layout(frames)
        written = cache_write.write_correction_file(obj, self.prefix, path, layout, read, self.vertices, self.tol)
        self._remove_previous()  # the file is complete: now FaceLab's previous keys and cache go
        index = cache_write.capture_index(obj, self.prefix)[1] if written.index is None else written.index
        name = bakes.add_correction_cache(obj, self.prefix, path, layout.format, layout.span[0], layout.span[-1],
                                          integrate=written.integrate, index=index)
        obj.data.update()
        return CorrectionResult(StorageOutcome.CACHE, cache_path=str(path), modifier=name, rank=budget,
                                frames=len(frames), max_error_mm=0.0, tolerance_mm=float(s.tolerance_mm),
                                note=f"The correction does not fit in {budget} keys within {s.tolerance_mm:g} mm, so "
                                     f"it was written as a {layout.format} point cache '{path}' played by the Mesh "
                                     f"Cache modifier '{name}' ({written.mode}).")

    def _write_patch(self, path, read, frames) -> CorrectionResult:
        """The correction as a point cache of its own vertices, added after the capture (``after_capture``)."""
        obj, s = self.obj, self.settings
        layout = self._layout(frames)
        write_offset_cache(path, layout, read, np.zeros((self.n, 3), np.float32))
        self._remove_previous()
        name = bakes.add_correction_patch(obj, self.prefix, path, layout.format,
                                          np.arange(self.V) if self.vertices is None else self.vertices,
                                          layout.span[0], layout.span[-1],
                                          index=cache_write.capture_index(obj, self.prefix)[1])
        obj.data.update()
        return CorrectionResult(StorageOutcome.PATCH_CACHE, cache_path=str(path), modifier=name, rank=0,
                                frames=len(frames), max_error_mm=0.0, tolerance_mm=float(s.tolerance_mm),
                                note=f"The correction of {self.n} vertices changes with every frame of the capture "
                                     f"cache, so it was written as a {layout.format} point cache of those vertices "
                                     f"only '{path}', added after the capture by the Geometry Nodes modifier "
                                     f"'{name}'.")

    # ------------------------------------------------------------------ lifetime
    def close(self) -> None:
        """Drop the spool file (also after :meth:`finish`); the scene is left as it is."""
        if self._closed:
            return
        self._closed = True
        with contextlib.suppress(OSError):
            self._f.close()
        shutil.rmtree(self._dir, ignore_errors=True)

    abort = close

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        self.close()
        return False

    def __del__(self):  # a writer dropped without finish() leaves no spool behind
        with contextlib.suppress(Exception):
            self.close()


def write_corrective_keys(obj, prefix: str, deltas, frames, *, vertices=None, metres_per_unit: float | None = None,
                          scene=None, settings: StorageSettings | None = None,
                          measured_on: str = "rest") -> StoredKeys:
    """Store a whole (T,n,3) correction with :class:`CorrectionWriter`; the key names written.

    Parameters
    ----------
    obj : bpy.types.Object
        Mesh object that receives the correction (a Basis key is created if missing).
    prefix : str
        Key-name prefix (one of :mod:`facelab_addon.names`); FaceLab's previous output with this
        prefix is replaced, other keys are never touched.
    deltas : (T,n,3) array_like
        Per-frame displacement of the vertices ``vertices`` (all when None), object-local units.
    frames : (T,) int array_like
        Scene frame of each row of ``deltas``.
    vertices : (n,) int array_like, optional
    metres_per_unit : float, optional
        Ignored (the scene's unit scale and the object's scale are read); kept for older callers.
    scene : bpy.types.Scene, optional
        Default ``bpy.context.scene``.
    settings : StorageSettings, optional
    measured_on : {"rest", "evaluated"}
        See :class:`CorrectionWriter`.

    Returns
    -------
    StoredKeys
        The key names (empty when the correction went to a cache or is zero); ``.storage`` is the
        :class:`CorrectionResult` (cache path, note).
    """
    scene = scene if scene is not None else bpy.context.scene
    D = np.asarray(deltas)
    with CorrectionWriter(scene, obj, prefix, vertices=vertices, settings=settings, measured_on=measured_on) as w:
        for i in range(0, len(D), 256):
            w.add(np.asarray(frames)[i:i + 256], D[i:i + 256])
        return StoredKeys.of(w.finish())


def silence_correction(obj, prefix: str, frame: int) -> int:
    """Turn FaceLab's stored correction ``prefix`` off on ``frame`` alone, keys and point cache alike.

    Each of FaceLab's ``prefix*`` keys is keyed 0 on ``frame`` and the correction cache's factor 0 there
    (:func:`facelab_addon.blender.shapekeys.zero_on_frame`: every other frame keeps its value). Nothing is
    removed. Returns how many keyed values were changed.
    """
    done = 0
    key = obj.data.shape_keys
    for name in owned_keys(obj, prefix) if key is not None else ():
        done += zero_on_frame(key, f'key_blocks["{bpy.utils.escape_identifier(name)}"].value', frame)
    factor = correction_cache_factor(obj, prefix)
    if factor is not None:
        done += zero_on_frame(*factor, frame)
    return done
