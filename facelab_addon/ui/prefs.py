"""Add-on preferences: solver weights and iterations (Dinev et al. 2018 §5 defaults).

The defaults come from the presets in ``assets/presets/`` (:mod:`facelab_addon.assets`):
``sketch_refine.json`` for the Refine Lips solver, ``regions.json`` for the Auto Regions band widths.
A missing or broken preset file raises :class:`facelab_addon.assets.AssetError` naming the file.
"""

import bpy
from bpy.props import FloatProperty, IntProperty

from ..pipeline.refine import REFINE_DEFAULTS
from ..pipeline.regions import REGION_DEFAULTS  # noqa: F401  (the Auto Regions band widths, see pipeline.regions)

# The add-on's module name: "facelab_addon" from a checkout, "bl_ext.<repo>.facelab" as an
# extension (whose root __init__.py imports the facelab_addon sub-package).
_parts = __package__.split(".")
ADDON_ID = ".".join(_parts[: _parts.index("facelab_addon")]) or "facelab_addon"

#: Refine Lips solver settings (keyword arguments of ``core.lips.sketch.refine_lips``), from the preset.
DEFAULTS = dict(REFINE_DEFAULTS)


class FACELAB_AP_preferences(bpy.types.AddonPreferences):
    bl_idname = ADDON_ID

    iterations: IntProperty(
        name="Iterations", default=DEFAULTS["iterations"], min=1, max=100,
        description="Solve / re-match iterations of the sketch refinement (paper: 5)",
    )
    lambda_pos: FloatProperty(
        name="Position Weight", default=DEFAULTS["lambda_pos"], min=0.0, soft_max=10.0,
        description="λpos: how strongly vertices keep their captured position (paper: 0.1; fixed vertices use 1)",
    )
    lambda_reg: FloatProperty(
        name="Rigidity Weight", default=DEFAULTS["lambda_reg"], min=0.0, soft_max=100.0,
        description="λreg: preservation of the local shape (Laplacian coordinates) (paper: 3)",
    )
    lambda_silh: FloatProperty(
        name="Silhouette Weight", default=DEFAULTS["lambda_silh"], min=0.0, soft_max=100.0,
        description="λsilh: pull of the sketched contours (paper: 1)",
    )

    def draw(self, context):
        col = self.layout.column()
        col.label(text="Sketch refinement (Dinev et al. 2018, Eq. 1)")
        for p in ("iterations", "lambda_pos", "lambda_reg", "lambda_silh"):
            col.prop(self, p)


def get_prefs(context=None) -> dict:
    """The solver settings: the add-on preferences when enabled as an add-on, else the defaults."""
    context = context or bpy.context
    addon = context.preferences.addons.get(ADDON_ID)
    if addon is None or addon.preferences is None:
        return dict(DEFAULTS)
    p = addon.preferences
    return {k: getattr(p, k) for k in DEFAULTS}


classes = (FACELAB_AP_preferences,)


register, unregister = bpy.utils.register_classes_factory(classes)
