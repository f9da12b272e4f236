"""The ``'INTEGRATE'`` deform mode of Blender's Mesh Cache modifier: shape keys on top of a cache.

In ``deform_mode='INTEGRATE'`` Blender (``BKE_mesh_calc_relative_deform``)
carries a shape key's offset in the local frame of every face corner of the
cache surface instead of adding it, so a correction wanted on top of a cache
frame must be stored as a transformed key offset. ``integrate_matrices`` gives
the per-vertex linear map of that mode for one frame and
``integrate_offsets_to_key`` inverts it.

Positions and offsets are object-local, scene units; the maps are
dimensionless (V,3,3). No bpy in this module.
"""

from __future__ import annotations

import numpy as np

from ..geometry.inv3 import inv3

__all__ = ["corner_neighbours", "integrate_matrices", "integrate_offsets_to_key"]


def corner_neighbours(face_offsets, corner_verts):
    """``(prev, next)`` (C,) int64: the vertex of the corner before and after each polygon corner.

    Parameters
    ----------
    face_offsets : (P+1,) array_like of int
        Start of each polygon in ``corner_verts`` (plus the total corner count).
    corner_verts : (C,) array_like of int
        Vertex of every polygon corner.
    """
    off = np.asarray(face_offsets, dtype=np.int64)
    cv = np.asarray(corner_verts, dtype=np.int64)
    sizes = np.diff(off)
    face_of = np.repeat(np.arange(len(sizes)), sizes)
    local = np.arange(len(cv)) - off[face_of]
    n = sizes[face_of]
    return cv[off[face_of] + (local - 1) % n], cv[off[face_of] + (local + 1) % n]


def integrate_matrices(rest, deformed, face_offsets, corner_verts) -> np.ndarray:
    """Per-vertex 3x3 maps of the Mesh Cache modifier's ``'INTEGRATE'`` mode.

    In ``deform_mode='INTEGRATE'`` Blender (``BKE_mesh_calc_relative_deform``)
    does not add a shape key's offset ``d`` to the cache position; it carries
    it in the local frame of every face corner (``barycentric_transform``) and
    averages over the corners of the vertex, so the evaluated position is
    ``deformed[v] + M[v] @ d[v]``: exact addition where the cache is a
    translation of the rest mesh, ``R @ d`` where it is rotated by ``R``,
    ``s * d`` where scaled by ``s``. A correction ``delta`` wanted *on top of*
    cache frame ``t`` must therefore be stored as the key offset
    ``solve(M[v], delta[v])`` (``integrate_offsets_to_key``).

    Parameters
    ----------
    rest : (V,3) array_like
        The mesh's own vertex positions (``mesh.vertices.co``, the Basis),
        object-local scene units.
    deformed : (V,3) array_like
        The cache positions on the frame, after the modifier's axis matrix
        (what the modifier shows with the keys muted).
    face_offsets : (P+1,) array_like of int
        Start of each polygon in ``corner_verts`` (``polygons.loop_start``
        plus the total corner count).
    corner_verts : (C,) array_like of int
        Vertex of every polygon corner (``loops.vertex_index``).

    Returns
    -------
    (V,3,3) float64 ndarray
        Linear maps (dimensionless); all zeros for vertices on no face (Blender
        drops the offset of loose vertices).
    """
    S = np.asarray(rest, dtype=np.float64)
    O = np.asarray(deformed, dtype=np.float64)
    cur = np.asarray(corner_verts, dtype=np.int64)
    prev, nxt = corner_neighbours(face_offsets, cur)

    def frame(P, scale_normal_by=None):
        e1 = P[prev] - P[cur]
        e2 = P[nxt] - P[cur]
        nrm = np.cross(P[cur] - P[prev], P[nxt] - P[cur])  # normal_tri_v3(prev, cur, next)
        area2 = np.linalg.norm(nrm, axis=1)
        nrm = nrm / np.where(area2 > 0, area2, 1.0)[:, None]
        return e1, e2, nrm, 0.5 * area2

    e1s, e2s, ns, As = frame(S)
    e1o, e2o, no, Ao = frame(O)
    k = np.sqrt(Ao / np.where(As > 0, As, 1.0))
    Bs = np.stack([e1s, e2s, ns], axis=2)  # (C,3,3) columns
    Bo = np.stack([e1o, e2o, no * k[:, None]], axis=2)
    ok = As > 0
    L = np.zeros((len(cur), 3, 3))
    if ok.any():
        L[ok] = Bo[ok] @ inv3(Bs[ok])  # closed form: no LAPACK call per corner
    Vn = len(S)
    M = np.zeros((Vn, 3, 3))
    np.add.at(M, cur, L)
    cnt = np.bincount(cur, minlength=Vn).astype(np.float64)
    M /= np.where(cnt > 0, cnt, 1.0)[:, None, None]
    return M


def integrate_offsets_to_key(matrices, deltas) -> np.ndarray:
    """Shape-key offsets that show as ``deltas`` on top of an ``'INTEGRATE'`` Mesh Cache.

    Parameters
    ----------
    matrices : (V,3,3) array_like
        From ``integrate_matrices`` for the frame the correction is made on.
    deltas : (V,3) array_like
        Wanted displacement of the evaluated mesh on that frame,
        object-local scene units.

    Returns
    -------
    (V,3) float64 ndarray
        Offsets to store in the shape key (key = Basis + offsets), scene
        units. Vertices whose map is singular (loose vertices) get the least
        squares solution (zero for a zero map).
    """
    M = np.asarray(matrices, dtype=np.float64)
    d = np.asarray(deltas, dtype=np.float64)
    out = np.zeros_like(d)
    det = np.linalg.det(M)
    good = np.abs(det) > 1e-12
    if good.any():
        out[good] = np.linalg.solve(M[good], d[good][..., None])[..., 0]
    for v in np.flatnonzero(~good):
        out[v] = np.linalg.lstsq(M[v], d[v], rcond=None)[0]
    return out
