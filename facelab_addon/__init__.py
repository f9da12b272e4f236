"""FaceLab: clean up facial performance capture in Blender.

The package is importable without Blender: ``facelab_addon.core`` is plain
NumPy/SciPy. Blender-specific modules are imported only by ``register()``.
"""

__version__ = "0.1.0"


def register():
    from . import ui

    ui.register()


def unregister():
    from . import ui

    ui.unregister()
