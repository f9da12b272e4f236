"""Create Blender data from arrays: mesh objects, camera backplates.

Used by the demo, the tests and pipeline scripts that bring captured data in.
"""

from __future__ import annotations

import bpy
import numpy as np

from . import compat

__all__ = ["new_mesh_object", "set_backplate"]


def new_mesh_object(name: str, vertices, faces=None, *, poly_verts=None, poly_offsets=None, collection=None):
    """A new mesh object from arrays (vertex order kept).

    Parameters
    ----------
    name : str
    vertices : (V,3) float
        Object-local positions, scene units.
    faces : (F,k) int, optional
        Faces with ``k`` corners each, or
    poly_verts, poly_offsets : (C,), (P+1,) int, optional
        Concatenated polygon corners and polygon starts (mixed quads/tris).
    collection : bpy.types.Collection, optional
        Default: the scene's master collection.
    """
    V = np.asarray(vertices, dtype=np.float64)
    if faces is not None:
        Fa = np.asarray(faces, dtype=np.int64)
        poly_verts = Fa.ravel()
        poly_offsets = np.arange(0, len(poly_verts) + 1, Fa.shape[1])
    pv = np.asarray(poly_verts, dtype=np.int32)
    off = np.asarray(poly_offsets, dtype=np.int64)
    me = bpy.data.meshes.new(name)
    me.vertices.add(len(V))
    me.vertices.foreach_set("co", V.astype(np.float32).ravel())
    me.loops.add(len(pv))
    me.loops.foreach_set("vertex_index", pv)
    me.polygons.add(len(off) - 1)
    me.polygons.foreach_set("loop_start", off[:-1].astype(np.int32))
    me.update(calc_edges=True)
    me.validate(verbose=False)
    ob = bpy.data.objects.new(name, me)
    (collection or bpy.context.scene.collection).objects.link(ob)
    return ob


def set_backplate(cam_obj, image_path: str, alpha: float = 1.0):
    """Show ``image_path`` behind the scene in camera view (the capture's plate)."""
    img = bpy.data.images.load(str(image_path), check_existing=True)
    cam = cam_obj.data
    cam.show_background_images = True
    bg = cam.background_images[0] if len(cam.background_images) else cam.background_images.new()
    bg.image = img
    bg.alpha = alpha
    bg.display_depth = "BACK"
    bg.frame_method = "FIT"
    return img


def add_studio_lights(scene, *, background=(0.05, 0.05, 0.06)):
    """A key and a fill sun lighting a face that looks along +Y-up/+Z-forward, and a dark world."""
    for name, rot, energy in (("Key", (-0.55, 0.35, 0.0), 3.5), ("Fill", (-0.15, -0.7, 0.0), 1.0)):
        light = bpy.data.objects.new(name, bpy.data.lights.new(name, "SUN"))
        light.data.energy = energy
        light.rotation_euler = rot
        scene.collection.objects.link(light)
    world = bpy.data.worlds.new("World")
    compat.node_tree(world).nodes["Background"].inputs["Color"].default_value = (*background, 1)
    scene.world = world
