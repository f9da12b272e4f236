"""Blender UI: properties, preferences, operators and panels (registered in this order)."""

from . import ops, panel, prefs, props

modules = (props, prefs, ops, panel)


def register():
    for m in modules:
        m.register()


def unregister():
    for m in reversed(modules):
        m.unregister()
