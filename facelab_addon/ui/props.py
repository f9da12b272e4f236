"""FaceLab scene and object properties."""

import bpy
from bpy.props import CollectionProperty, IntProperty, PointerProperty, StringProperty

from ..names import FIXED_GROUP


def _is_mesh(self, obj):
    return obj.type == "MESH"


class FACELAB_PG_training_frame(bpy.types.PropertyGroup):
    """A corrected frame: training data for Propagate"""

    frame: IntProperty(name="Frame", description="The corrected frame")
    shape_key: StringProperty(name="Shape Key", description="Corrective shape key holding the correction")
    source: StringProperty(name="Source", default="sketch",
                           description="'sketch' (Refine Lips), 'sculpt' (Add Corrected Frame) or 'marked' "
                                       "(sculpted in place, Mark Training Frame)")


class FACELAB_PG_object(bpy.types.PropertyGroup):
    training_frames: CollectionProperty(type=FACELAB_PG_training_frame)
    active_training_index: IntProperty(default=0)


class FACELAB_PG_scene(bpy.types.PropertyGroup):
    face: PointerProperty(
        name="Face",
        type=bpy.types.Object,
        poll=_is_mesh,
        description="The captured face mesh to correct (default: the active mesh)",
    )
    sketch: PointerProperty(
        name="Sketch",
        type=bpy.types.Object,
        description="Grease Pencil object with 'Upper lip' and 'Lower lip' layers (default: found automatically)",
    )
    fixed_group: StringProperty(
        name="Fixed Group",
        default=FIXED_GROUP,
        description="Vertex group of hidden vertices that must not move (inner mouth, teeth, back of the head); "
        "without it, separate mesh parts are fixed",
    )


classes = (FACELAB_PG_training_frame, FACELAB_PG_object, FACELAB_PG_scene)


def register():
    for c in classes:
        bpy.utils.register_class(c)
    bpy.types.Scene.facelab = PointerProperty(type=FACELAB_PG_scene)
    bpy.types.Object.facelab = PointerProperty(type=FACELAB_PG_object)


def unregister():
    del bpy.types.Object.facelab
    del bpy.types.Scene.facelab
    for c in reversed(classes):
        bpy.utils.unregister_class(c)
