"""How a pipeline setting describes itself, so the panel, the scene and the CLI can offer it.

A pipeline's settings dataclass declares each user-facing field with :func:`setting`::

    @dataclass
    class ExampleSettings:  # an illustration, not one of FaceLab's settings classes
        weight: float = setting(1.0, label="Weight", min=0.0, soft_max=10.0,
                                description="How strongly the term pulls")
        reach: float = setting(0.5, label="Reach", min=0.0, unit="mouth",
                               description="How far from the sketch the mesh may move, in mouth widths")

The metadata (label, description, bounds, unit) is what a generated Blender property, a panel
row or a CLI flag needs; :func:`describe` lists it. Fields declared with plain defaults are internal
(not offered to the artist).

``unit`` is one of ``None`` (a plain number), ``"mm"`` (millimetres of the object's world space,
whatever the scene's unit scale or the object's scale), ``"mouth"`` (a multiple of the mouth
width), ``"edge"`` (a multiple of the mean lip edge length), ``"px"`` (image pixels) or
``"frames"``.
"""

from __future__ import annotations

import dataclasses

__all__ = ["UNITS", "setting", "describe", "stored"]

#: The units a setting can be expressed in (see the module docstring).
UNITS = (None, "mm", "mouth", "edge", "px", "frames")


def setting(default, *, label: str, description: str, min=None, max=None, soft_min=None, soft_max=None,
            unit: str | None = None, choices: tuple = ()):
    """A dataclass field offered to the artist (panel, scene property, CLI flag).

    Parameters
    ----------
    default : bool, int, float or str
        The default value (from a preset in ``assets/presets`` where one exists).
    label : str
        Short name shown in the panel (title case).
    description : str
        One-sentence tooltip / ``--help`` text, naming the unit.
    min, max, soft_min, soft_max : float, optional
        Bounds (hard bounds are enforced; soft ones only guide sliders).
    unit : str, optional
        One of :data:`UNITS`.
    choices : tuple of (str, str, str), optional
        ``(identifier, label, description)`` items when the setting is a choice among strings.
    """
    if unit not in UNITS:
        raise ValueError(f"unit must be one of {UNITS}, not {unit!r}")
    meta = dict(label=label, description=description, min=min, max=max, soft_min=soft_min, soft_max=soft_max,
                unit=unit, choices=tuple(choices))
    return dataclasses.field(default=default, metadata={"facelab": meta})


def describe(settings_cls) -> list:
    """The user-facing fields of a settings dataclass, in declaration order.

    Returns
    -------
    list of dict
        One dict per field declared with :func:`setting`: ``name``, ``type`` (the default's Python
        type), ``default`` and the metadata keys of :func:`setting`.
    """
    out = []
    for f in dataclasses.fields(settings_cls):
        meta = f.metadata.get("facelab")
        if meta is None:
            continue
        out.append(dict(name=f.name, type=type(f.default), default=f.default, **meta))
    return out


def stored(scene, attr: str, settings_cls):
    """The settings ``settings_cls`` saved with the shot in ``scene.<attr>``, or its defaults.

    The UI registers one scene property group per settings class (``ui/scene_settings.py``); a
    pipeline called without explicit settings reads them here, so the panel, the operators and the
    CLI agree. Values are read back as the decimals they were set to (Blender stores 32-bit floats).
    """
    group = getattr(scene, attr, None) if scene is not None else None
    if group is None:
        return settings_cls()
    kw = {}
    for d in describe(settings_cls):
        v = getattr(group, d["name"], d["default"])
        kw[d["name"]] = float(f"{v:.7g}") if d["type"] is float else d["type"](v)
    return settings_cls(**kw)
