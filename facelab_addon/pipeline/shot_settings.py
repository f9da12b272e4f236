"""The settings stored with the shot: which pipeline settings a scene holds, and reading them.

Every field a pipeline's settings dataclass declares with
:func:`facelab_addon.pipeline.settings.setting` is stored on the scene in a property group
(``scene.<attr>``, generated and registered by :mod:`facelab_addon.ui.scene_settings`), is a
default for new scenes in the add-on preferences, and is a flag of the CLI commands that run the
step (:func:`add_flags`, :func:`apply_flags`). Adding a settings class is one line of
:data:`SCENE_SETTINGS`::

    Entry("facelab_store", StorageSettings, "FACELAB_PT_propagate", ("propagate",)),

Fields named in :data:`SHARED` are stored once, in FaceLab > Setup (``scene.facelab``), for every step.
A scene's group is filled from the preferences' defaults the first time a FaceLab operator, the CLI
or a file load touches it (:func:`ensure_initialized`).

The readers (:func:`scene_settings`, :func:`refine_settings`, :func:`solve_settings`,
:func:`reconstruct_settings`...) turn the scene's values into a pipeline's settings; the operators
and the CLI both call them, so neither depends on the other.
"""

from __future__ import annotations

import argparse
from typing import NamedTuple

import bpy
import numpy as np

from ..blender import tracking
from ..blender.actions import scene_vector_values
from ..names import STORE_SETTINGS_ATTR
from .bake import BakeSettings
from .correctives import StorageSettings
from .propagate import PropagateSettings
from .reconstruct import CorrectiveSettings, ReconstructSettings
from .refine import RefineSettings
from .regions import RegionSettings
from .retarget import RetargetSettings
from .settings import describe
from .solve import BindSettings, SolveSettings

# The add-on's module name: "facelab_addon" from a checkout, "bl_ext.<repo>.facelab" as an
# extension (whose root __init__.py imports the facelab_addon sub-package).
_parts = __package__.split(".")
ADDON_ID = ".".join(_parts[: _parts.index("facelab_addon")]) or "facelab_addon"


class Entry(NamedTuple):
    """One settings class stored on the scene.

    Attributes
    ----------
    attr : str
        Scene attribute holding the generated property group (``scene.<attr>``).
    cls : type
        The pipeline's settings dataclass.
    panel : str or None
        ``bl_idname`` of the panel whose *Settings* sub-panel draws the fields (None: FaceLab's main panel).
    commands : tuple of str
        CLI commands (``python -m facelab_addon COMMAND``) that take the fields as flags.
    label : str
        The sub-panel's title (distinct among the sub-panels of one step).
    everyday : tuple of str or None
        The fields an artist changes in everyday work, drawn in the sub-panel; the others (solver
        weights) go to its closed *Advanced* sub-panel. None: every field is everyday.
    """

    attr: str
    cls: type
    panel: str | None = None
    commands: tuple = ()
    label: str = "Settings"
    everyday: tuple | None = None


#: The settings stored with the shot. Adding a settings class is one line here.
SCENE_SETTINGS = (
    Entry("facelab_regions", RegionSettings, "FACELAB_PT_setup", ("propagate",)),
    Entry("facelab_refine", RefineSettings, "FACELAB_PT_sketch", ("refine",),
          everyday=("free_radius", "use_regions", "crossings", "all_views")),
    Entry("facelab_propagate", PropagateSettings, "FACELAB_PT_propagate", ("propagate",), label="Propagate Settings"),
    Entry("facelab_bake", BakeSettings, "FACELAB_PT_bake", ()),
    Entry(STORE_SETTINGS_ATTR, StorageSettings, "FACELAB_PT_propagate", ("propagate", "solve", "reconstruct", "retarget"),
          label="Shape Key Storage", everyday=("cache_directory",)),
)

#: Fields every step shares, stored once in FaceLab > Setup: ``{field: property of scene.facelab}``.
SHARED = {"fixed_group": "fixed_group"}

