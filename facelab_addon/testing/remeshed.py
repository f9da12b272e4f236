"""A face that is not ICT's topology, with known ground truth: ICT-FaceKit decimated to quads, every expression
transferred by barycentric projection.

:func:`remeshed_ict` decimates the ICT head (skin with the attached mouth bag, teeth, gums and tongue,
eyeballs) with Blender's Decimate modifier (collapse, mirror-symmetric in x), joins the triangles into
quads, and projects every new vertex onto the ICT surface of its own part (the nearest triangle that
faces the same way, so an upper-lip vertex never lands on the lower lip 1 mm away). The new neutral and
every expression are the same barycentric combinations of ICT's vertices, so a pose of the new face is
exactly the ICT pose sampled at other points: the truth of any performance stays known.

The result quacks like :class:`facelab_addon.core.capture.ict.ICTModel` where the scene builders and
the benchmarks read it (``neutral``, ``faces``, ``poly_verts``, ``poly_offsets``, ``expressions``,
``expression_names``, ``parts``, ``part_vertex_mask``, ``pose``, ``scale``), so
:func:`facelab_addon.testing.scenes.build_ict_face_scene` builds a scene from it unchanged. Units are
the ICT model's (centimetres times ``ict.scale``). ``source`` is the model it samples (the benchmark's truth
lip line is carried from it: :func:`facelab_addon.testing.lip_truth.transferred_truth_line`). Building takes a few seconds; the arrays are cached
under ``FACELAB_CACHE_DIR`` (default ``~/.cache/facelab``). Needs ``bpy``.
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = ["RemeshedFace", "remeshed_ict", "SOURCE_PARTS"]

#: The ICT parts kept (the lashes, tear films and occlusion shells are left out).
SOURCE_PARTS = ("M_Face", "M_BackHead", "M_GumsTongue", "M_Teeth", "M_ScleraLeft", "M_ScleraRight",
                "M_IrisLeft", "M_IrisRight")


@dataclass
class RemeshedFace:
    """The decimated ICT face (see the module docstring). Shapes: V vertices, P polygons, F triangles."""

    neutral: np.ndarray  # (V,3)
    poly_verts: np.ndarray  # (C,) polygon corners
    poly_offsets: np.ndarray  # (P+1,)
    poly_part: np.ndarray  # (P,) index into parts
    parts: list
    expressions: dict  # name -> (V,3)
    source_triangle: np.ndarray  # (V,) index into the ICT triangles
    barycentric: np.ndarray  # (V,3)
    source_vertices: np.ndarray  # (V,3) ICT vertex ids of those triangles
    scale: float = 1.0
    faces: np.ndarray = field(default=None)  # (F,3) fan triangulation of the polygons
    source: object = field(default=None, repr=False, compare=False)  # the model it samples (ICTModel), if known

    def __post_init__(self):
        if self.faces is None:
            tris = []
            for p in range(len(self.poly_offsets) - 1):
                c = self.poly_verts[self.poly_offsets[p]:self.poly_offsets[p + 1]]
                tris += [[c[0], c[i], c[i + 1]] for i in range(1, len(c) - 1)]
            self.faces = np.asarray(tris, dtype=np.int64)

    @property
    def expression_names(self):
        return list(self.expressions)

    def transfer(self, X):
        """ICT positions (..., V_ict, 3) sampled at this face's vertices: (..., V, 3)."""
        X = np.asarray(X, dtype=np.float64)
        return np.einsum("...vkc,vk->...vc", X[..., self.source_vertices, :], self.barycentric)

    def pose(self, weights: dict | None = None):
        """Neutral plus weighted expression offsets, (V,3)."""
        out = self.neutral.copy()
        for n, w in (weights or {}).items():
            out += w * (self.expressions[n] - self.neutral)
        return out

    def part_vertex_mask(self, *names):
        """(V,) bool: vertices of polygons of the given parts."""
        ids = [self.parts.index(n) for n in names if n in self.parts]
        sizes = np.diff(self.poly_offsets)
        sel = np.repeat(np.isin(self.poly_part, ids), sizes)
        m = np.zeros(len(self.neutral), bool)
        m[self.poly_verts[sel]] = True
        return m

    @property
    def n_quads(self) -> int:
        return int((np.diff(self.poly_offsets) == 4).sum())


