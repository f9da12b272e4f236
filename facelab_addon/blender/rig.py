"""Shape-key rigs -> arrays: the blendshape rig, the dataset of facial shapes, FaceLab's keys, drivers.

Every reader works in object-local coordinates (shape-key space) and leaves
out FaceLab's own keys (those it recorded, :func:`.ownership.owned_keys`).
"""

from __future__ import annotations

import numpy as np

from .. import names as fl
from ..core.errors import FaceLabError
from .actions import curve_values, key_path
from .ownership import owned_keys
from .shapekeys import rest_vertices

__all__ = [
    "rig_shapes",
    "rig_animation",
    "prefixed_key_deltas",
    "dataset_shapes",
    "template_shapes",
    "add_product_driver",
]


def _key_coords(kb, n, dtype):
    a = np.empty(3 * n, dtype)
    kb.data.foreach_get("co", a)
    return a.reshape(n, 3)


def rig_shapes(obj):
    """The blendshape rig of ``obj``: its shape keys except the Basis, muted keys and FaceLab's keys.

    Returns
    -------
    names : list of str
    neutral : (V,3) float64 ndarray
        The Basis key.
    deltas : (S,V,3) float64 ndarray
        Each key minus its relative key.

    Raises
    ------
    FaceLabError
        No shape keys, absolute keys, or nothing but a Basis to solve for.
    """
    key = obj.data.shape_keys
    if key is None or len(key.key_blocks) < 2:
        raise FaceLabError(
            f"'{obj.name}' has no shape keys: the solve needs a blendshape rig. Add the expressions as shape keys "
            "(Object Data > Shape Keys) on top of a Basis."
        )
    if not key.use_relative:
        raise FaceLabError(f"The shape keys of '{obj.name}' are absolute; enable Relative in Object Data > Shape Keys.")
    n = len(obj.data.vertices)
    basis = key.reference_key

    def co(kb):
        return _key_coords(kb, n, np.float32).astype(np.float64)

    names, deltas, owned = [], [], set(owned_keys(obj))
    for kb in key.key_blocks:
        if kb == basis or kb.mute or (kb.name.startswith(fl.PREFIX) and kb.name in owned):
            continue
        names.append(kb.name)
        deltas.append(co(kb) - co(kb.relative_key))
    if not names:
        raise FaceLabError(
            f"'{obj.name}' has only a Basis (or only muted / FaceLab keys): add the blendshape expressions as shape "
            "keys to solve for."
        )
    return names, co(basis), np.stack(deltas)


def prefixed_key_deltas(obj, prefix: str, neutral):
    """``(names, (R,V,3) float64)``: the keys named ``prefix*`` minus ``neutral`` (V,3), in key order."""
    key = obj.data.shape_keys
    kbs = [kb for kb in key.key_blocks if kb.name.startswith(prefix)] if key is not None else []
    n = len(neutral)
    out = np.empty((len(kbs), n, 3))
    for i, kb in enumerate(kbs):
        out[i] = _key_coords(kb, n, np.float32) - neutral
    return [kb.name for kb in kbs], out


def rig_animation(obj, frames, corrective_prefix: str = fl.SOLVE_PREFIX, *, factored: bool = False):
    """A solved performance as arrays: the rig, its keyed weights and its keyed correctives.

    Parameters
    ----------
    obj : bpy.types.Object
        The actor (a rig as :func:`rig_shapes` reads it, animated by F-curves).
    frames : (T,) array_like of int
    corrective_prefix : str
        Prefix of the per-frame corrective keys.

    Returns
    -------
    names : list of str
    neutral : (V,3) float64 ndarray
    deltas : (S,V,3) float64 ndarray
    weights : (T,S) float64 ndarray
        Key values on ``frames`` from their F-curves.
    correctives : (T,V,3) float64 ndarray or None
        The corrective keys mixed by their keyed values (None without such keys); with
        ``factored``, the pair ``(keys' deltas (R,V,3), keyed values (T,R))`` instead (no
        (T,V,3) array is built).
    """
    names, neutral, deltas = rig_shapes(obj)
    key = obj.data.shape_keys
    W = curve_values(key, names, frames)
    c_names, basis = prefixed_key_deltas(obj, corrective_prefix, neutral)
    C = None
    if c_names:
        cw = curve_values(key, c_names, frames)
        C = (basis, cw) if factored else np.einsum("tr,rvd->tvd", cw, basis)
    return names, neutral, deltas, W, C


def dataset_shapes(obj):
    """The dataset of facial shapes: every shape key of ``obj`` but the Basis and FaceLab's keys.

    Returns
    -------
    names : list of str
    shapes : (S,V,3) float64 ndarray
        Object-local positions: Basis + (key - its relative key).

    Raises
    ------
    FaceLabError
        When the object has no shape keys.
    """
    key = obj.data.shape_keys
    if key is None:
        raise FaceLabError(
            f"'{obj.name}' has no shape keys; the dataset of facial shapes must be shape keys of the face "
            "(at least 4)."
        )
    n = len(obj.data.vertices)
    basis = key.reference_key

    def co(kb):
        return _key_coords(kb, n, np.float64)

    base = co(basis)
    names, shapes, owned = [], [], set(owned_keys(obj))
    for kb in key.key_blocks:
        if kb == basis or (kb.name.startswith(fl.PREFIX) and kb.name in owned):
            continue
        names.append(kb.name)
        shapes.append(base + co(kb) - co(kb.relative_key))
    return names, np.array(shapes).reshape(-1, n, 3)


def template_shapes(rig_obj, neutral) -> dict:
    """``{name: (V,3)}``: the template rig's shape keys as deltas applied to the face's ``neutral`` (V,3).

    Raises
    ------
    FaceLabError
        When the rig's vertex count differs from the face's.
    """
    names, shapes = dataset_shapes(rig_obj)
    if shapes.shape[1] != len(neutral):
        raise FaceLabError(
            f"Rig '{rig_obj.name}' has {shapes.shape[1]} vertices, the face {len(neutral)}; the template rig must "
            "share the face's topology (transfer it onto the actor's neutral first)."
        )
    base = rest_vertices(rig_obj)
    return {n: neutral + (s - base) for n, s in zip(names, shapes)}


def add_product_driver(key, kb, components):
    """Drive ``kb.value`` by the product of the values of the shape keys ``components`` (a combination corrective).

    Returns the driver's F-curve.
    """
    fc = kb.driver_add("value")
    drv = fc.driver
    drv.type = "SCRIPTED"
    terms = []
    for i, name in enumerate(components):
        v = drv.variables.new()
        v.name = f"w{i}"
        v.type = "SINGLE_PROP"
        v.targets[0].id_type = "KEY"
        v.targets[0].id = key
        v.targets[0].data_path = key_path(name)
        terms.append(v.name)
    drv.expression = " * ".join(terms)
    return fc
