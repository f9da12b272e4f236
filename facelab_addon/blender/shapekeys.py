"""Corrective shape keys: write displacements as new keys and key them on the timeline."""

from __future__ import annotations


import bpy
import numpy as np

from ..names import CORRECTIVES_ACTION, OWNED_KEYS_PROP, PREFIX
from . import compat
from .ownership import key_matches, own_key, owned_key_names, owned_keys

__all__ = [
    "unique_key_name",
    "add_corrective_key",
    "key_spike",
    "zero_on_frame",
    "find_fcurve",
    "values_from_action_only",
    "key_values",
    "shape_key_sequence",
    "remove_keys",
    "key_values_bulk",
    "key_property_bulk",
    "add_keys_from_deltas",
    "rest_vertices",
    "remove_fcurve",
    "fcurve_for_key",
    "finite_key_offsets",
]


def unique_name(base: str, names) -> str:
    """``base``, or ``base.001``, ``base.002``... the first not in ``names`` (Blender's own scheme)."""
    names = set(names)
    if base not in names:
        return base
    i = 1
    while f"{base}.{i:03d}" in names:
        i += 1
    return f"{base}.{i:03d}"


def unique_key_name(obj, base: str) -> str:
    """``base``, or ``base.001``... so that an existing key is never overwritten."""
    keys = obj.data.shape_keys
    return unique_name(base, keys.key_blocks.keys() if keys else ())


def add_corrective_key(obj, name: str, deltas_local) -> "bpy.types.ShapeKey":
    """Add a shape key = Basis + ``deltas_local`` (V,3), object-local units.

    Creates the Basis key from the mesh when the object has none. Never
    replaces an existing key: ``name`` is made unique first.
    """
    d = np.asarray(deltas_local, dtype=np.float64)
    n = len(obj.data.vertices)
    if d.shape != (n, 3):
        raise ValueError(f"deltas must be ({n},3), got {d.shape}")
    if obj.data.shape_keys is None:
        obj.shape_key_add(name="Basis", from_mix=False)
    basis = obj.data.shape_keys.reference_key
    co = np.empty(n * 3, dtype=np.float64)
    basis.data.foreach_get("co", co)
    kb = obj.shape_key_add(name=unique_key_name(obj, name), from_mix=False)
    kb.relative_key = basis
    kb.data.foreach_set("co", (co + d.ravel()).astype(np.float32))
    kb.value = 0.0
    own_key(kb)
    obj.data.update()
    return kb


def key_spike(key_block, frame: int) -> None:
    """Key ``value`` 1 on ``frame`` and 0 on its neighbours (linear interpolation)."""
    from .scene_time import require_scene_time

    require_scene_time(None, "Keying")
    for f, v in ((frame - 1, 0.0), (frame, 1.0), (frame + 1, 0.0)):
        key_block.value = v
        key_block.keyframe_insert("value", frame=f)
    key = key_block.id_data
    path = f'key_blocks["{bpy.utils.escape_identifier(key_block.name)}"].value'
    ad = key.animation_data
    if ad and ad.action:
        fc = compat.anim_fcurve(ad, path)
        if fc is not None:
            for kp in fc.keyframe_points:
                kp.interpolation = "LINEAR"
    key_block.value = 1.0 if bpy.context.scene.frame_current == frame else 0.0


def zero_on_frame(id_data, data_path: str, frame: int) -> bool:
    """Key ``id_data.<data_path>`` 0 on ``frame``, leaving every other integer frame's value as it was.

    Its values on ``frame - 1`` and ``frame + 1`` are keyed as they evaluate now (when not keyed already) and the
    three keyframes interpolate linearly, so only ``frame`` (and the subframes around it) changes. Returns
    whether there was an F-curve to change (a property that is not animated is left alone).
    """
    fc = find_fcurve(id_data, data_path)
    if fc is None:
        return False
    n = len(fc.keyframe_points)
    co = np.empty(2 * n, np.float32)
    fc.keyframe_points.foreach_get("co", co)
    keyed = set(np.round(co[0::2]).astype(np.int64).tolist()) if n else set()
    values = {f: (0.0 if f == frame else float(fc.evaluate(f))) for f in (frame - 1, frame, frame + 1)}
    for f, v in values.items():
        if f == frame or f not in keyed:
            kp = fc.keyframe_points.insert(f, v)
            kp.interpolation = "LINEAR"
    fc.update()
    return True


def find_fcurve(id_data, data_path: str):
    """The F-curve animating ``id_data.<data_path>`` in its action, or None (no action, not keyed).

    Parameters
    ----------
    id_data : bpy.types.ID
        An object, a shape-key datablock (``mesh.shape_keys``)...
    data_path : str
        For example ``'["FL_extrapolation"]'`` or ``'key_blocks["Smile"].value'``.
    """
    ad = getattr(id_data, "animation_data", None)
    if ad is None or ad.action is None:
        return None
    return compat.anim_fcurve(ad, data_path)


