"""The add-on registers cleanly; panels exist; every operator's poll explains itself."""

import pytest

import bpy

import facelab_addon

pytestmark = pytest.mark.blender

OPERATORS = ["new_lip_sketch", "refine_lips", "auto_regions", "mark_training_frame", "remove_training_frame",
             "jump_training_frame", "propagate", "bake", "reconstruct_from_bundles"]
PANELS = ["FACELAB_PT_main", "FACELAB_PT_setup", "FACELAB_PT_sketch", "FACELAB_PT_propagate", "FACELAB_PT_reconstruct",
          "FACELAB_PT_bake"]


def test_register_unregister_register():
    facelab_addon.register()
    try:
        for p in PANELS:
            assert hasattr(bpy.types, p), p
        for op in OPERATORS:
            assert hasattr(bpy.ops.facelab, op)
        assert hasattr(bpy.types.Scene, "facelab") and hasattr(bpy.types.Object, "facelab")
        # an empty scene: every operator refuses with a reason instead of failing
        bpy.ops.wm.read_factory_settings(use_empty=True)
        for op in OPERATORS:
            fn = getattr(bpy.ops.facelab, op)
            assert not fn.poll(), op
            with pytest.raises(RuntimeError, match=r"(?i)select|camera|training"):
                fn()
    finally:
        facelab_addon.unregister()
    assert not hasattr(bpy.types, "FACELAB_PT_main")
    facelab_addon.register()  # and again, as Blender does on reload
    facelab_addon.unregister()
