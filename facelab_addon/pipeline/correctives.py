"""Write per-frame corrections as a few compressed corrective shape keys.

Every feature that produces a correction per frame (Propagate, Solve's
out-of-subspace corrective, Retarget, Reconstruct) stores it the same way:
:func:`facelab_addon.core.geometry.compress.compress` finds a small basis that
reproduces every frame within the tolerance, each basis vector becomes a
shape key ``<prefix>NN`` and the per-frame weights are keyed on the timeline.
"""

from __future__ import annotations

import numpy as np

from ..blender.shapekeys import add_keys_from_deltas, key_values_bulk, remove_keys
from ..core.geometry.compress import compress

__all__ = ["write_corrective_keys"]


def write_corrective_keys(obj, prefix: str, deltas, frames, *, vertices=None, metres_per_unit: float = 1.0) -> list:
    """Replace FaceLab's ``prefix`` keys on ``obj`` with a compressed basis of ``deltas``.

    Parameters
    ----------
    obj : bpy.types.Object
        Mesh object that receives the keys (a Basis key is created if missing).
    prefix : str
        Key-name prefix (one of :mod:`facelab_addon.names`); previous keys with
        this prefix are removed first, other keys are never touched.
    deltas : (T,n,3) array_like
        Per-frame displacement of the vertices ``vertices`` (all vertices when
        ``vertices`` is None), object-local units, relative to each frame's
        evaluated basis.
    frames : (T,) int array_like
        Scene frame of each row of ``deltas``.
    vertices : (n,) int array_like, optional
        Vertex ids the deltas belong to; other vertices get 0.
    metres_per_unit : float
        Scene unit scale (``scene.unit_settings.scale_length``), so the
        compression tolerance is in millimetres whatever the units.

    Returns
    -------
    list of str
        Names of the keys written (empty when every frame's delta is zero).
    """
    D = np.asarray(deltas, dtype=np.float64)
    basis_part, weights = compress(D, metres_per_unit=metres_per_unit or 1.0)
    remove_keys(obj, prefix)
    if not len(basis_part):
        return []
    if vertices is None:
        basis = basis_part
    else:
        basis = np.zeros((len(basis_part), len(obj.data.vertices), 3))
        basis[:, np.asarray(vertices)] = basis_part
    names = add_keys_from_deltas(obj, prefix, basis)
    key_values_bulk(obj, names, np.asarray(frames), weights)
    return names
