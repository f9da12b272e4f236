"""Pipelines: one per workflow step (refine, propagate, bake, solve, retarget, reconstruct).

A pipeline reads the scene through the adapters in :mod:`facelab_addon.blender`, runs the
solvers in :mod:`facelab_addon.core`, writes the result through the adapters and returns a
typed result (a dataclass saying what it did, what it skipped and why). The operators in
:mod:`facelab_addon.ui` and the CLI in :mod:`facelab_addon.cli` both call these functions;
neither holds results in module-level state.
"""