# --------------------------------------------------------------------------- sequences
def fcurve_for_key(key, kb):
    """The F-curve keying the value of the key block ``kb`` of the Key datablock ``key``, or None."""
    ad = key.animation_data
    if ad is None or ad.action is None:
        return None
    return compat.anim_fcurve(ad, f'key_blocks["{bpy.utils.escape_identifier(kb.name)}"].value')


def values_from_action_only(key) -> bool:
    """Whether ``key``'s values on any frame are those of its action's F-curves (or the current values): no
    drivers, NLA, partial influence or layered blending, which only a scene evaluation gives."""
    ad = key.animation_data
    return ad is None or not (len(ad.drivers) or len(ad.nla_tracks) or ad.action_influence != 1.0
                              or ad.action_blend_type != "REPLACE")


def key_values(key, kb, frames) -> np.ndarray:
    """(T,) float64 value of the key block ``kb`` on scene ``frames``: its (unmuted) F-curve, else its current
    value, clipped to its slider range (what the mix uses when :func:`values_from_action_only`)."""
    frames = np.asarray(frames, dtype=np.float64).ravel()
    fc = fcurve_for_key(key, kb)
    if fc is not None and not fc.mute:
        w = np.array([fc.evaluate(f) for f in frames])
    else:
        w = np.full(len(frames), kb.value)
    return np.clip(w, kb.slider_min, kb.slider_max)


def finite_key_offsets(obj, kb, offsets, frames, weights, vertices=None):
    """A key's flat offsets ``offsets`` (3V,) with non-finite entries zeroed where the key is off, or refused.

    A key with a NaN or infinite position shows it only on the frames where its value is not 0 (Blender skips a
    key of value 0); mixed as ``value * offset`` it would give NaN (0 x inf) on every frame. ``weights`` (T,)
    are its values on ``frames`` (T,); ``vertices`` (n,) the vertex ids of the offsets when they are a subset.

    Raises
    ------
    MeshError
        The key is on (value not 0) on some of ``frames``: naming the key, its first bad vertex and those frames
        (the scene frames, not list positions).
    """
    bad = ~np.isfinite(offsets)
    if not bad.any():
        return offsets
    on = np.asarray(frames)[np.asarray(weights) != 0]
    if len(on):
        first = int(np.flatnonzero(bad)[0]) // 3
        first = first if vertices is None else int(vertices[first])
        from ..core.errors import MeshError

        shown = ", ".join(f"{f:g}" for f in on[:5]) + (f" and {len(on) - 5} more" if len(on) > 5 else "")
        raise MeshError(
            f"The shape key '{kb.name}' of '{obj.name}' has NaN or infinite positions "
            f"({int(bad.reshape(-1, 3).any(axis=1).sum())} vertices, the first {first}) and "
            f"is on (value not 0) on frame {shown}: those frames would be broken. Fix or delete the key (or key it "
            "to 0 there), then run again.")
    out = offsets.copy()
    out[bad] = 0.0
    return out


def shape_key_sequence(obj, frames, *, skip_prefixes=(PREFIX,), ignore_modifiers: bool = False):
    """(T,V,3) float32 object-local positions of a shape-key-animated mesh, without frame_set.

    Evaluates each key's value F-curve at ``frames`` and mixes
    ``basis + sum_k value_k (key_k - relative_k)``, honouring mute,
    slider limits and relative keys. Keys ``skip_prefixes`` select
    (:func:`key_matches`: FaceLab's own output) are left out.

    With ``ignore_modifiers`` the mix is returned even when modifiers deform the mesh (the input
    of the modifier stack). Returns ``None`` when this fast path does not apply (modifiers that
    deform, drivers, vertex-group-masked keys, absolute keys): use frame-by-frame
    evaluation then.
    """
    key = obj.data.shape_keys
    frames = np.asarray(frames, dtype=np.float64)
    n = len(obj.data.vertices)
    if not ignore_modifiers and any(m.show_viewport for m in obj.modifiers):
        return None
    if key is None:
        co = np.empty(n * 3, np.float32)
        obj.data.vertices.foreach_get("co", co)
        return np.broadcast_to(co.reshape(1, n, 3), (len(frames), n, 3)).copy()
    if not key.use_relative:
        return None
    if not values_from_action_only(key):
        return None  # drivers / NLA / layered blending: evaluate frame by frame instead
    basis = key.reference_key

    def coords(kb):
        c = np.empty(n * 3, np.float32)
        kb.data.foreach_get("co", c)
        return c

    deltas, weights = [], []
    skip, owned = tuple(skip_prefixes), set(owned_key_names(key, create=False))
    for kb in key.key_blocks:
        if kb == basis or kb.mute or key_matches(key, kb.name, skip, owned):
            continue
        if kb.vertex_group:
            return None
        w = key_values(key, kb, frames)
        if not np.any(w):
            continue
        deltas.append(finite_key_offsets(obj, kb, coords(kb) - coords(kb.relative_key), frames, w))
        weights.append(w)
    out = np.empty((len(frames), n * 3), np.float32)
    if deltas:
        np.matmul(np.stack(weights, 1).astype(np.float32), np.stack(deltas), out=out)
        out += coords(basis)
    else:
        out[:] = coords(basis)
    return out.reshape(len(frames), n, 3)


