"""Add-on preferences: only the defaults of new scenes.

A shot's solver settings live in its scene (:mod:`.scene_settings`, saved with the .blend). The
preferences hold one group of defaults per settings class of
:data:`~facelab_addon.pipeline.shot_settings.SCENE_SETTINGS` (the same generated property groups), copied
into a scene the first time FaceLab works on it; *Save as Defaults* in a step's Settings sub-panel
copies a shot's values here. The built-in defaults come from the presets in ``assets/presets/``
(``sketch_refine.json``, ``regions.json``) through the settings dataclasses.
"""

import bpy
from bpy.props import PointerProperty

from ..pipeline.refine import REFINE_DEFAULTS
from ..pipeline import shot_settings
from ..pipeline.shot_settings import ADDON_ID
from . import scene_settings

#: Refine Lips solver settings of the preset ``assets/presets/sketch_refine.json``.
DEFAULTS = dict(REFINE_DEFAULTS)

_CLASSES: list = []


def _draw(self, context):
    col = self.layout.column()
    col.label(text="Defaults for new scenes (a shot's own settings are in the FaceLab tab, saved with it)",
              icon="INFO")
    for e in shot_settings.SCENE_SETTINGS:
        box = col.box()
        box.label(text=e.cls.__name__.removesuffix("Settings"))
        grp = getattr(self, e.attr)
        for d in shot_settings.fields(e):
            box.prop(grp, d["name"])


def make_preferences_class():
    """The ``AddonPreferences`` class: a pointer to each registered settings group."""
    ann = {e.attr: PointerProperty(type=scene_settings.group_class(e.attr)) for e in shot_settings.SCENE_SETTINGS}
    return type("FACELAB_AP_preferences", (bpy.types.AddonPreferences,),
                {"bl_idname": ADDON_ID, "__annotations__": ann, "draw": _draw,
                 "__doc__": "FaceLab's defaults for new scenes"})


def register():
    cls = make_preferences_class()
    bpy.utils.register_class(cls)
    _CLASSES.append(cls)


def unregister():
    while _CLASSES:
        bpy.utils.unregister_class(_CLASSES.pop())
