"""Silhouettes (occluding contours) of a triangle mesh seen from a camera.

Used by the sketch-based lip refinement (Dinev et al. 2018 §5): silhouette
vertices are split into upper and lower lip by the image-space direction of
their normals, and by the contour metrics of the tests and benchmarks.
An edge is a silhouette edge when one adjacent triangle faces the camera and
the other faces away (perspective test against the camera centre).
"""

from __future__ import annotations

import numpy as np

from .mesh import edge_faces, face_normals, vertex_normals

__all__ = [
    "facing",
    "silhouette_edges",
    "silhouette_vertices",
    "projected_normals",
    "lip_side",
    "point_segment_distance",
    "contour_distance",
]


def facing(vertices, faces, camera) -> np.ndarray:
    """(F,) signed facing of each triangle: ``n · (c - centroid)``; > 0 faces the camera.

    Units: scene units cubed (area-weighted normal times distance); only the
    sign is meaningful.
    """
    V = np.asarray(vertices, dtype=np.float64)
    F = np.asarray(faces)
    n = face_normals(V, F, unit=False)
    cen = V[F].mean(axis=1)
    return np.einsum("ij,ij->i", n, camera.center[None] - cen)


def silhouette_edges(vertices, faces, camera, edges_and_faces=None, face_mask=None) -> np.ndarray:
    """(S,2) vertex pairs of the silhouette edges seen from ``camera``.

    Parameters
    ----------
    vertices : (V,3) float
    faces : (F,3) int
    camera : Camera
    edges_and_faces : tuple, optional
        Precomputed ``mesh.edge_faces(faces)`` (edges (E,2), ef (E,2)).
    face_mask : (F,) bool, optional
        Only edges whose two triangles are both in the mask count.
    """
    edges, ef = edge_faces(faces) if edges_and_faces is None else edges_and_faces
    s = facing(vertices, faces, camera) > 0
    inner = (ef >= 0).all(axis=1)
    e_ok = inner.copy()
    if face_mask is not None:
        fm = np.asarray(face_mask, bool)
        e_ok &= fm[np.maximum(ef[:, 0], 0)] & fm[np.maximum(ef[:, 1], 0)]
    f0, f1 = np.maximum(ef[:, 0], 0), np.maximum(ef[:, 1], 0)
    sil = e_ok & (s[f0] != s[f1])
    return edges[sil]


def silhouette_vertices(vertices, faces, camera, edges_and_faces=None, face_mask=None) -> np.ndarray:
    """(S,) sorted unique indices of vertices on silhouette edges."""
    return np.unique(silhouette_edges(vertices, faces, camera, edges_and_faces, face_mask))


def projected_normals(vertices, normals, camera, idx=None) -> np.ndarray:
    """(N,2) image-space directions of vertex normals (unit length, pixels, y down).

    The derivative of the projection at ``x`` applied to the normal ``n``.
    """
    X = np.asarray(vertices, dtype=np.float64)
    N = np.asarray(normals, dtype=np.float64)
    if idx is not None:
        X, N = X[idx], N[idx]
    xc = camera.to_camera(X)
    nc = N @ camera.R.T
    z = xc[:, 2:3]
    # d/dε of K (x + ε n) / z(x + ε n) at ε=0, dropping K's scale (direction only)
    d = (nc[:, :2] * z - xc[:, :2] * nc[:, 2:3]) / z**2
    d = d @ camera.K[:2, :2].T
    return d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)


def lip_side(vertices, faces, camera, idx, normals=None) -> np.ndarray:
    """(N,) +1 for upper-lip, -1 for lower-lip silhouette vertices ``idx``.

    With image y pointing down, the inner contour of the upper lip has normals
    pointing down the image (into the mouth opening), those of the lower lip up.
    """
    if normals is None:
        normals = vertex_normals(vertices, faces)
    d = projected_normals(vertices, normals, camera, idx)
    return np.where(d[:, 1] > 0, 1, -1)


def point_segment_distance(p, a, b) -> np.ndarray:
    """(N,M) distances from points ``p`` (N,2) to segments ``a``-``b`` (M,2)."""
    p = np.asarray(p, float)[:, None, :]
    a = np.asarray(a, float)[None]
    b = np.asarray(b, float)[None]
    ab = b - a
    t = np.einsum("nmd,nmd->nm", p - a, np.broadcast_to(ab, (p.shape[0],) + ab.shape[1:]))
    t = np.clip(t / np.maximum((ab**2).sum(-1), 1e-300), 0, 1)
    return np.linalg.norm(p - (a + t[..., None] * ab), axis=-1)


def contour_distance(vertices, faces, camera, sketch_px, side: int, candidates=None, edges_and_faces=None):
    """Distance (px) from each sketch sample to the mesh's matching lip silhouette.

    Parameters
    ----------
    vertices : (V,3) float
    faces : (F,3) int
    camera : Camera
    sketch_px : (N,2) float
        Sketch samples in pixels.
    side : {+1, -1}
        +1 upper lip, -1 lower lip.
    candidates : (V,) bool, optional
        Vertices allowed on the lip silhouette (both ends of an edge).

    Returns
    -------
    (N,) ndarray
        Pixels; ``inf`` where no silhouette edge of that lip exists.
    """
    V = np.asarray(vertices, dtype=np.float64)
    E = silhouette_edges(V, faces, camera, edges_and_faces)
    if candidates is not None:
        c = np.asarray(candidates, bool)
        E = E[c[E[:, 0]] & c[E[:, 1]]]
    if len(E) == 0:
        return np.full(len(sketch_px), np.inf)
    s = lip_side(V, faces, camera, E.ravel()).reshape(-1, 2)
    E = E[(s == side).all(axis=1)]
    if len(E) == 0:
        return np.full(len(sketch_px), np.inf)
    uv = camera.project(V[np.unique(E)])
    lut = np.zeros(len(V), np.int64)
    lut[np.unique(E)] = np.arange(len(uv))
    return point_segment_distance(sketch_px, uv[lut[E[:, 0]]], uv[lut[E[:, 1]]]).min(axis=1)
