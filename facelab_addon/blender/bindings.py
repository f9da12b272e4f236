"""Track and bundle bindings stored on the face object (``Object.facelab_solve.bindings``) <-> arrays.

A binding ties a named 2D track or 3D bundle to a point of the face surface:
``x = sum_k bary_k * V[vertices_k]`` (one triangle's vertex ids and
barycentric weights). Bind Tracks writes them; the solve and Retarget read
them back by kind (``"MARKER"`` or ``"BUNDLE"``).
"""

from __future__ import annotations

import numpy as np

__all__ = ["write_bindings", "read_bindings"]


def write_bindings(obj, kind: str, names, vertices, bary) -> None:
    """Replace the ``kind`` bindings of ``obj`` (bulk write).

    Parameters
    ----------
    obj : bpy.types.Object
        The face; its bindings of the other kind are kept.
    kind : {"MARKER", "BUNDLE"}
    names : sequence of str
        Track or bundle names, one per binding.
    vertices : (m,3) int array_like
        Triangle vertex ids of each binding's surface point.
    bary : (m,3) float array_like
        Barycentric weights in that triangle (stored as float32).
    """
    coll = obj.facelab_solve.bindings
    keep = [(b.name, b.kind, tuple(b.vertices), tuple(b.bary)) for b in coll if b.kind != kind]
    coll.clear()
    rows = keep + [(n, kind, tuple(int(x) for x in v), tuple(float(x) for x in w))
                   for n, v, w in zip(names, np.asarray(vertices), np.asarray(bary))]
    for _ in rows:
        coll.add()
    coll.foreach_set("vertices", np.array([r[2] for r in rows], np.int32).ravel() if rows else np.zeros(0, np.int32))
    coll.foreach_set("bary", np.array([r[3] for r in rows], np.float32).ravel() if rows else np.zeros(0, np.float32))
    for item, r in zip(coll, rows):
        item.name, item.kind = r[0], r[1]


def read_bindings(obj, kind: str):
    """The ``kind`` bindings of ``obj``.

    Returns
    -------
    names : list of str
    vertices : (m,3) int64 ndarray
    bary : (m,3) float64 ndarray
        Re-normalised to sum to 1 (the storage is float32).
    """
    coll = obj.facelab_solve.bindings
    n = len(coll)
    v = np.empty(3 * n, np.int32)
    b = np.empty(3 * n, np.float32)
    coll.foreach_get("vertices", v)
    coll.foreach_get("bary", b)
    sel = [i for i, it in enumerate(coll) if it.kind == kind]
    names = [coll[i].name for i in sel]
    V = v.reshape(n, 3)[sel].astype(np.int64)
    B = b.reshape(n, 3)[sel].astype(np.float64)
    B /= np.where(B.sum(1, keepdims=True) > 0, B.sum(1, keepdims=True), 1.0)  # float32 storage: re-normalise
    return names, V, B
