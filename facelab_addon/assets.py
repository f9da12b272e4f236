"""Files FaceLab ships beside its code: presets, the sketch material, a sample lip mesh.

The ``assets/`` folder sits at the extension root, next to ``blender_manifest.toml`` and the
``facelab_addon`` package, in a checkout (``<repo>/assets``) and in an installed extension
(``<extensions>/<repo>/facelab/assets``) alike, so one path rule serves both. No ``bpy``.

Layout::

    assets/presets/sketch_refine.json   solver weights of Refine Lips (Dinev et al. 2018 §5)
    assets/presets/regions.json         Auto Regions band widths (Dinev et al. 2018 §4, Fig. 2)
    assets/presets/sketch_material.json colour of the lip-sketch Grease Pencil material
    assets/meshes/lips.obj              two facing half tubes: a tiny mouth for a first run and tests

A preset is a flat JSON object of named values; keys starting with ``_`` are comments and ignored.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

from .core.errors import FaceLabError

__all__ = ["ASSETS_DIR", "AssetError", "asset_path", "load_json", "load_preset"]

#: The ``assets`` folder at the extension root (one level above this package).
ASSETS_DIR = Path(__file__).resolve().parent.parent / "assets"

_REINSTALL = ("reinstall the FaceLab extension, or restore the file from the repository "
              "(meshes: python scripts/make_assets.py)")


class AssetError(FaceLabError):
    """An asset file is missing, unreadable, or does not hold the expected values."""


def asset_path(*parts: str) -> Path:
    """Absolute path of a file in the ``assets`` folder.

    Parameters
    ----------
    *parts : str
        Path components below ``assets/``, e.g. ``asset_path("presets", "regions.json")``.

    Returns
    -------
    pathlib.Path
        The existing file or folder.

    Raises
    ------
    AssetError
        If the path leaves the ``assets`` folder or does not exist.
    """
    if not parts:
        raise AssetError("asset_path() needs the file's path below assets/, e.g. asset_path('meshes', 'lips.obj').")
    path = ASSETS_DIR.joinpath(*parts).resolve()
    if not path.is_relative_to(ASSETS_DIR):
        raise AssetError(f"Asset path {'/'.join(parts)!r} leaves {ASSETS_DIR}; name a file inside assets/.")
    if not path.exists():
        raise AssetError(f"FaceLab asset {path} is missing; {_REINSTALL}.")
    return path


def load_json(*parts: str):
    """Parsed contents of a JSON file in the ``assets`` folder.

    Parameters
    ----------
    *parts : str
        Path components below ``assets/``.

    Returns
    -------
    dict or list
        The decoded JSON document.

    Raises
    ------
    AssetError
        If the file is missing, unreadable or not valid JSON (the message names the file and line).
    """
    path = asset_path(*parts)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise AssetError(f"Cannot read FaceLab asset {path} ({e}); {_REINSTALL}.") from None
    try:
        return json.loads(text)
    except json.JSONDecodeError as e:
        raise AssetError(f"FaceLab asset {path} is not valid JSON (line {e.lineno}, column {e.colno}: {e.msg}); "
                         f"fix the file or {_REINSTALL}.") from None


def load_preset(name: str, schema: dict) -> dict:
    """Values of ``assets/presets/<name>.json``, checked against a schema.

    Parameters
    ----------
    name : str
        Preset name without ``.json`` (``"sketch_refine"``, ``"regions"``, ``"sketch_material"``).
    schema : dict of str to type
        Expected keys and their types: ``int``, ``float`` (ints accepted, converted), ``bool``,
        ``str`` or ``tuple`` (a JSON list of numbers, returned as a tuple of floats). Numbers must be
        finite.

    Returns
    -------
    dict
        The values, in the schema's key order, converted to the schema's types.

    Raises
    ------
    AssetError
        If the file is missing or broken, a key is missing or unknown, or a value has the wrong type;
        the message names the file and the key.
    """
    data = load_json("presets", f"{name}.json")
    path = ASSETS_DIR / "presets" / f"{name}.json"
    if not isinstance(data, dict):
        raise AssetError(f"Preset {path} must hold a JSON object of named values, got {type(data).__name__}; "
                         f"fix the file or {_REINSTALL}.")
    values = {k: v for k, v in data.items() if not k.startswith("_")}
    missing = [k for k in schema if k not in values]
    unknown = [k for k in values if k not in schema]
    if missing or unknown:
        what = "; ".join(s for s in (f"missing {missing}" if missing else "",
                                     f"unknown {unknown}" if unknown else "") if s)
        raise AssetError(f"Preset {path}: {what} (expected keys {list(schema)}); fix the file or {_REINSTALL}.")
    out = {}
    for key, kind in schema.items():
        out[key] = _convert(values[key], kind, path, key)
    return out


def _convert(value, kind, path, key):
    def bad(expected):
        return AssetError(f"Preset {path}: {key!r} must be {expected}, got {value!r}; fix the file or {_REINSTALL}.")

    def number(v):
        return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)

    if kind is bool:
        if not isinstance(value, bool):
            raise bad("true or false")
        return value
    if kind is str:
        if not isinstance(value, str):
            raise bad("a string")
        return value
    if kind is int:
        if not (isinstance(value, int) and not isinstance(value, bool)):
            raise bad("an integer")
        return value
    if kind is float:
        if not number(value):
            raise bad("a finite number")
        return float(value)
    if kind is tuple:
        if not (isinstance(value, list) and value and all(number(v) for v in value)):
            raise bad("a list of finite numbers")
        return tuple(float(v) for v in value)
    raise TypeError(f"load_preset schema type {kind!r} for {key!r} is not one of int, float, bool, str, tuple")