#: How a unit reads after a label (``"Lip Band (mouth widths)"``).
UNIT_LABELS = {"mm": "mm", "mouth": "mouth widths", "edge": "edge lengths", "px": "px", "frames": "frames"}

#: Marks a scene group whose values are the shot's own (set from the preferences or edited).
INITIALIZED = "initialized"


def fields(entry: Entry) -> list:
    """The described fields of ``entry`` stored in its scene group (not the shared ones)."""
    return [d for d in describe(entry.cls) if d["name"] not in SHARED]


def panel_fields(entry: Entry, advanced: bool) -> list:
    """The fields drawn in ``entry``'s sub-panel (``advanced`` False) or in its *Advanced* sub-panel."""
    return [d for d in fields(entry) if (entry.everyday is not None and d["name"] not in entry.everyday) == advanced]


def label(d: dict) -> str:
    """A field's panel label with its unit."""
    u = UNIT_LABELS.get(d["unit"])
    return f"{d['label']} ({u})" if u else d["label"]


def entry_for(cls_or_attr) -> Entry | None:
    """The :data:`SCENE_SETTINGS` entry of a settings class or a scene attribute."""
    for e in SCENE_SETTINGS:
        if e.cls is cls_or_attr or e.attr == cls_or_attr:
            return e
    return None


# --------------------------------------------------------------------------- preferences -> scene
def preferences(context=None):
    """FaceLab's ``AddonPreferences`` when enabled as an add-on (None from the ``bpy`` module or a script)."""
    context = context or bpy.context
    addon = context.preferences.addons.get(ADDON_ID)
    return None if addon is None else addon.preferences


def preference_defaults(entry: Entry, context=None) -> dict:
    """``{field: value}`` for a new scene: the add-on preferences' defaults when enabled, else the dataclass's."""
    out = {d["name"]: d["default"] for d in fields(entry)}
    p = preferences(context)
    grp = getattr(p, entry.attr, None) if p is not None else None
    if grp is not None:
        out.update({k: getattr(grp, k) for k in out})
    return out


def ensure_initialized(scene, entry: Entry, context=None) -> bool:
    """Fill ``scene``'s group of ``entry`` from the preferences' defaults unless it holds the shot's own values.

    Returns True when it was filled now."""
    grp = getattr(scene, entry.attr, None)
    if grp is None or grp.get(INITIALIZED):
        return False
    for k, v in preference_defaults(entry, context).items():
        setattr(grp, k, v)
    grp[INITIALIZED] = True
    return True


def copy_values(src, dst, entry: Entry) -> None:
    """Copy every field of ``entry`` from one group to another (scene <-> preferences)."""
    for d in fields(entry):
        setattr(dst, d["name"], getattr(src, d["name"]))


def _exact(v, d):
    """A float property's value as the decimal it was set to (Blender stores 32-bit floats: 0.1 reads
    0.10000000149)."""
    return float(f"{v:.7g}") if d["type"] is float else v


def scene_settings(scene, cls, **overrides):
    """The settings ``cls(...)`` stored in ``scene`` (filled from the preferences first when new), with
    ``overrides`` (an operator's own options) on top. A class not in :data:`SCENE_SETTINGS` gets its defaults."""
    entry = entry_for(cls)
    kw = {}
    if entry is not None and getattr(scene, entry.attr, None) is not None:
        ensure_initialized(scene, entry)
        grp = getattr(scene, entry.attr)
        kw = {d["name"]: _exact(getattr(grp, d["name"]), d) for d in fields(entry)}
    names = {d["name"] for d in describe(cls)}
    for field, prop in SHARED.items():
        if field in names:
            kw[field] = getattr(scene.facelab, prop)
    kw.update(overrides)
    return cls(**kw)


def values(scene, entry: Entry) -> dict:
    """``{field: value}`` stored in ``scene`` for ``entry`` (shared fields included), for summaries."""
    s = scene_settings(scene, entry.cls)
    return {d["name"]: getattr(s, d["name"]) for d in describe(entry.cls)}


