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

from ..errors import ObjFileError

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
    ObjFileError
        When a ``v`` line has fewer than three numbers, a non-number or a
        NaN/infinite coordinate (the message names the file and line).
    """
    with open(path, "rb") as fh:
        lines = [(n, ln) for n, ln in enumerate(fh.read().split(b"\n"), 1) if ln.startswith(b"v ")]
    verts = [_vertex(ln, n, path) for n, ln in lines]
    return np.array(verts, dtype=np.float64).reshape(-1, 3)


def _bad(path, n, what):
    return ObjFileError(f"OBJ file '{path}', line {n}: {what}. Re-export the OBJ (or fix that line).")


def _vertex(ln, n, path):
    """The three coordinates of a ``v`` line as floats (ObjFileError naming the line)."""
    tok = ln.split()[1:4]
    try:
        xyz = [float(t) for t in tok]
    except ValueError:
        raise _bad(path, n, f"the vertex {ln[:60]!r} has a coordinate that is not a number") from None
    if len(xyz) < 3:
        raise _bad(path, n, f"the vertex {ln[:60]!r} has {len(xyz)} coordinates instead of 3")
    if not all(np.isfinite(xyz)):
        raise _bad(path, n, "the vertex has a NaN or infinite coordinate")
    return xyz


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
    ObjFileError
        When a ``v``/``vt``/``f``/``usemtl`` line is malformed, a coordinate
        is NaN or infinite, or a face refers to a vertex or UV the file does
        not have (the message names the file and line).
    """
    verts, uvs, corners_v, corners_uv, offsets, part_of_poly, parts = [], [], [], [], [0], [], []
    current = -1
    with open(path, "rb") as fh:
        data = fh.read()
    for n, ln in enumerate(data.split(b"\n"), 1):
        if ln.startswith(b"v "):
            verts.append(_vertex(ln, n, path))
        elif ln.startswith(b"vt "):
            try:
                uv = [float(t) for t in ln.split()[1:3]]
            except ValueError:
                raise _bad(path, n, "a texture coordinate is not a number") from None
            if len(uv) < 2 or not all(np.isfinite(uv)):
                raise _bad(path, n, "a texture coordinate needs two finite numbers")
            uvs.append(uv)
        elif ln.startswith(b"f "):
            toks = ln.split()[1:]
            if len(toks) < 3:
                raise _bad(path, n, f"the face has {len(toks)} corners; a face needs at least 3")
            for t in toks:
                s = t.split(b"/")
                try:
                    iv = int(s[0])
                    iuv = int(s[1]) if len(s) > 1 and s[1] else 0
                except ValueError:
                    raise _bad(path, n, f"the face corner {t[:30]!r} is not a vertex index") from None
                if iv == 0:
                    raise _bad(path, n, "the face refers to vertex 0; OBJ vertex indices start at 1")
                corners_v.append(iv)
                corners_uv.append(iuv)
            offsets.append(len(corners_v))
            part_of_poly.append(current)
        elif ln.startswith(b"usemtl"):
            tok = ln.split()[1:2]
            name = tok[0].decode("utf-8", "replace") if tok else "default"
            if name not in parts:
                parts.append(name)
            current = parts.index(name)
    if current == -1 or min(part_of_poly, default=0) < 0:
        parts = parts + ["default"]
        part_of_poly = [p if p >= 0 else len(parts) - 1 for p in part_of_poly]
    V = np.array(verts, dtype=np.float64).reshape(-1, 3)
    cv = np.array(corners_v, dtype=np.int64)
    cv = np.where(cv < 0, len(V) + cv, cv - 1)
    cuv = np.array(corners_uv, dtype=np.int64)
    cuv = np.where(cuv < 0, len(uvs) + cuv, cuv - 1)
    if len(cv) and (cv.max() >= len(V) or cv.min() < 0):
        raise ObjFileError(f"OBJ file '{path}' has faces that refer to vertices it does not have (it has {len(V)}). "
                           "Re-export the OBJ.")
    if len(cuv) and (cuv.max() >= len(uvs) or cuv.min() < -1):
        raise ObjFileError(f"OBJ file '{path}' has faces that refer to texture coordinate {int(cuv.max()) + 1} but "
                           f"only {len(uvs)}. Re-export the OBJ with its UVs.")
    return ObjMesh(
        V,
        np.array(uvs, dtype=np.float64).reshape(-1, 2),
        cv,
        cuv,
        np.array(offsets, dtype=np.int64),
        np.array(part_of_poly, dtype=np.int64),
        parts,
    )
