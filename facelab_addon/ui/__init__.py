"""Blender UI: properties, preferences, operators and panels (registered in this order)."""

from . import (
    ops,
    ops_assets,
    ops_live,
    ops_propagate,
    ops_reconstruct,
    ops_review,
    ops_solve,
    panel,
    panel_solve,
    prefs,
    props,
    props_solve,
    scene_settings,
)

modules = (props, props_solve, scene_settings, prefs, ops, ops_live, ops_assets, ops_propagate, ops_reconstruct, ops_solve,
           ops_review, panel_solve, panel)


def register():
    for m in modules:
        m.register()


def unregister():
    for m in reversed(modules):
        m.unregister()
