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

import math
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


def _floats(path, lineno: int, line: bytes, n: int, what: str) -> list:
    """The first ``n`` numbers after the keyword of an OBJ line, checked finite."""
    toks = line.split()[1 : 1 + n]
    try:
        if len(toks) < n:
            raise ValueError
        vals = [float(t) for t in toks]
    except ValueError:
        raise ObjFileError(
            f"{path}, line {lineno}: a '{what}' line needs {n} numbers, got {_show(line)}. "
            "Fix or re-export the OBJ."
        ) from None
    if not all(math.isfinite(v) for v in vals):
        raise ObjFileError(
            f"{path}, line {lineno}: NaN or infinite coordinate in {_show(line)}. Fix the mesh in the "
            "program that exported it (or re-export the OBJ); FaceLab does not guess positions."
        )
    return vals


def _show(line: bytes) -> str:
    text = line.decode("utf-8", "replace").strip()
    return repr(text if len(text) <= 60 else text[:57] + "...")


def _lines(path):
    """``(line number, stripped line)`` of a file, 1-based."""
    try:
        with open(path, "rb") as fh:
            data = fh.read()
    except IsADirectoryError:
        raise ObjFileError(f"{path} is a folder, not an OBJ file; give the .obj file.") from None
    if b"\0" in data[:4096]:
        raise ObjFileError(f"{path} is a binary file, not a Wavefront OBJ (text); give an .obj exported as text.")
    return [(i + 1, ln.strip()) for i, ln in enumerate(data.split(b"\n"))]


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
        (a ``MeshError`` and a ``ValueError``) naming the file and line: a
        ``v`` line with fewer than three numbers, a non-number, NaN or
        infinity; a binary file.
    """
    V = [_floats(path, n, ln, 3, "v") for n, ln in _lines(path) if ln.startswith(b"v ")]
    return np.array(V, dtype=np.float64).reshape(-1, 3)


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
        (a ``MeshError`` and a ``ValueError``) naming the file and line: a
        malformed ``v``/``vt``/``f``/``usemtl`` line, a NaN or infinite
        coordinate, a face with fewer than 3 corners, a vertex or UV index
        out of range; a binary file.
    """
    verts, uvs, corners_v, corners_uv, offsets, part_of_poly, parts = [], [], [], [], [0], [], []
    face_lines = []
    current = -1
    for lineno, ln in _lines(path):
        if ln.startswith(b"v "):
            verts.append(_floats(path, lineno, ln, 3, "v"))
        elif ln.startswith(b"vt "):
            uvs.append(_floats(path, lineno, ln, 2, "vt"))
        elif ln.startswith(b"f "):
            toks = ln.split()[1:]
            if len(toks) < 3:
                raise ObjFileError(f"{path}, line {lineno}: a face needs at least 3 corners, got {_show(ln)}. "
                                   "Fix or re-export the OBJ.")
            for t in toks:
                s = t.split(b"/")
                try:
                    cv = int(s[0])
                    cuv = int(s[1]) if len(s) > 1 and s[1] else 0
                except ValueError:
                    raise ObjFileError(f"{path}, line {lineno}: face corner {t.decode('utf-8', 'replace')!r} is "
                                       "not 'v', 'v/vt', 'v/vt/vn' or 'v//vn' indices. Fix or re-export the OBJ."
                                       ) from None
                if cv == 0 or -cv > len(verts) or -cuv > len(uvs):
                    raise ObjFileError(f"{path}, line {lineno}: face corner {t.decode('utf-8', 'replace')!r} "
                                       f"names vertex {cv} / UV {cuv}, but {len(verts)} vertices and {len(uvs)} "
                                       "UVs come before it (indices start at 1). Fix or re-export the OBJ.")
                corners_v.append(cv if cv > 0 else len(verts) + cv + 1)
                corners_uv.append(cuv if cuv >= 0 else len(uvs) + cuv + 1)
            offsets.append(len(corners_v))
            part_of_poly.append(current)
            face_lines.append(lineno)
        elif ln.startswith(b"usemtl"):
            toks = ln.split()
            if len(toks) < 2:
                raise ObjFileError(f"{path}, line {lineno}: 'usemtl' without a material name. Fix the OBJ.")
            name = toks[1].decode("utf-8", "replace")
            if name not in parts:
                parts.append(name)
            current = parts.index(name)
    if current == -1 or (part_of_poly and min(part_of_poly) < 0):
        parts = parts + ["default"]
        part_of_poly = [p if p >= 0 else len(parts) - 1 for p in part_of_poly]
    V = np.array(verts, dtype=np.float64).reshape(-1, 3)
    cv = np.array(corners_v, dtype=np.int64) - 1
    cuv = np.array(corners_uv, dtype=np.int64) - 1
    bad = np.flatnonzero((cv >= len(V)) | (cuv >= len(uvs)))
    if len(bad):
        face = int(np.searchsorted(offsets, bad[0], side="right")) - 1
        raise ObjFileError(f"{path}, line {face_lines[face]}: a face names vertex {int(cv[bad[0]]) + 1} / UV "
                           f"{int(cuv[bad[0]]) + 1}, but the file has {len(V)} vertices and {len(uvs)} UVs. "
                           "Fix or re-export the OBJ.")
    return ObjMesh(
        V,
        np.array(uvs, dtype=np.float64).reshape(-1, 2),
        cv,
        cuv,
        np.array(offsets, dtype=np.int64),
        np.array(part_of_poly, dtype=np.int64),
        parts,
    )