# --------------------------------------------------------------------------- CLI flags
def flag(d: dict, attr: str, taken: set) -> str:
    """``--lambda-pos`` (``--<attr>-lambda-pos`` when another group of the command has that name)."""
    f = "--" + d["name"].replace("_", "-")
    if f in taken:
        f = "--" + attr.removeprefix("facelab_") + "-" + d["name"].replace("_", "-")
    taken.add(f)
    return f


def command_fields(command: str):
    """``[(entry, field dict, flag, dest), ...]`` of the settings a CLI command takes as flags."""
    out, taken = [], set()
    for e in SCENE_SETTINGS:
        if command not in e.commands:
            continue
        for d in describe(e.cls):
            if d["name"] in SHARED and any(o[1]["name"] == d["name"] for o in out):
                continue
            f = flag(d, e.attr, taken)
            out.append((e, d, f, "setting__" + f[2:].replace("-", "_")))
    return out


def add_flags(parser, command: str) -> None:
    """Add a flag per setting of ``command`` (default: the value stored in the .blend)."""
    items = command_fields(command)
    if not items:
        return
    g = parser.add_argument_group("settings (default: the values saved in the .blend, FaceLab > ... > Settings)")
    for e, d, f, dest in items:
        unit = UNIT_LABELS.get(d["unit"])
        bounds = ", ".join(f"{k.replace('_', ' ')} {d[k]:g}" for k in ("min", "max") if d.get(k) is not None)
        help_ = d["description"] + (f" [{unit}]" if unit and unit not in d["description"] else "") \
            + (f" ({bounds})" if bounds else "") + f"; new scenes: {d['default']!r}"
        help_ = help_.replace("%", "%%")
        if d["type"] is bool:
            g.add_argument(f, dest=dest, action=argparse.BooleanOptionalAction, default=None, help=help_)
        else:
            g.add_argument(f, dest=dest, default=None, type=d["type"], help=help_,
                           choices=[c[0] for c in d["choices"]] or None,
                           metavar=None if d["choices"] else {int: "N", float: "X"}.get(d["type"], "NAME"))


def check_value(d: dict, value, f: str) -> str | None:
    """Why ``value`` is outside the field's hard bounds (None when it is inside)."""
    if d.get("min") is not None and value < d["min"]:
        return f"{f} {value}: below the minimum {d['min']:g}; give a value from {d['min']:g}" + (
            f" to {d['max']:g}." if d.get("max") is not None else " up.")
    if d.get("max") is not None and value > d["max"]:
        return f"{f} {value}: above the maximum {d['max']:g}; give a value up to {d['max']:g}."
    return None


def apply_flags(args, scene, command: str) -> dict:
    """Write the settings flags given in ``args`` into ``scene`` (the saved .blend then records them).

    Returns
    -------
    dict
        ``{scene attribute: {field: value}}`` of every setting ``command`` uses, after the flags.

    Raises
    ------
    ValueError
        A value outside its bounds (the message names the flag and the range).
    """
    items = command_fields(command)
    for e, d, f, dest in items:
        v = getattr(args, dest, None)
        if v is None:
            continue
        why = check_value(d, v, f)
        if why:
            raise ValueError(why)
        if d["name"] in SHARED:
            setattr(scene.facelab, SHARED[d["name"]], v)
        else:
            ensure_initialized(scene, e)
            setattr(getattr(scene, e.attr), d["name"], v)
    return {e.attr: values(scene, e) for e in SCENE_SETTINGS if command in e.commands}


# --------------------------------------------------------------------------- readers of the other steps
def refine_settings(scene) -> RefineSettings:
    """The Refine Lips settings saved with the shot (FaceLab > Sketch & Refine > Settings; the fixed group
    from Setup)."""
    return scene_settings(scene, RefineSettings)


