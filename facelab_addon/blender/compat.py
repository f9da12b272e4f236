"""The Blender API differences between the supported versions (4.5 LTS to 5.3), in one place.

Features call these helpers instead of checking ``bpy.app.version``. Each helper asks Blender
whether the newer API is there (an attribute, a data collection, a deprecated property) and falls
back to the 4.5 spelling otherwise.

========================  ===============================  ===================================
What                      Blender 4.5 LTS                  Blender 5.0 and newer
========================  ===============================  ===================================
Action channelbags        ``strip.channelbag(slot,         ``anim_utils.action_ensure_``
                          ensure=True)``                   ``channelbag_for_slot``
Grease Pencil (v3) data   ``bpy.data.grease_pencils_v3``,  ``bpy.data.grease_pencils``,
                          ``bpy.types.GreasePencilv3``     ``bpy.types.GreasePencil``
Scene annotation          ``scene.grease_pencil``          ``scene.annotation``
Annotation data           ``bpy.data.grease_pencils``      ``bpy.data.annotations``
Node trees                ``use_nodes = True`` needed      always on (``use_nodes`` deprecated)
GP material fill          ``show_fill``                    fill opacity (``show_fill`` unused)
========================  ===============================  ===================================

The Grease Pencil object type is ``"GREASEPENCIL"`` (``GREASE_PENCIL_TYPE``) in all of them.
"""

from __future__ import annotations

import bpy

GREASE_PENCIL_TYPE = "GREASEPENCIL"
"""``Object.type`` of a Grease Pencil (v3) object in every supported Blender."""


def _property_in_use(struct, name: str) -> bool:
    """Whether RNA ``struct`` has property ``name`` and Blender has not deprecated it."""
    prop = struct.bl_rna.properties.get(name)
    return prop is not None and not getattr(prop, "is_deprecated", False)


# --------------------------------------------------------------------------- animation
def action_channelbag(action, slot, create: bool = False):
    """The channelbag of ``slot`` in ``action`` (``bpy.types.ActionChannelbag``), or None.

    Parameters
    ----------
    action : bpy.types.Action or None
    slot : bpy.types.ActionSlot or None
    create : bool
        Make the layer, keyframe strip and channelbag when missing (``action`` and ``slot`` must
        then be given).
    """
    from bpy_extras import anim_utils

    if not create:
        if action is None or slot is None:
            return None
        return anim_utils.action_get_channelbag_for_slot(action, slot)
    ensure = getattr(anim_utils, "action_ensure_channelbag_for_slot", None)
    if ensure is not None:
        return ensure(action, slot)
    layer = action.layers[0] if len(action.layers) else action.layers.new("Layer")
    strip = layer.strips[0] if len(layer.strips) else layer.strips.new(type="KEYFRAME")
    return strip.channelbag(slot, ensure=True)


def anim_fcurve(anim_data, data_path: str):
    """The F-curve animating ``data_path`` in ``anim_data``'s action, or None: in the channelbag of the
    assigned slot (layered actions, Blender 4.4+), else ``Action.fcurves`` (removed in 5.0)."""
    action = anim_data.action
    slot = getattr(anim_data, "action_slot", None)
    try:
        cb = action_channelbag(action, slot)
        if cb is not None:
            return cb.fcurves.find(data_path)
    except Exception:
        pass
    fcurves = getattr(action, "fcurves", None)  # Blender < 5.0
    return fcurves.find(data_path) if fcurves is not None else None


def anim_data_channelbag(anim_data, create: bool = False):
    """The channelbag of the action slot assigned in ``anim_data`` (``bpy.types.AnimData``), or None.

    With ``create`` a slot for the owning ID is made and assigned when none is, and the channelbag
    is created when missing (``anim_data.action`` must be set).
    """
    action = anim_data.action
    if action is None:
        return None
    slot = getattr(anim_data, "action_slot", None)
    if slot is None:
        if not create:
            return None
        idd = anim_data.id_data
        slot = action.slots.new(id_type=idd.id_type, name=idd.name)
        anim_data.action_slot = slot
    return action_channelbag(action, slot, create=create)


# --------------------------------------------------------------------------- grease pencil
def grease_pencil_data():
    """``bpy.data``'s collection of Grease Pencil (v3) data blocks (``.new(name)``, ``.remove``)."""
    v3 = getattr(bpy.data, "grease_pencils_v3", None)  # an empty collection is falsy: compare with None
    return v3 if v3 is not None else bpy.data.grease_pencils


def grease_pencil_struct():
    """``bpy.types`` class of Grease Pencil (v3) data (for ``PointerProperty`` types, ``isinstance``)."""
    return getattr(bpy.types, "GreasePencilv3", None) or bpy.types.GreasePencil


def set_gp_material_fill(style, show: bool) -> None:
    """Show or hide the fill of a Grease Pencil material (``style``: ``Material.grease_pencil``).

    Hiding also makes the fill colour transparent, which is what hides it where ``show_fill`` is
    deprecated (unused).
    """
    if _property_in_use(style, "show_fill"):
        style.show_fill = bool(show)
    if not show:
        style.fill_color = (*style.fill_color[:3], 0.0)


def gp_material_fill_shown(style) -> bool:
    """Whether a Grease Pencil material (``Material.grease_pencil``) draws its fill."""
    shown = bool(style.is_fill_visible)
    if _property_in_use(style, "show_fill"):
        shown = shown and bool(style.show_fill)
    return shown


# --------------------------------------------------------------------------- annotations
def _annotation_property() -> str:
    props = bpy.types.Scene.bl_rna.properties
    return "annotation" if "annotation" in props else "grease_pencil"


def scene_annotation(scene):
    """The scene's annotation data (drawn with the Annotate tool), or None."""
    return getattr(scene, _annotation_property(), None)


def set_scene_annotation(scene, annotation) -> None:
    """Make ``annotation`` (from ``annotation_data().new``) the scene's annotation."""
    setattr(scene, _annotation_property(), annotation)


def annotation_data():
    """``bpy.data``'s collection of annotation data blocks (``.new(name)``)."""
    ann = getattr(bpy.data, "annotations", None)
    return ann if ann is not None else bpy.data.grease_pencils


# --------------------------------------------------------------------------- shading nodes
def node_tree(idblock):
    """The shader node tree of a material or world, switching nodes on where that is still needed."""
    if _property_in_use(idblock, "use_nodes") and not idblock.use_nodes:
        idblock.use_nodes = True
    return idblock.node_tree