def _decimate(V, poly_verts, poly_offsets, material, ratio):
    """Blender's Decimate (collapse, symmetric in x) and Tris to Quads: ``(V, poly_verts, poly_offsets, material)``."""
    import bpy  # noqa: I001  (bmesh is importable once bpy is)
    import bmesh

    from ..blender.scene import new_mesh_object

    obj = new_mesh_object("FL_remesh_src", V, poly_verts=poly_verts, poly_offsets=poly_offsets)
    for i in range(int(material.max()) + 1):
        obj.data.materials.append(bpy.data.materials.new(f"FL_part_{i}"))
    obj.data.polygons.foreach_set("material_index", material.astype(np.int32))
    mod = obj.modifiers.new("Decimate", "DECIMATE")
    mod.decimate_type, mod.ratio = "COLLAPSE", float(ratio)
    mod.use_symmetry, mod.symmetry_axis = True, "X"
    bpy.context.view_layer.update()
    dg = bpy.context.evaluated_depsgraph_get()
    bm = bmesh.new()
    bm.from_object(obj, dg)
    bmesh.ops.join_triangles(bm, faces=bm.faces[:], angle_face_threshold=np.radians(40.0),
                             angle_shape_threshold=np.radians(40.0))
    bm.verts.index_update()
    Vn = np.array([v.co[:] for v in bm.verts], dtype=np.float64)
    pv, off, mat = [], [0], []
    for f in bm.faces:
        pv += [v.index for v in f.verts]
        off.append(len(pv))
        mat.append(f.material_index)
    bm.free()
    me = obj.data
    bpy.data.objects.remove(obj)
    bpy.data.meshes.remove(me)
    return Vn, np.asarray(pv, np.int64), np.asarray(off, np.int64), np.asarray(mat, np.int64)


def _project(P, N, V, F, k=24):
    """Nearest point of triangles ``F`` (over ``V``) to each point ``P`` among triangles facing like ``N``.

    Returns ``(triangle (n,), barycentric (n,3))``: the candidate among the ``k`` triangles with the nearest
    centroids whose normal agrees with ``N`` (cosine > 0.2), clamped to the triangle.
    """
    from scipy.spatial import cKDTree

    A, B, C = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    fn = np.cross(B - A, C - A)
    fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-300)
    _, cand = cKDTree((A + B + C) / 3).query(P, k=min(k, len(F)))
    cand = cand.reshape(len(P), -1)
    best = np.full(len(P), np.inf)
    tri = np.zeros(len(P), np.int64)
    bary = np.zeros((len(P), 3))
    for j in range(cand.shape[1]):
        t = cand[:, j]
        a, b, c = A[t], B[t], C[t]
        v0, v1, v2 = b - a, c - a, P - a
        d00, d01, d11 = (v0 * v0).sum(1), (v0 * v1).sum(1), (v1 * v1).sum(1)
        d20, d21 = (v2 * v0).sum(1), (v2 * v1).sum(1)
        den = np.where(np.abs(d00 * d11 - d01 * d01) > 0, d00 * d11 - d01 * d01, 1.0)
        w1 = (d11 * d20 - d01 * d21) / den
        w2 = (d00 * d21 - d01 * d20) / den
        w = np.clip(np.c_[1 - w1 - w2, w1, w2], 0, None)
        w /= np.maximum(w.sum(1, keepdims=True), 1e-300)
        q = w[:, :1] * a + w[:, 1:2] * b + w[:, 2:] * c
        d = np.linalg.norm(P - q, axis=1)
        d = np.where((fn[t] * N).sum(1) > 0.2, d, np.inf)
        better = d < best
        best[better], tri[better], bary[better] = d[better], t[better], w[better]
    if not np.isfinite(best).all():  # no facing triangle nearby: plain nearest
        bad = ~np.isfinite(best)
        t2, w2 = _project(P[bad], np.zeros_like(P[bad]) + fn[cand[bad, 0]], V, F, k)
        tri[bad], bary[bad] = t2, w2
    return tri, bary


