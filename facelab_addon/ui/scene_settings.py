"""Pipeline settings stored with the shot: scene properties, panel rows and CLI flags generated from
the settings dataclasses.

Every field a pipeline's settings dataclass declares with
:func:`facelab_addon.pipeline.settings.setting` becomes, without further code:

* a property of a generated ``PropertyGroup`` on the scene (``scene.<attr>``), saved in the .blend;
* a row of the step's *Settings* sub-panel, or of its closed *Advanced* one (:data:`Entry` ``everyday``,
  :func:`draw_settings`);
* a flag of the CLI commands that run the step (:func:`add_flags`, :func:`apply_flags`);
* a default for new scenes in the add-on preferences (:mod:`.prefs`), which hold nothing else.

Adding a settings class is one line of :data:`SCENE_SETTINGS`::

    Entry("facelab_store", StorageSettings, "FACELAB_PT_propagate", ("propagate",)),

Fields named in :data:`SHARED` are stored once, in FaceLab > Setup (``scene.facelab``), for every step.
A scene's group is filled from the preferences' defaults the first time a FaceLab operator, the CLI
or a file load touches it (:func:`ensure_initialized`); editing any value marks it as the shot's own.
"""

from __future__ import annotations

import argparse
from typing import NamedTuple

import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, PointerProperty, StringProperty

from ..names import STORE_SETTINGS_ATTR
from ..pipeline.bake import BakeSettings
from ..pipeline.correctives import StorageSettings
from ..pipeline.propagate import PropagateSettings
from ..pipeline.refine import RefineSettings
from ..pipeline.regions import RegionSettings
from ..pipeline.settings import describe


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

_GROUPS: dict = {}  # attr -> generated PropertyGroup class (registered)
_PANELS: list = []  # generated sub-panels (registered)


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


def _mark(self, context):
    self[INITIALIZED] = True


def make_property(d: dict):
    """The ``bpy.props`` definition of one described field (bool, int, float, str, or a choice of str)."""
    kw = dict(name=label(d), description=d["description"], default=d["default"], update=_mark)
    bounds = {k: d[k] for k in ("min", "max", "soft_min", "soft_max") if d.get(k) is not None}
    t = d["type"]
    if t is bool:
        return BoolProperty(**kw)
    if t is int:
        return IntProperty(**kw, **{k: int(v) for k, v in bounds.items()})
    if t is float:
        return FloatProperty(**kw, **bounds, precision=3)
    if t is str and d["choices"]:
        return EnumProperty(items=[tuple(c) for c in d["choices"]], **kw)
    if t is str:
        return StringProperty(**kw)
    raise TypeError(f"setting {d['name']!r}: a {t.__name__} cannot be a scene property; use bool, int, float or str")


def make_group(entry: Entry):
    """A ``PropertyGroup`` class with one property per field of ``entry`` (not registered)."""
    ann = {d["name"]: make_property(d) for d in fields(entry)}
    ann[INITIALIZED] = BoolProperty(default=False, options={"HIDDEN"})
    name = "FACELAB_PG_" + entry.attr
    doc = (entry.cls.__doc__ or entry.cls.__name__).split("\n")[0]
    return type(name, (bpy.types.PropertyGroup,), {"__annotations__": ann, "__doc__": doc})


def group_class(attr: str):
    """The registered property group of ``attr`` (None before :func:`register`)."""
    return _GROUPS.get(attr)


def entry_for(cls_or_attr) -> Entry | None:
    """The :data:`SCENE_SETTINGS` entry of a settings class or a scene attribute."""
    for e in SCENE_SETTINGS:
        if e.cls is cls_or_attr or e.attr == cls_or_attr:
            return e
    return None


# --------------------------------------------------------------------------- preferences -> scene
def preference_defaults(entry: Entry, context=None) -> dict:
    """``{field: value}`` for a new scene: the add-on preferences' defaults when enabled, else the dataclass's."""
    from .prefs import preferences

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


@bpy.app.handlers.persistent
def _on_load(_dummy=None):
    for scene in bpy.data.scenes:
        if scene.library is None:  # a linked scene is not ours to fill
            for e in SCENE_SETTINGS:
                ensure_initialized(scene, e)


# --------------------------------------------------------------------------- panel
def draw_settings(layout, context, entry: Entry, advanced: bool = False) -> None:
    """The rows of ``entry``'s everyday fields, or its ``advanced`` ones (a ``*_group`` text field is a
    vertex-group picker on the face), then Reset / Save as Defaults (under the everyday ones)."""
    from .ops import face_object

    grp = getattr(context.scene, entry.attr, None)
    col = layout.column()
    if grp is None:
        col.label(text=f"{entry.attr} is not registered", icon="ERROR")
        return
    face = face_object(context)
    for d in panel_fields(entry, advanced):
        if d["type"] is str and not d["choices"] and d["name"].endswith("_group") and face is not None:
            col.prop_search(grp, d["name"], face, "vertex_groups")
        else:
            col.prop(grp, d["name"])
    if advanced:
        return
    row = col.row(align=True)
    row.operator("facelab.reset_settings", text="Reset", icon="LOOP_BACK").target = entry.attr
    row.operator("facelab.save_settings_defaults", text="Save as Defaults", icon="PREFERENCES").target = entry.attr


def make_panel(entry: Entry, advanced: bool = False):
    """A closed sub-panel under ``entry.panel`` (titled ``entry.label``) drawing ``entry``'s everyday fields,
    or (``advanced``) its closed *Advanced* sub-panel with the other fields."""
    idname = f"FACELAB_PT_{entry.attr}" + ("_advanced" if advanced else "")
    parent = f"FACELAB_PT_{entry.attr}" if advanced else (entry.panel or "FACELAB_PT_main")

    def draw(self, context):
        draw_settings(self.layout, context, entry, advanced)

    return type(idname, (bpy.types.Panel,), dict(
        bl_space_type="VIEW_3D", bl_region_type="UI", bl_category="FaceLab", bl_parent_id=parent,
        bl_label="Advanced" if advanced else entry.label, bl_options={"DEFAULT_CLOSED"},
        bl_idname=idname, draw=draw,
        __doc__=("Solver settings: change them when the everyday ones do not give the result" if advanced
                 else f"{entry.label}, saved with the shot")))


def register_panels() -> None:
    """Register the sub-panels (after their parent panels)."""
    for e in SCENE_SETTINGS:
        if e.panel is None or hasattr(bpy.types, e.panel):
            for advanced in (False, True) if panel_fields(e, True) else (False,):
                p = make_panel(e, advanced)
                bpy.utils.register_class(p)
                _PANELS.append(p)


def unregister_panels() -> None:
    while _PANELS:
        bpy.utils.unregister_class(_PANELS.pop())


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


# --------------------------------------------------------------------------- register
def register() -> None:
    for e in SCENE_SETTINGS:
        cls = make_group(e)
        bpy.utils.register_class(cls)
        _GROUPS[e.attr] = cls
        setattr(bpy.types.Scene, e.attr, PointerProperty(type=cls, name=e.cls.__name__))
    if _on_load not in bpy.app.handlers.load_post:
        bpy.app.handlers.load_post.append(_on_load)


def unregister() -> None:
    if _on_load in bpy.app.handlers.load_post:
        bpy.app.handlers.load_post.remove(_on_load)
    for e in reversed(SCENE_SETTINGS):
        if e.attr in _GROUPS:
            delattr(bpy.types.Scene, e.attr)
            bpy.utils.unregister_class(_GROUPS.pop(e.attr))
