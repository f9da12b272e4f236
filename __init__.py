"""Blender extension entry point (the manifest sits beside this file).

The add-on itself is the ``facelab_addon`` package; ``facelab_addon.core`` is
importable without Blender for pipeline scripts.
"""

from .facelab_addon import register, unregister  # noqa: F401
