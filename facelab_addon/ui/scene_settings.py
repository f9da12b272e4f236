"""Pipeline settings stored with the shot, on the Blender side: the scene properties and panel rows
generated from the settings dataclasses.

Every settings class of :data:`facelab_addon.pipeline.shot_settings.SCENE_SETTINGS` becomes, without
further code:

* a generated ``PropertyGroup`` on the scene (``scene.<attr>``), saved in the .blend;
* a row of the step's *Settings* sub-panel, or of its closed *Advanced* one (:data:`Entry` ``everyday``,
  :func:`draw_settings`);
* a default for new scenes in the add-on preferences (:mod:`.prefs`), which hold nothing else.

The registry, the CLI flags and the readers that turn the scene's values into a pipeline's settings
live in :mod:`facelab_addon.pipeline.shot_settings` (the CLI uses them without the UI). Editing any
value marks the scene's group as the shot's own.
"""

from __future__ import annotations

import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, PointerProperty, StringProperty

from ..pipeline import shot_settings
from ..pipeline.shot_settings import INITIALIZED, Entry, ensure_initialized, fields, label, panel_fields
from .common import face_object


_GROUPS: dict = {}  # attr -> generated PropertyGroup class (registered)
_PANELS: list = []  # generated sub-panels (registered)


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


@bpy.app.handlers.persistent
def _on_load(_dummy=None):
    for scene in bpy.data.scenes:
        if scene.library is None:  # a linked scene is not ours to fill
            for e in shot_settings.SCENE_SETTINGS:
                ensure_initialized(scene, e)


# --------------------------------------------------------------------------- panel
def draw_settings(layout, context, entry: Entry, advanced: bool = False) -> None:
    """The rows of ``entry``'s everyday fields, or its ``advanced`` ones (a ``*_group`` text field is a
    vertex-group picker on the face), then Reset / Save as Defaults (under the everyday ones)."""
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
    for e in shot_settings.SCENE_SETTINGS:
        if e.panel is None or hasattr(bpy.types, e.panel):
            for advanced in (False, True) if panel_fields(e, True) else (False,):
                p = make_panel(e, advanced)
                bpy.utils.register_class(p)
                _PANELS.append(p)


def unregister_panels() -> None:
    while _PANELS:
        bpy.utils.unregister_class(_PANELS.pop())


# --------------------------------------------------------------------------- register
def register() -> None:
    for e in shot_settings.SCENE_SETTINGS:
        cls = make_group(e)
        bpy.utils.register_class(cls)
        _GROUPS[e.attr] = cls
        setattr(bpy.types.Scene, e.attr, PointerProperty(type=cls, name=e.cls.__name__))
    if _on_load not in bpy.app.handlers.load_post:
        bpy.app.handlers.load_post.append(_on_load)


def unregister() -> None:
    if _on_load in bpy.app.handlers.load_post:
        bpy.app.handlers.load_post.remove(_on_load)
    for e in reversed(shot_settings.SCENE_SETTINGS):
        if e.attr in _GROUPS:
            delattr(bpy.types.Scene, e.attr)
            bpy.utils.unregister_class(_GROUPS.pop(e.attr))
