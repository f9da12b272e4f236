"""Adapters between Blender data and arrays: meshes, cameras, Grease Pencil and annotation
strokes, masks, Movie Clip tracking, bundles, shape keys and actions, captured caches and bakes.

Each module translates one kind of Blender data to the NumPy arrays :mod:`facelab_addon.core`
works on, or writes arrays back; none of them solves anything.
"""
