"""A face model with its vertices split along seams, as a glTF import or a game export gives it.

Blender's glTF importer (default: Merge Vertices off) and many engine formats keep one vertex per distinct
(position, UV, normal) of the polygon corners: every vertex on a UV seam (or a sharp edge) becomes two or
more coincident vertices and the surface falls into pieces. :func:`split_seams` makes such a face from a
face model (:class:`~facelab_addon.core.capture.ict.ICTModel`, split by its own UVs, or
:class:`~facelab_addon.testing.remeshed.RemeshedFace`, which has no UVs: split along the mirror plane, an
edge loop crossing the mouth, and any other given cuts); the result is a face model
:func:`~facelab_addon.testing.route.build_route_scene` accepts as it is (``neutral``, ``expressions``,
``faces``, ``poly_verts``, ``poly_offsets``, ``part_vertex_mask``), and ``source`` maps it back.

Vertex order: the split vertices are sorted by (source vertex, corner label), so the first copy of every
source vertex (the representative :func:`facelab_addon.core.geometry.weld.weld` picks) comes in the
source's order. Units are the source model's.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..core.geometry.mesh import triangulate

__all__ = ["SplitFace", "split_seams", "mirror_labels"]


@dataclass
class SplitFace:
    """A face model split along seams. Shapes: V split vertices, V0 source vertices, C corners, P polygons.

    Attributes
    ----------
    neutral : (V,3) float
    expressions : dict name -> (V,3) float
    poly_verts : (C,) int64
        The source's polygon corners, re-indexed to the split vertices.
    poly_offsets : (P+1,) int64
    faces : (F,3) int64
        Fan triangulation of the split polygons (the source's triangles, re-indexed).
    source : (V,) int64
        The source vertex of each split vertex.
    base : object
        The source model.
    """

    neutral: np.ndarray
    expressions: dict
    poly_verts: np.ndarray
    poly_offsets: np.ndarray
    faces: np.ndarray
    source: np.ndarray
    base: object = field(repr=False, default=None)

    @property
    def expression_names(self):
        return list(self.expressions)

    @property
    def n_duplicates(self) -> int:
        """Split vertices beyond the source's (the copies made along the seams)."""
        return len(self.source) - len(np.unique(self.source))

    def part_vertex_mask(self, *names):
        """(V,) bool: the source's mask (e.g. ``"M_Face"``) at every copy of its vertices."""
        return np.asarray(self.base.part_vertex_mask(*names))[self.source]

    def duplicates(self) -> np.ndarray:
        """(D,2) int64 pairs ``(first copy, other copy)`` of every vertex split in two or more."""
        first = np.r_[True, np.diff(self.source) != 0]
        head = np.maximum.accumulate(np.where(first, np.arange(len(self.source)), 0))
        dup = np.flatnonzero(~first)
        return np.c_[head[dup], dup]


def mirror_labels(face, axis: int = 0, cuts=()) -> np.ndarray:
    """(C,) int per polygon corner: which side of the mirror plane (and of each plane of ``cuts``) its polygon is on.

    The mirror plane is the median of the neutral's ``axis`` coordinate (the face's left-right axis in the
    model's frame, x for ICT); ``cuts`` are further planes ``(axis, value)`` in the model's units. A vertex
    whose polygons lie on both sides of a plane is split there: the polygons' boundary is an edge loop.
    """
    V = np.asarray(face.neutral, dtype=np.float64)
    pv, off = np.asarray(face.poly_verts), np.asarray(face.poly_offsets)
    sizes = np.diff(off)
    centre = np.add.reduceat(V[pv], off[:-1], axis=0) / sizes[:, None]
    planes = [(axis, float(np.median(V[:, axis])))] + [(int(a), float(v)) for a, v in cuts]
    label = np.zeros(len(sizes), np.int64)
    for k, (a, value) in enumerate(planes):
        label |= (centre[:, a] > value).astype(np.int64) << k
    return np.repeat(label, sizes)


def split_seams(face, labels=None) -> SplitFace:
    """``face`` with every vertex split into one copy per distinct label of its polygon corners.

    Parameters
    ----------
    face : ICTModel or RemeshedFace
        A face model (``neutral``, ``expressions``, ``poly_verts``, ``poly_offsets``, ``part_vertex_mask``).
    labels : (C,) int array_like, optional
        A label per polygon corner; corners of one vertex with different labels get different copies.
        Default: the model's UV index per corner (``poly_uv``: a UV-seam split, as a glTF import) when it has
        one, else :func:`mirror_labels` (the mirror plane).

    Returns
    -------
    SplitFace
    """
    pv = np.asarray(face.poly_verts, dtype=np.int64)
    off = np.asarray(face.poly_offsets, dtype=np.int64)
    if labels is None:
        labels = getattr(face, "poly_uv", None)
        if labels is None:
            labels = mirror_labels(face)
    labels = np.asarray(labels, dtype=np.int64)
    if labels.shape != pv.shape:
        raise ValueError(f"labels has shape {labels.shape}, the corners {pv.shape}")
    # copies of the unused vertices too, so every source vertex has one (the split keeps the source's order)
    rows = np.r_[np.c_[pv, labels], np.c_[np.arange(len(face.neutral)), np.full(len(face.neutral), labels.min())]]
    pairs, inv = np.unique(rows, axis=0, return_inverse=True)
    inv = inv.ravel()
    # a vertex used only by corners labelled above the minimum got an extra, unused copy: drop those
    used = np.zeros(len(pairs), bool)
    used[inv[: len(pv)]] = True
    first = np.r_[True, np.diff(pairs[:, 0]) != 0]
    keep = used | (first & ~np.isin(pairs[:, 0], pv))
    new = np.cumsum(keep) - 1
    source = pairs[keep, 0]
    cv = new[inv[: len(pv)]]
    tris, _ = triangulate(cv, off)
    return SplitFace(neutral=np.asarray(face.neutral)[source],
                     expressions={n: np.asarray(x)[source] for n, x in face.expressions.items()},
                     poly_verts=cv, poly_offsets=off, faces=np.asarray(tris, dtype=np.int64), source=source,
                     base=face)