def remeshed_ict(ict, ratio: float = 0.45, *, use_cache: bool = True) -> RemeshedFace:
    """The ICT head decimated to a quad-dominant mesh of about ``ratio`` of its triangles, with every expression.

    Parameters
    ----------
    ict : ICTModel
        The source model (its units; its expressions are all transferred).
    ratio : float
        Decimate's collapse ratio.
    use_cache : bool
        Read / write the arrays under ``FACELAB_CACHE_DIR`` (default ``~/.cache/facelab``).

    Returns
    -------
    RemeshedFace
    """
    from ..core.geometry.mesh import vertex_normals

    names = list(ict.expression_names)
    key = hashlib.sha1(np.ascontiguousarray(ict.neutral[:200]).tobytes() + f"{ratio}{len(names)}v2".encode())
    cache = Path(os.environ.get("FACELAB_CACHE_DIR", Path.home() / ".cache" / "facelab")) / \
        f"remeshed_ict_{key.hexdigest()[:12]}.npz"
    parts = [p for p in SOURCE_PARTS if p in ict.parts]
    if use_cache and cache.exists():
        d = np.load(cache)
        return RemeshedFace(neutral=d["neutral"], poly_verts=d["poly_verts"], poly_offsets=d["poly_offsets"],
                            poly_part=d["poly_part"], parts=parts,
                            expressions={n: d["expressions"][i] for i, n in enumerate(names)},
                            source_triangle=d["source_triangle"], barycentric=d["barycentric"],
                            source_vertices=d["source_vertices"], scale=float(ict.scale), source=ict)
    # the kept ICT polygons, with their part as the material
    sizes = np.diff(ict.poly_offsets)
    ppart = np.asarray(ict.poly_part)
    keep_poly = np.isin(ppart, [ict.parts.index(p) for p in parts])
    corner_keep = np.repeat(keep_poly, sizes)
    pv = np.asarray(ict.poly_verts)[corner_keep]
    off = np.r_[0, np.cumsum(sizes[keep_poly])]
    mat = np.array([parts.index(ict.parts[i]) for i in ppart[keep_poly]])
    Vn, pvn, offn, matn = _decimate(ict.neutral, pv, off, mat, ratio)
    used = np.unique(pvn)
    remap = -np.ones(len(Vn), np.int64)
    remap[used] = np.arange(len(used))
    Vn, pvn = Vn[used], remap[pvn]
    # each new vertex's part (skin and mouth bag together: they are one surface)
    group = lambda p: 0 if parts[p] in ("M_Face", "M_BackHead") else p  # noqa: E731
    vpart = np.zeros(len(Vn), np.int64)
    vpart[pvn] = np.repeat([group(m) for m in matn], np.diff(offn))
    tmp = RemeshedFace(neutral=Vn, poly_verts=pvn, poly_offsets=offn, poly_part=matn, parts=parts, expressions={},
                       source_triangle=np.zeros(0), barycentric=np.zeros(0), source_vertices=np.zeros(0))
    Nn = vertex_normals(Vn, tmp.faces)
    tri_part = np.array([group(parts.index(ict.parts[ppart[p]])) if keep_poly[p] else -1
                         for p in _triangle_polygons(ict)])
    src_tri = np.zeros(len(Vn), np.int64)
    bary = np.zeros((len(Vn), 3))
    for g in np.unique(vpart):
        sel = vpart == g
        tsel = np.flatnonzero(tri_part == g)
        t, w = _project(Vn[sel], Nn[sel], ict.neutral, ict.faces[tsel])
        src_tri[sel], bary[sel] = tsel[t], w
    src_v = ict.faces[src_tri]
    out = RemeshedFace(neutral=np.zeros_like(Vn), poly_verts=pvn, poly_offsets=offn, poly_part=matn, parts=parts,
                       expressions={}, source_triangle=src_tri, barycentric=bary, source_vertices=src_v,
                       scale=float(ict.scale), faces=tmp.faces, source=ict)
    out.neutral = out.transfer(ict.neutral)
    out.expressions = {n: out.transfer(ict.expressions[n]) for n in names}
    if use_cache:
        cache.parent.mkdir(parents=True, exist_ok=True)
        np.savez(cache, neutral=out.neutral, poly_verts=pvn, poly_offsets=offn, poly_part=matn,
                 expressions=np.stack([out.expressions[n] for n in names]), source_triangle=src_tri,
                 barycentric=bary, source_vertices=src_v)
    return out


def _triangle_polygons(ict):
    """(F,) the ICT polygon each of ``ict.faces`` comes from (fan triangulation order of the loader)."""
    sizes = np.diff(ict.poly_offsets)
    return np.repeat(np.arange(len(sizes)), sizes - 2)
