"""Blender UI: properties, preferences, operators and panels (registered in this order)."""

from . import ops, ops_propagate, ops_reconstruct, panel, prefs, props

modules = (props, prefs, ops, ops_propagate, ops_reconstruct, panel)


def register():
    for m in modules:
        m.register()


def unregister():
    for m in reversed(modules):
        m.unregister()
