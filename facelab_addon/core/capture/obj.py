"""Wavefront OBJ meshes: vertices, polygons, UVs and material parts, in file order.

A minimal reader for the OBJ files FaceLab exchanges (the ICT-FaceKit model,
meshes and corrected frames given to the command line): ``v`` positions,
``vt`` texture coordinates, ``f`` polygons (``v``, ``v/vt``, ``v/vt/vn`` and
``v//vn`` corners, 1-based or negative indices) and ``usemtl`` parts. Vertex
order and coordinates are kept exactly as in the file (no axis conversion, no
merging, no triangulation; :func:`facelab_addon.core.geometry.mesh.triangulate`
fan-triangulates the polygons). Normals, groups and other statements are
ignored.

Polygons use the flat layout of :mod:`.ict` and Blender: ``poly_verts`` holds
the 0-based vertex of every polygon corner and polygon ``p`` has the corners
``poly_verts[poly_offsets[p]:poly_offsets[p + 1]]``. Positions are in the
file's units. No bpy in this module.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

__all__ = ["ObjMesh", "read_obj", "read_obj_vertices"]


class ObjMesh(NamedTuple):
    """An OBJ mesh as read by :func:`read_obj` (a tuple, so it also unpacks in this field order).

    Attributes
    ----------
    vertices : (V,3) float64 ndarray
        ``v`` positions, file units, file order.
    uvs : (U,2) float64 ndarray
        ``vt`` texture coordinates.
    poly_verts : (C,) int64 ndarray
        0-based vertex of every polygon corner.
    poly_uv : (C,) int64 ndarray
        0-based UV of every polygon corner (-1 when the corner has none).
    poly_offsets : (P+1,) int64 ndarray
        Start of each polygon in ``poly_verts`` plus the total corner count.
    poly_part : (P,) int64 ndarray
        Index into ``parts`` of each polygon.
    parts : list of str
        ``usemtl`` material names in order of first use, plus ``"default"``
        when the file has no ``usemtl`` or polygons before the first one.
    """

    vertices: np.ndarray
    uvs: np.ndarray
    poly_verts: np.ndarray
    poly_uv: np.ndarray
    poly_offsets: np.ndarray
    poly_part: np.ndarray
    parts: list


def read_obj_vertices(path) -> np.ndarray:
    """Vertex positions of an OBJ file, without parsing its faces.

    Parameters
    ----------
    path : str or os.PathLike

    Returns
    -------
    (V,3) float64 ndarray
        ``v`` positions in file order, file units.

    Raises
    ------
    OSError
        When the file cannot be read.
    ValueError
        When a ``v`` line has fewer than three numbers or a non-number.
    """
    with open(path, "rb") as fh:
        lines = [ln for ln in fh.read().split(b"\n") if ln.startswith(b"v ")]
    return np.array([ln.split()[1:4] for ln in lines], dtype=np.float64)


def read_obj(path) -> ObjMesh:
    """Read the vertices, polygons, UVs and material parts of an OBJ file.

    Parameters
    ----------
    path : str or os.PathLike

    Returns
    -------
    ObjMesh
        ``(vertices, uvs, poly_verts, poly_uv, poly_offsets, poly_part, parts)``.

    Raises
    ------
    OSError
        When the file cannot be read.
    ValueError, IndexError
        When a ``v``/``vt``/``f``/``usemtl`` line is malformed.
    """
    verts, uvs, corners_v, corners_uv, offsets, part_of_poly, parts = [], [], [], [], [0], [], []
    current = -1
    with open(path, "rb") as fh:
        for ln in fh.read().split(b"\n"):
            if ln.startswith(b"v "):
                verts.append(ln.split()[1:4])
            elif ln.startswith(b"vt "):
                uvs.append(ln.split()[1:3])
            elif ln.startswith(b"f "):
                toks = ln.split()[1:]
                for t in toks:
                    s = t.split(b"/")
                    corners_v.append(int(s[0]))
                    corners_uv.append(int(s[1]) if len(s) > 1 and s[1] else 0)
                offsets.append(len(corners_v))
                part_of_poly.append(current)
            elif ln.startswith(b"usemtl"):
                name = ln.split()[1].decode()
                if name not in parts:
                    parts.append(name)
                current = parts.index(name)
    if current == -1 or min(part_of_poly) < 0:
        parts = parts + ["default"]
        part_of_poly = [p if p >= 0 else len(parts) - 1 for p in part_of_poly]
    V = np.array(verts, dtype=np.float64)
    cv = np.array(corners_v, dtype=np.int64)
    cv = np.where(cv < 0, len(V) + cv, cv - 1)
    cuv = np.array(corners_uv, dtype=np.int64)
    cuv = np.where(cuv < 0, len(uvs) + cuv, cuv - 1)
    return ObjMesh(
        V,
        np.array(uvs, dtype=np.float64).reshape(-1, 2),
        cv,
        cuv,
        np.array(offsets, dtype=np.int64),
        np.array(part_of_poly, dtype=np.int64),
        parts,
    )
