"""What FaceLab owns in a scene: its ``FL_*`` shape keys and its correction caches.

FaceLab replaces or removes only what it recorded as its own, so an artist's key named
``FL_Prop_MyFix`` or an artist's Mesh Cache is never touched:

- shape keys: the names listed in the Key datablock's
  :data:`facelab_addon.names.OWNED_KEYS_PROP` (:func:`owned_key_names`, :func:`key_matches`);
- correction caches: per key prefix, the modifier and the files recorded in the object's
  :data:`facelab_addon.names.CORRECTION_CACHES_PROP` (:func:`correction_cache_record`,
  :func:`correction_cache`).

Reading the capture mutes both (:func:`muted_shape_keys`, :func:`muted_correction_caches`).
"""

from __future__ import annotations

import contextlib
import re

import bpy

from ..names import CORRECTION_CACHES_PROP, LEGACY_KEY_PATTERNS, LIVE_PREVIEW_KEY, OWNED_KEYS_PROP, PREFIX
from . import compat

__all__ = ["as_prefixes", "owned_key_names", "own_key", "key_matches", "owned_keys", "muted_shape_keys",
           "CORRECTION_TYPES", "correction_cache_record", "correction_cache", "is_correction_cache",
           "correction_cache_prefix", "muted_correction_caches", "correction_cache_factor"]


def as_prefixes(p) -> tuple:
    """``p`` as a tuple of name prefixes: None -> ``()``, a string -> ``(p,)``, else ``tuple(p)``."""
    if p is None:
        return ()
    if isinstance(p, str):
        return (p,)
    return tuple(p)


# --------------------------------------------------------------------------- shape keys
def owned_key_names(key, create: bool) -> list:
    """The names listed in ``key[OWNED_KEYS_PROP]`` (a list, pruned to existing keys).

    ``key`` is a Key datablock (``mesh.shape_keys``). A datablock without a registry (a file
    from before it) adopts the keys whose names match
    :data:`facelab_addon.names.LEGACY_KEY_PATTERNS`; with ``create`` the returned list is the one
    to store back (``key[OWNED_KEYS_PROP] = names``)."""
    names = set(key.key_blocks.keys())
    reg = key.get(OWNED_KEYS_PROP)
    if reg is None:
        if not create:
            return [n for n in names if _legacy(key, n)]
        reg = sorted(n for n in names if _legacy(key, n))
    return [str(n) for n in reg if str(n) in names]


def _legacy(key, name: str) -> bool:
    """Whether the key ``name`` of ``key`` is one FaceLab made before the registry: its exact FaceLab name
    (:data:`facelab_addon.names.LEGACY_KEY_PATTERNS`) *and* what FaceLab always gave such a key, so an
    artist's own key of that name (in a file FaceLab never touched) is never taken over. A numbered key
    (``FL_Prop_00``, ``FL_Solve_03``...) had the slider range -10..10; a frame key (``FL_Refine_0012``,
    ``FL_Corrected_0012``) was keyed 0, 1, 0 on the frames around the one in its name."""
    if re.fullmatch(LEGACY_KEY_PATTERNS[0], name) is not None:
        kb = key.key_blocks[name]
        return kb.slider_min == -10.0 and kb.slider_max == 10.0
    if re.fullmatch(LEGACY_KEY_PATTERNS[1], name) is None:
        return False
    frame = int(re.search(r"-?\d{4,}", name[len(PREFIX):]).group())
    ad = key.animation_data
    fc = None if ad is None or ad.action is None else compat.anim_fcurve(
        ad, f'key_blocks["{bpy.utils.escape_identifier(name)}"].value')
    if fc is None:
        return False
    keyed = {round(kp.co[0]): kp.co[1] for kp in fc.keyframe_points}
    return keyed.get(frame - 1) == 0.0 and keyed.get(frame) == 1.0 and keyed.get(frame + 1) == 0.0


def own_key(key_block) -> None:
    """Record ``key_block`` as created by FaceLab (:data:`facelab_addon.names.OWNED_KEYS_PROP`)."""
    key = key_block.id_data
    reg = owned_key_names(key, create=True)
    if key_block.name not in reg:
        reg.append(key_block.name)
    key[OWNED_KEYS_PROP] = reg


def key_matches(key, name: str, prefixes, owned=None) -> bool:
    """Whether the shape key ``name`` of the Key datablock ``key`` is one ``prefixes`` select.

    A prefix under FaceLab's own (:data:`facelab_addon.names.PREFIX`, ``FL_``) selects only keys
    FaceLab recorded as its own, so an artist's ``FL_Prop_MyFix`` is never taken for FaceLab's output;
    any other prefix (``"CaptureError"``) selects by name.

    Parameters
    ----------
    key : bpy.types.Key
    name : str
    prefixes : tuple of str
    owned : collection of str, optional
        FaceLab's recorded keys of ``key`` (computed when omitted; pass it in loops).
    """
    for p in prefixes:
        if name.startswith(p):
            if not p.startswith(PREFIX) or name == LIVE_PREVIEW_KEY:  # Live Refine's preview is never the capture
                return True
            if owned is None:
                owned = set(owned_key_names(key, create=False))
            if name in owned:
                return True
    return False