def scene_views(scene) -> list:
    """The scene's solve views as :class:`facelab_addon.blender.tracking.View` (unchecked: the pipelines
    name a view without camera or clip)."""
    return [tracking.View(v.camera, v.clip, mask=v.mask, sketch=v.sketch, name=v.camera.name if v.camera else "")
            for v in scene.facelab_solve.views]


def bind_settings(scene) -> BindSettings:
    """Bind Tracks' settings from ``scene.facelab_solve`` and FaceLab > Setup."""
    s = scene.facelab_solve
    return BindSettings(views=scene_views(scene), bundles=s.bundles, bundle_collection=s.bundle_collection,
                        fixed_group=scene.facelab.fixed_group)


def solve_settings(scene) -> SolveSettings:
    """Solve Performance's settings from ``scene.facelab_solve`` and FaceLab > Setup."""
    s = scene.facelab_solve
    return SolveSettings(
        views=scene_views(scene), frame_start=s.frame_start, frame_end=s.frame_end, bundles=s.bundles,
        bundle_collection=s.bundle_collection, fixed_group=scene.facelab.fixed_group, use_contours=s.use_contours,
        annotation_view=s.annotation_view, use_corrective=s.use_corrective, sliding=s.sliding,
        weight_min=s.weight_min, weight_max=s.weight_max, marker_weight=s.marker_weight,
        contour_weight=s.contour_weight, existing_animation=s.existing_animation, anchor_weight=s.anchor_weight,
        contour_damping=s.contour_damping, lip_passes=s.lip_passes, lip_line_weight=s.lip_line_weight,
        lip_damping=s.lip_damping)


def retarget_settings(scene) -> RetargetSettings:
    """Retarget's settings from ``scene.facelab_solve``; hand-set lip end points are read on every frame
    of the range (they may be keyed on the timeline)."""
    s = scene.facelab_solve
    up = lo = None
    f0, f1 = s.frame_start, s.frame_end
    if s.lip_sync and s.use_end_points and f1 >= f0:  # (an empty range is the pipeline's to report)
        frames = np.arange(f0, f1 + 1)
        up = scene_vector_values(scene, "facelab_solve.end_points_upper", s.end_points_upper, frames)
        lo = scene_vector_values(scene, "facelab_solve.end_points_lower", s.end_points_lower, frames)
    return RetargetSettings(
        frame_start=s.frame_start, frame_end=s.frame_end, correspondence=s.correspondence,
        creature_markers=s.creature_markers, lip_sync=s.lip_sync, lip_threshold=s.lip_threshold,
        end_points_upper=up, end_points_lower=lo, existing_animation=s.existing_animation, views=scene_views(scene))


def reconstruct_settings(scene, selected=(), *, frame_start: int | None = None, frame_end: int | None = None,
                         bind_frame: int = -2,
                         smooth: int = 0) -> ReconstructSettings:
    """Reconstruct's settings from ``scene.facelab_recon``.

    ``selected`` are the selected objects (the ``SELECTED`` bundle source);
    ``bind_frame`` -2 and ``smooth`` 0 take the panel's values.
    """
    r = scene.facelab_recon
    return ReconstructSettings(
        frame_start=frame_start, frame_end=frame_end, bind_frame=bind_frame if bind_frame != -2 else r.bind_frame,
        smooth=smooth or r.smooth, bundle_source=r.bundle_source, selected=tuple(selected),
        method=r.method, noise=r.noise,
        bundle_collection=r.bundle_collection, bundle_mesh=r.bundle_mesh, jaw_source=r.jaw_source,
        jaw_armature=r.jaw_armature, jaw_bone=r.jaw_bone, jaw_object=r.jaw_object, jaw_group=r.jaw_group)


def corrective_settings(scene, combinations: str = "", n_bundles: int = 100, drivers: bool = True):
    """Generate Correctives' settings: the panel's rig, and its combinations unless ``combinations`` is given."""
    r = scene.facelab_recon
    return CorrectiveSettings(rig_object=r.rig_object, combinations=combinations or r.combinations,
                              n_bundles=n_bundles, drivers=drivers)
