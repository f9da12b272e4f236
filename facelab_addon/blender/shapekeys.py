"""Corrective shape keys: write displacements as new keys and key them on the timeline."""

from __future__ import annotations

import bpy
import numpy as np

__all__ = ["unique_key_name", "add_corrective_key", "key_spike"]


def unique_key_name(obj, base: str) -> str:
    """``base``, or ``base.001``... so that an existing key is never overwritten."""
    keys = obj.data.shape_keys
    names = set(keys.key_blocks.keys()) if keys else set()
    if base not in names:
        return base
    i = 1
    while f"{base}.{i:03d}" in names:
        i += 1
    return f"{base}.{i:03d}"


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
    obj.data.update()
    return kb


def key_spike(key_block, frame: int) -> None:
    """Key ``value`` 1 on ``frame`` and 0 on its neighbours (linear interpolation)."""
    for f, v in ((frame - 1, 0.0), (frame, 1.0), (frame + 1, 0.0)):
        key_block.value = v
        key_block.keyframe_insert("value", frame=f)
    key = key_block.id_data
    path = f'key_blocks["{bpy.utils.escape_identifier(key_block.name)}"].value'
    ad = key.animation_data
    if ad and ad.action:
        fc = _find_fcurve(ad, path)
        if fc is not None:
            for kp in fc.keyframe_points:
                kp.interpolation = "LINEAR"
    key_block.value = 1.0 if bpy.context.scene.frame_current == frame else 0.0


def _find_fcurve(anim_data, data_path):
    """F-curve by data path via the Blender 5.0 channelbag API (layered actions)."""
    action = anim_data.action
    slot = getattr(anim_data, "action_slot", None)
    try:
        from bpy_extras import anim_utils

        cb = anim_utils.action_get_channelbag_for_slot(action, slot)
        if cb is not None:
            return cb.fcurves.find(data_path)
    except Exception:
        pass
    fcurves = getattr(action, "fcurves", None)  # Blender < 5.0
    return fcurves.find(data_path) if fcurves is not None else None
