"""Blender extension entry point (the manifest sits beside this file).

The add-on itself is the ``facelab_addon`` package; ``facelab_addon.core`` is
importable without Blender for pipeline scripts.
"""

# Blender imports this file as a package (``bl_ext.<repo>.facelab``). pytest may import it as a
# plain module when the checkout's folder name is not a valid package name (``wt-pack``,
# ``facelab-main``): there is no parent package then, and nothing to register.
if __package__:
    from .facelab_addon import register, unregister  # noqa: F401