def remove_keys(obj, prefix: str) -> int:
    """Remove FaceLab's own shape keys named ``prefix*`` (:func:`owned_keys`) and their F-curves.

    Keys the artist made are kept, even when their name starts with ``prefix``.
    """
    key = obj.data.shape_keys
    if key is None:
        return 0
    names = owned_keys(obj, prefix)
    ad = key.animation_data
    for name in names:
        if ad is not None and ad.action is not None:
            cb = _channelbag(ad, create=False)
            path = f'key_blocks["{bpy.utils.escape_identifier(name)}"].value'
            fc = cb.fcurves.find(path) if cb is not None else None
            if fc is not None:
                cb.fcurves.remove(fc)
        obj.shape_key_remove(key.key_blocks[name])
    if names:
        key = obj.data.shape_keys
        if key is not None:
            key[OWNED_KEYS_PROP] = owned_key_names(key, create=True)
    return len(names)


def _channelbag(anim_data, create: bool):
    """The channelbag of the assigned action slot, creating the slot if asked."""
    return compat.anim_data_channelbag(anim_data, create=create)


def key_property_bulk(id_data, data_path: str, frames, values, action_name: str = CORRECTIVES_ACTION) -> None:
    """Key ``values`` (T,) of ``id_data.<data_path>`` on ``frames`` (T,) in one bulk insert.

    Uses the channelbag of the assigned action slot (``keyframe_points.add`` +
    ``foreach_set``) with linear interpolation. An existing action (the
    artist's animation) is kept; only this one F-curve is (re)written.
    """
    from .scene_time import SceneTimeError, require_scene_time

    require_scene_time(None, "Keying")  # keys on scene frames play at those frames only without Time Stretching
    ad = id_data.animation_data or id_data.animation_data_create()
    if ad.use_tweak_mode:
        raise SceneTimeError(f"Keying '{id_data.name}': its animation is in NLA tweak mode (the strip's action plays "
                             "in the strip's time); leave tweak mode (Tab in the NLA editor) and run again.")
    if ad.action is None:
        ad.action = bpy.data.actions.new(action_name)
    cb = _channelbag(ad, create=True)
    f = np.asarray(frames, dtype=np.float32)
    v = np.asarray(values, dtype=np.float32).reshape(len(f))
    fc = cb.fcurves.find(data_path)
    if fc is not None:
        cb.fcurves.remove(fc)
    fc = cb.fcurves.new(data_path)
    fc.keyframe_points.add(len(f))
    co = np.empty(2 * len(f), np.float32)
    co[0::2], co[1::2] = f, v
    fc.keyframe_points.foreach_set("co", co)
    lin = bpy.types.Keyframe.bl_rna.properties["interpolation"].enum_items["LINEAR"].value
    fc.keyframe_points.foreach_set("interpolation", np.full(len(f), lin, np.int32))
    fc.update()


def key_values_bulk(obj, names, frames, values) -> None:
    """Key shape-key values ``values`` (T,K) on ``frames`` (T,) for keys ``names`` (K,), in bulk."""
    key = obj.data.shape_keys
    V = np.asarray(values, dtype=np.float32).reshape(len(frames), len(names))
    for k, name in enumerate(names):
        key_property_bulk(key, f'key_blocks["{bpy.utils.escape_identifier(name)}"].value', frames, V[:, k])


def add_keys_from_deltas(obj, prefix: str, deltas) -> list:
    """Add shape keys ``prefix00``, ``prefix01``... = Basis + deltas[i] (R,V,3), object-local units."""
    names = []
    for i, d in enumerate(np.asarray(deltas)):
        kb = add_corrective_key(obj, f"{prefix}{i:02d}", d)
        kb.slider_min, kb.slider_max = -10.0, 10.0
        names.append(kb.name)
    return names


def rest_vertices(obj) -> np.ndarray:
    """(V,3) float64 object-local rest positions (the Basis key, else the mesh)."""
    n = len(obj.data.vertices)
    co = np.empty(n * 3, np.float64)
    key = obj.data.shape_keys
    (key.reference_key.data if key else obj.data.vertices).foreach_get("co", co)
    return co.reshape(n, 3)


def remove_fcurve(id_data, data_path: str) -> bool:
    """Remove the F-curve animating ``id_data.<data_path>`` from its action; whether there was one."""
    ad = getattr(id_data, "animation_data", None)
    if ad is None or ad.action is None:
        return False
    cb = _channelbag(ad, create=False)
    fc = cb.fcurves.find(data_path) if cb is not None else None
    if fc is None:
        fcurves = getattr(ad.action, "fcurves", None)  # Blender < 5.0 without slots
        fc = fcurves.find(data_path) if fcurves is not None else None
        if fc is None:
            return False
        fcurves.remove(fc)
        return True
    cb.fcurves.remove(fc)
    return True