def owned_keys(obj, prefix: str = "") -> list:
    """Names of the shape keys of ``obj`` FaceLab created (recorded in the registry), starting with ``prefix``.

    A key the artist made is never listed, whatever its name (an ``FL_Prop_MyFix`` sculpted by hand
    stays the artist's). In a file from before the registry, keys named exactly as FaceLab named
    them (``FL_Prop_00``, ``FL_Refine_0012``..., :data:`facelab_addon.names.LEGACY_KEY_PATTERNS`)
    and set up as FaceLab set them up (slider range -10..10; keyed 0, 1, 0 around their frame) count
    as FaceLab's; an artist's key of such a name in a file FaceLab never touched does not.
    """
    key = obj.data.shape_keys
    if key is None:
        return []
    return [n for n in owned_key_names(key, create=False) if n.startswith(prefix)]


@contextlib.contextmanager
def muted_shape_keys(obj, prefixes):
    """Mute the shape keys ``prefixes`` select (:func:`key_matches`: under ``FL_`` only FaceLab's
    recorded keys); restore on exit."""
    pref = as_prefixes(prefixes)
    keys = obj.data.shape_keys if obj.type == "MESH" else None
    saved = []
    try:
        if keys is not None and pref:
            owned = set(owned_key_names(keys, create=False))
            for kb in keys.key_blocks:
                if key_matches(keys, kb.name, pref, owned) and kb != keys.reference_key:
                    saved.append((kb, kb.mute))
                    kb.mute = True
        yield
    finally:
        for kb, mute in saved:
            kb.mute = mute


# --------------------------------------------------------------------------- correction caches
#: Modifier types a correction cache can be: a Mesh Cache, or the Geometry Nodes modifier of a patch cache.
CORRECTION_TYPES = ("MESH_CACHE", "NODES")


def correction_cache_record(obj) -> dict:
    """``{prefix: entry}``: a copy of the correction caches recorded on ``obj``
    (:data:`facelab_addon.names.CORRECTION_CACHES_PROP`); each entry names the ``modifier``, the
    ``files`` FaceLab wrote and, for a patch cache, its ``patch`` object, ``node_group`` and
    ``attribute``."""
    rec = obj.get(CORRECTION_CACHES_PROP)
    return rec.to_dict() if rec is not None and hasattr(rec, "to_dict") else {}


def correction_cache(obj, prefix: str):
    """``(modifier or None, files)``: the correction cache FaceLab recorded on ``obj`` for ``prefix``.

    ``files`` are the absolute paths FaceLab wrote for it, oldest first (the last is the one the
    modifier plays).
    """
    entry = correction_cache_record(obj).get(prefix, {})
    md = obj.modifiers.get(entry.get("modifier", "")) if entry.get("modifier") else None
    if md is not None and md.type not in CORRECTION_TYPES:
        md = None
    return md, [str(f) for f in entry.get("files", [])]


def correction_cache_factor(obj, prefix: str):
    """``(id, data_path)`` of the keyed factor that turns ``obj``'s correction cache for ``prefix`` on (1) and off
    (0) per frame (the Mesh Cache's own, or the patch object's for a patch cache), or None without one."""
    md = correction_cache(obj, prefix)[0]
    if md is None:
        return None
    owner = obj
    if md.type == "NODES":
        owner = bpy.data.objects.get(correction_cache_record(obj).get(prefix, {}).get("patch", ""))
        md = next((m for m in owner.modifiers if m.type == "MESH_CACHE"), None) if owner is not None else None
        if md is None:
            return None
    return owner, f'modifiers["{bpy.utils.escape_identifier(md.name)}"].factor'


def is_correction_cache(obj, md) -> bool:
    """Whether the modifier ``md`` of ``obj`` is a correction cache FaceLab added (not a capture)."""
    return correction_cache_prefix(obj, md) is not None


def correction_cache_prefix(obj, md):
    """The key prefix whose correction cache the modifier ``md`` of ``obj`` plays, or None (not FaceLab's)."""
    if md.type not in CORRECTION_TYPES:
        return None
    return next((p for p, e in correction_cache_record(obj).items() if e.get("modifier") == md.name), None)


@contextlib.contextmanager
def muted_correction_caches(obj, prefixes):
    """Turn off FaceLab's correction-cache modifiers whose key prefix ``prefixes`` select (as FaceLab's
    keys are muted when the capture is read); restore on exit."""
    pref = as_prefixes(prefixes)
    mods = []
    if obj.type == "MESH" and pref:
        for p in correction_cache_record(obj):
            md = correction_cache(obj, p)[0]
            if md is not None and md.show_viewport and any(p.startswith(q) for q in pref):
                mods.append(md)
    try:
        for m in mods:
            m.show_viewport = False
        yield
    finally:
        for m in mods:
            m.show_viewport = True
