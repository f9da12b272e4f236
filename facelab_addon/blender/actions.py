"""Shape-key and scene animation <-> arrays: F-curve values on frames, and the action FaceLab writes into.

Layered actions: curves live in the channelbag of the action slot assigned
to the animated ID (``compat.anim_data_channelbag``).
"""

from __future__ import annotations

import bpy
import numpy as np

from . import compat

__all__ = [
    "ACTION_TAG",
    "key_path",
    "fcurve_paths",
    "animated_keys",
    "prepare_action",
    "curve_values",
    "scene_vector_values",
]

#: Custom property marking the actions FaceLab made (a re-run replaces their curves in place).
ACTION_TAG = "facelab_solve"


def key_path(name: str) -> str:
    """Data path of shape key ``name``'s value on its Key datablock."""
    return f'key_blocks["{bpy.utils.escape_identifier(name)}"].value'


def fcurve_paths(action) -> set:
    """Data paths of every F-curve of ``action`` (all layers, strips and channelbags)."""
    paths = set()
    for layer in getattr(action, "layers", ()):
        for strip in layer.strips:
            for cb in strip.channelbags:
                paths.update(fc.data_path for fc in cb.fcurves)
    return paths


def animated_keys(key, names) -> list:
    """The shape keys among ``names`` whose value has an F-curve in ``key``'s current action, sorted."""
    ad = key.animation_data
    act = ad.action if ad is not None else None
    if act is None:
        return []
    paths = fcurve_paths(act)
    return sorted(n for n in names if key_path(n) in paths)


def prepare_action(key, names, mode: str, action_name: str) -> str:
    """Make sure writing the rig keys' curves never silently destroys the artist's animation.

    * no action: a new one ``action_name`` (tagged as FaceLab's);
    * FaceLab's own action (a previous run): reused, its curves replaced;
    * an artist's action animating none of ``names``: written into in place;
    * an artist's action animating some of ``names``: ``mode == 'NEW_ACTION'``
      copies it to ``action_name`` (everything else keeps playing), keeps the
      original with a fake user and assigns the copy; ``'REPLACE'`` writes
      into it.

    Parameters
    ----------
    key : bpy.types.Key
        The rig's shape-key datablock.
    names : sequence of str
        The rig keys about to be keyed.
    mode : {"NEW_ACTION", "REPLACE"}
    action_name : str
        Name of a new action (one of :mod:`facelab_addon.names`).

    Returns
    -------
    str
        A note for the report ('' when nothing needed saying).
    """
    ad = key.animation_data or key.animation_data_create()
    act = ad.action
    if act is None:
        act = bpy.data.actions.new(action_name)
        act[ACTION_TAG] = True
        ad.action = act
        return ""
    if act.get(ACTION_TAG):
        return ""
    animated = sorted(n for n in names if key_path(n) in fcurve_paths(act))
    if not animated:
        return ""
    if mode == "REPLACE":
        return f"replaced the curves of {len(animated)} animated keys in action '{act.name}'"
    slot_id = ad.action_slot.identifier if ad.action_slot is not None else None
    new = act.copy()
    new.name = action_name
    new[ACTION_TAG] = True
    act.use_fake_user = True
    ad.action = new
    if ad.action_slot is None and len(new.slots):
        match = [s for s in new.slots if s.identifier == slot_id]
        ad.action_slot = match[0] if match else new.slots[0]
    return (f"kept your action '{act.name}' (fake user; {len(animated)} keys were animated) and wrote the result "
            f"to the new action '{new.name}'")


def curve_values(key, names, frames) -> np.ndarray:
    """(T,K) values of shape keys ``names`` on ``frames`` from their F-curves.

    A key without an (unmuted) F-curve in the assigned action slot holds its
    current value on every frame.
    """
    ad = key.animation_data
    cb = compat.anim_data_channelbag(ad) if ad is not None else None
    out = np.empty((len(frames), len(names)))
    for k, n in enumerate(names):
        fc = cb.fcurves.find(key_path(n)) if cb is not None else None
        if fc is not None and not fc.mute:
            out[:, k] = [fc.evaluate(float(f)) for f in frames]
        else:
            out[:, k] = key.key_blocks[n].value
    return out


def scene_vector_values(scene, path: str, current, frames) -> np.ndarray:
    """(T,n) values of a scene vector property on ``frames``.

    Parameters
    ----------
    path : str
        The property's data path on the scene (e.g. ``"facelab_solve.end_points_upper"``).
    current : (n,) array_like
        Its current value, used for every component without an (unmuted) F-curve.
    frames : (T,) array_like of int
    """
    cur = np.array(current, dtype=np.float64)
    out = np.broadcast_to(cur, (len(frames), len(cur))).copy()
    ad = scene.animation_data
    cb = compat.anim_data_channelbag(ad) if ad is not None else None
    if cb is None:
        return out
    for i in range(len(cur)):
        fc = cb.fcurves.find(path, index=i) if cb is not None else None
        if fc is not None and not fc.mute:
            out[:, i] = [fc.evaluate(float(f)) for f in frames]
    return out
