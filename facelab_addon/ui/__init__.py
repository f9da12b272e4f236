"""Blender UI: properties, preferences, operators and panels (registered in this order)."""

from . import ops, ops_assets, ops_propagate, ops_reconstruct, ops_solve, panel, panel_solve, prefs, props, props_solve

modules = (props, props_solve, prefs, ops, ops_assets, ops_propagate, ops_reconstruct, ops_solve, panel_solve, panel)


def register():
    for m in modules:
        m.register()


def unregister():
    for m in reversed(modules):
        m.unregister()
