"""Loader for the ICT-FaceKit face model in its upstream OBJ layout.

ICT-FaceKit (MIT, USC Institute for Creative Technologies) is our test, demo
and benchmark face: ``FaceXModel/generic_neutral_mesh.obj`` (26,719 vertices,
centimetres, Y up), one full-mesh OBJ per expression and per identity target,
all in the same vertex order, and ``vertex_indices.json``.

The data is never copied into the repository. It is found through, in order:
the ``root`` argument, the ``FACELAB_ICT_DIR`` environment variable, then
``../shared/ict-facekit`` next to the repository. Parsed arrays are cached
(``.npz``) in ``FACELAB_CACHE_DIR``, else ``$XDG_CACHE_HOME/facelab``, else
``~/.cache/facelab``.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import DataMissingError
from ..geometry.mesh import triangulate
from .obj import read_obj, read_obj_vertices

__all__ = ["ICTModel", "find_ict_dir", "load_ict", "CLONE_HINT"]

CLONE_HINT = (
    "Clone it with `git clone https://github.com/ICT-VGL/ICT-FaceKit` and set "
    "FACELAB_ICT_DIR to the clone (the folder that contains FaceXModel/)."
)
_NEUTRAL = "generic_neutral_mesh.obj"
_CACHE_VERSION = 2


@dataclass
class ICTModel:
    """The ICT-FaceKit face, parsed.

    Attributes
    ----------
    neutral : (V,3) float64
        Neutral vertices, centimetres times ``scale``.
    faces : (F,3) int64
        Triangles (fan-triangulated polygons, upstream vertex order).
    tri_poly : (F,) int64
        Source polygon of each triangle.
    poly_verts, poly_offsets : (C,), (P+1,) int64
        The upstream polygons (mostly quads), for building a Blender mesh.
    poly_part : (P,) int64
        Index into ``parts`` (the OBJ ``usemtl`` material) of each polygon.
    parts : list of str
        Part names, such as ``M_Face``, ``M_Teeth``, ``M_GumsTongue``.
    uvs : (U,2) float64 and poly_uv : (C,) int64
        Texture coordinates and the UV index of each polygon corner.
    expressions : dict str -> (V,3) float64
        Expression targets as full meshes (delta = target - neutral).
    identities : dict str -> (V,3) float64
        Identity targets as full meshes.
    landmarks : (68,) int64
        Landmark vertex indices from ``vertex_indices.json``.
    scale : float
        Multiplier applied to the upstream centimetres.
    """

    neutral: np.ndarray
    faces: np.ndarray
    tri_poly: np.ndarray
    poly_verts: np.ndarray
    poly_offsets: np.ndarray
    poly_part: np.ndarray
    parts: list
    uvs: np.ndarray
    poly_uv: np.ndarray
    expressions: dict = field(default_factory=dict)
    identities: dict = field(default_factory=dict)
    landmarks: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    scale: float = 1.0

    @property
    def expression_names(self):
        return list(self.expressions)

    def deltas(self, names=None):
        """(S,V,3) expression deltas (target - neutral) for ``names`` (default: all)."""
        names = list(self.expressions) if names is None else list(names)
        return np.stack([self.expressions[n] - self.neutral for n in names])

    def pose(self, weights: dict | None = None, identity: dict | None = None):
        """(V,3) vertices of ``neutral + sum_i w_i (target_i - neutral)``.

        Parameters
        ----------
        weights : dict name -> float
            Expression weights (ARKit-style names such as ``"jawOpen"``).
        identity : dict name -> float
            Identity weights (``"identity000"``...).
        """
        X = self.neutral.copy()
        for src, w in ((self.expressions, weights or {}), (self.identities, identity or {})):
            for name, value in w.items():
                if name not in src:
                    raise KeyError(f"unknown ICT target {name!r}")
                X += float(value) * (src[name] - self.neutral)
        return X

    def part_vertex_mask(self, *names):
        """(V,) bool: vertices used by polygons of the given parts (e.g. ``"M_Teeth"``)."""
        ids = [self.parts.index(n) for n in names if n in self.parts]
        sel = np.isin(self.poly_part, ids)
        corner_sel = np.repeat(sel, np.diff(self.poly_offsets))
        m = np.zeros(len(self.neutral), dtype=bool)
        m[self.poly_verts[corner_sel]] = True
        return m

    def part_face_mask(self, *names):
        """(F,) bool: triangles of the given parts."""
        ids = [self.parts.index(n) for n in names if n in self.parts]
        return np.isin(self.poly_part[self.tri_poly], ids)


def find_ict_dir(root=None) -> Path:
    """Locate the ICT-FaceKit folder (the one holding ``FaceXModel/``).

    Raises
    ------
    DataMissingError
        When no candidate holds ``FaceXModel/generic_neutral_mesh.obj``; the
        message says how to get the data.
    """
    here = Path(__file__).resolve()
    # An explicit root, else FACELAB_ICT_DIR, is the only place looked at: a wrong
    # setting is reported instead of silently falling back to another copy.
    if root is not None:
        cands = [Path(root)]
    elif os.environ.get("FACELAB_ICT_DIR"):
        cands = [Path(os.environ["FACELAB_ICT_DIR"])]
    else:  # ../shared/ict-facekit next to the repository (repo = parents[3] of this file)
        cands = [here.parents[4] / "shared" / "ict-facekit", Path.cwd().parent / "shared" / "ict-facekit"]
    for c in cands:
        for d in (c, c.parent):
            if (d / "FaceXModel" / _NEUTRAL).is_file():
                return d
        if c.name == "FaceXModel" and (c / _NEUTRAL).is_file():
            return c.parent
    tried = ", ".join(str(c) for c in cands)
    raise DataMissingError(f"ICT-FaceKit data not found (looked in: {tried}). {CLONE_HINT}")


def _cache_dir() -> Path:
    if os.environ.get("FACELAB_CACHE_DIR"):
        return Path(os.environ["FACELAB_CACHE_DIR"])
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "facelab"


def _parse(root: Path) -> dict:
    fx = root / "FaceXModel"
    meta = json.loads((fx / "vertex_indices.json").read_text()) if (fx / "vertex_indices.json").exists() else {}
    V, uvs, cv, cuv, off, ppart, parts = read_obj(fx / _NEUTRAL)
    on_disk = sorted(p.stem for p in fx.glob("*.obj") if p.name != _NEUTRAL and not p.stem.startswith("identity"))
    listed = [n for n in meta.get("expressions", []) if n in on_disk]
    expr_names = listed + [n for n in on_disk if n not in listed]
    id_names = sorted(p.stem for p in fx.glob("identity*.obj"))
    out = dict(
        neutral=V, uvs=uvs, poly_verts=cv, poly_uv=cuv, poly_offsets=off, poly_part=ppart,
        parts=np.array(parts), landmarks=np.asarray(meta.get("idx_to_landmark_verts", []), dtype=np.int64),
        expr_names=np.array(expr_names), id_names=np.array(id_names),
    )
    for prefix, names in (("e_", expr_names), ("i_", id_names)):
        for n in names:
            X = read_obj_vertices(fx / f"{n}.obj")
            if X.shape != V.shape:
                raise DataMissingError(
                    f"ICT target {n}.obj has {len(X)} vertices, the neutral has {len(V)}; "
                    f"the ICT-FaceKit copy is damaged. {CLONE_HINT}"
                )
            out[prefix + n] = X
    return out


def load_ict(root=None, *, scale: float = 1.0, expressions=None, use_cache: bool = True) -> ICTModel:
    """Load the ICT-FaceKit model.

    Parameters
    ----------
    root : path-like, optional
        The ICT-FaceKit folder; default: ``FACELAB_ICT_DIR`` or ``../shared/ict-facekit``.
    scale : float
        Multiplier for the upstream centimetres (``0.01`` gives metres,
        ``10`` millimetres).
    expressions : list of str, optional
        Keep only these expressions (default: all 57).
    use_cache : bool
        Read the parsed arrays from the ``.npz`` cache when it is there, else parse the OBJ files and
        write it.

    Returns
    -------
    ICTModel
    """
    root = find_ict_dir(root)
    fx = root / "FaceXModel"
    stamp = hashlib.sha1()
    for p in sorted(fx.glob("*")):
        st = p.stat()
        stamp.update(f"{p.name}:{st.st_size}:{int(st.st_mtime)}".encode())
    key = f"ict-v{_CACHE_VERSION}-{stamp.hexdigest()[:16]}.npz"
    cache = _cache_dir() / key
    data = None
    if use_cache and cache.is_file():
        try:
            with np.load(cache, allow_pickle=False) as z:
                data = {k: z[k] for k in z.files}
        except Exception:  # corrupt cache: re-parse
            data = None
    if data is None:
        data = _parse(root)
        if use_cache:
            try:
                cache.parent.mkdir(parents=True, exist_ok=True)
                tmp = cache.with_suffix(".tmp.npz")
                np.savez(tmp, **data)
                os.replace(tmp, cache)
            except OSError:
                pass
    s = float(scale)
    tris, tri_poly = triangulate(data["poly_verts"], data["poly_offsets"])
    names = [str(n) for n in data["expr_names"]]
    if expressions is not None:
        missing = [n for n in expressions if n not in names]
        if missing:
            raise KeyError(f"unknown ICT expressions {missing}; available: {names}")
        names = list(expressions)
    return ICTModel(
        neutral=data["neutral"] * s,
        faces=tris,
        tri_poly=tri_poly,
        poly_verts=data["poly_verts"],
        poly_offsets=data["poly_offsets"],
        poly_part=data["poly_part"],
        parts=[str(p) for p in data["parts"]],
        uvs=data["uvs"],
        poly_uv=data["poly_uv"],
        expressions={n: data["e_" + n] * s for n in names},
        identities={str(n): data["i_" + str(n)] * s for n in data["id_names"]},
        landmarks=data["landmarks"],
        scale=s,
    )
