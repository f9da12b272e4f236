"""The shipped sample shot (``assets/sample/``) as arrays, and built into a Blender scene.

The sample is stored version-independently (a ``.blend`` saved by one Blender does not open in an
older one): ``assets/sample/face.npz`` holds a reduced ICT-FaceKit face (its ``M_Face`` part,
un-subdivided once: about 4,700 vertices, metres, y up, looking along +z), a 48-frame performance
(expression shape keys and their per-frame weights), the capture's inner-lip error as one more
shape key with its per-frame strength, and the camera; ``assets/sample/plate/plate_0001.jpg``...
is the footage, rendered from the face *without* the capture error (what the actor really did), so
the artist's sketch over the plate tells FaceLab how the lips should look.
``scripts/make_sample.py`` regenerates it from the ICT-FaceKit checkout.

* :func:`read_sample` -- the arrays, checked (:class:`SampleData`);
* :func:`build_sample` -- the face (shape keys keyed on the frames), the camera and lights in a
  scene; the plate is loaded by :mod:`facelab_addon.blender.plate`.
"""

from __future__ import annotations

from dataclasses import dataclass

import bpy
import numpy as np

from ..assets import AssetError, asset_path
from ..core.capture.camera import Camera
from .camera import new_camera_object
from .scene import add_studio_lights, new_mesh_object
from .shapekeys import key_property_bulk

__all__ = ["SAMPLE_FILE", "PLATE_DIR", "ERROR_KEY", "PERFORMANCE_ACTION", "LIP_TINT_ATTRIBUTE", "SampleData", "read_sample",
           "build_sample"]

#: The arrays of the sample, below ``assets/``.
SAMPLE_FILE = ("sample", "face.npz")
#: The plate frames (``plate_0001.jpg``...), below ``assets/``.
PLATE_DIR = ("sample", "plate")
#: The shape key holding the capture's inner-lip error (part of the capture: not a FaceLab key).
ERROR_KEY = "Capture lip error"
#: The action that keys the performance's shape-key values.
PERFORMANCE_ACTION = "Sample performance"

_KEYS = {"vertices": (np.floating, 2), "poly_verts": (np.integer, 1), "poly_offsets": (np.integer, 1),
         "expression_names": (np.str_, 1), "expression_deltas": (np.floating, 3), "weights": (np.floating, 2),
         "capture_error": (np.floating, 2), "capture_error_weights": (np.floating, 1), "frame_start": (np.integer, 0),
         "fps": (np.integer, 0), "K": (np.floating, 2), "R": (np.floating, 2), "t": (np.floating, 1),
         "image_size": (np.integer, 1), "inner_lip_loop": (np.integer, 1), "source_vertices": (np.integer, 1)}


@dataclass
class SampleData:
    """The sample shot.

    Attributes
    ----------
    vertices : (V,3) float64
        Rest pose, metres (object-local = world: the face object sits at the origin).
    poly_verts, poly_offsets : (C,), (P+1,) int64
        Polygons (mostly quads) as concatenated corners and polygon starts.
    expression_names : list of str
        The performance's shape keys (ICT-FaceKit expression names).
    expression_deltas : (K,V,3) float64
        Their offsets from the rest pose, metres.
    weights : (T,K) float64
        Key values per frame.
    capture_error : (V,3) float64
        The capture's inner-lip error at full strength, metres (the lips fail to close).
    capture_error_weights : (T,) float64
        Its strength per frame (the captured frame ``t`` = truth + ``capture_error_weights[t] *
        capture_error``).
    frames : (T,) int64
        Scene frames of the performance.
    fps : int
    camera : Camera
        The plate's camera (pixels, OpenCV convention).
    inner_lip_loop : (L,) int64
        The inner-lip contact loop of the rest pose (what Auto Regions finds), for checks.
    source_vertices : (V,) int64
        The ICT-FaceKit vertex each vertex is (provenance: the reduced face keeps upstream vertices).
    """

    vertices: np.ndarray
    poly_verts: np.ndarray
    poly_offsets: np.ndarray
    expression_names: list
    expression_deltas: np.ndarray
    weights: np.ndarray
    capture_error: np.ndarray
    capture_error_weights: np.ndarray
    frames: np.ndarray
    fps: int
    camera: Camera
    inner_lip_loop: np.ndarray
    source_vertices: np.ndarray

    def truth(self) -> np.ndarray:
        """(T,V,3) float64: what the actor did (the plate), metres."""
        return self.vertices[None] + np.einsum("tk,kvd->tvd", self.weights, self.expression_deltas)

    def captured(self) -> np.ndarray:
        """(T,V,3) float64: the capture (truth + its inner-lip error), metres."""
        return self.truth() + self.capture_error_weights[:, None, None] * self.capture_error[None]


def read_sample(path=None) -> SampleData:
    """Read and check the sample's arrays.

    Parameters
    ----------
    path : str or Path, optional
        Default: ``assets/sample/face.npz``.

    Returns
    -------
    SampleData

    Raises
    ------
    AssetError
        The file is missing, unreadable, or an array is missing or has the wrong type or shape.
    """
    path = asset_path(*SAMPLE_FILE) if path is None else path
    fix = "reinstall the FaceLab extension, or regenerate it with python scripts/make_sample.py"
    try:
        with np.load(path, allow_pickle=False) as z:
            raw = {k: z[k] for k in z.files}
    except (OSError, ValueError) as e:
        raise AssetError(f"Cannot read the sample {path} ({e}); {fix}.") from None
    for key, (kind, ndim) in _KEYS.items():
        a = raw.get(key)
        if a is None or not np.issubdtype(a.dtype, kind) or a.ndim != ndim:
            raise AssetError(f"The sample {path} has no valid {key!r} array; {fix}.")
    V = raw["vertices"].astype(np.float64)
    n, K, T = len(V), len(raw["expression_names"]), len(raw["weights"])
    shapes = {"vertices": (n, 3), "expression_deltas": (K, n, 3), "weights": (T, K), "capture_error": (n, 3),
              "capture_error_weights": (T,), "K": (3, 3), "R": (3, 3), "t": (3,), "image_size": (2,),
              "source_vertices": (n,)}
    bad = [k for k, s in shapes.items() if raw[k].shape != s]
    pv, po = raw["poly_verts"].astype(np.int64), raw["poly_offsets"].astype(np.int64)
    if bad or T == 0 or len(po) < 2 or po[0] != 0 or po[-1] != len(pv) or (pv < 0).any() or (pv >= n).any():
        raise AssetError(f"The sample {path} is inconsistent ({', '.join(bad) or 'polygons'}); {fix}.")
    W, H = (int(v) for v in raw["image_size"])
    f0 = int(raw["frame_start"])
    return SampleData(
        vertices=V, poly_verts=pv, poly_offsets=po, expression_names=[str(s) for s in raw["expression_names"]],
        expression_deltas=raw["expression_deltas"].astype(np.float64), weights=raw["weights"].astype(np.float64),
        capture_error=raw["capture_error"].astype(np.float64),
        capture_error_weights=raw["capture_error_weights"].astype(np.float64),
        frames=np.arange(f0, f0 + T, dtype=np.int64), fps=int(raw["fps"]),
        camera=Camera(raw["K"].astype(np.float64), raw["R"].astype(np.float64), raw["t"].astype(np.float64), W, H),
        inner_lip_loop=raw["inner_lip_loop"].astype(np.int64), source_vertices=raw["source_vertices"].astype(np.int64))


def _add_key(obj, name: str, deltas) -> None:
    """A plain shape key = Basis + ``deltas`` (the capture's own keys: not registered as FaceLab's)."""
    if obj.data.shape_keys is None:
        obj.shape_key_add(name="Basis", from_mix=False)
    basis = obj.data.shape_keys.reference_key
    n = len(obj.data.vertices)
    co = np.empty(n * 3, np.float64)
    basis.data.foreach_get("co", co)
    kb = obj.shape_key_add(name=name, from_mix=False)
    kb.relative_key = basis
    kb.data.foreach_set("co", (co + np.asarray(deltas, np.float64).ravel()).astype(np.float32))
    kb.value = 0.0


#: Colour attribute of the sample face: 1 on the lips, 0 on the skin (tints the lips in renders).
LIP_TINT_ATTRIBUTE = "lip_tint"


def _lip_tint(vertices, loop, radius: float = 0.012) -> np.ndarray:
    """(V,) weights: 1 at the inner-lip loop, falling smoothly to 0 at ``radius`` metres from it."""
    d = np.linalg.norm(vertices[:, None] - vertices[loop][None], axis=2).min(axis=1)
    u = np.clip(d / radius, 0.0, 1.0)
    return 1.0 - u * u * (3.0 - 2.0 * u)


def _skin_material(name: str, skin, lips):
    """Skin shader whose base colour mixes to ``lips`` by the :data:`LIP_TINT_ATTRIBUTE` attribute."""
    from . import compat

    mat = bpy.data.materials.new(name)
    mat.diffuse_color = (*skin, 1.0)
    nt = compat.node_tree(mat)
    bsdf = nt.nodes.get("Principled BSDF")
    if bsdf is None:
        return mat
    bsdf.inputs["Roughness"].default_value = 0.5
    attr = nt.nodes.new("ShaderNodeAttribute")
    attr.attribute_name = LIP_TINT_ATTRIBUTE
    mix = nt.nodes.new("ShaderNodeMix")
    mix.data_type = "RGBA"
    by_id = {s.identifier: s for s in mix.inputs}
    by_id["A_Color"].default_value = (*skin, 1.0)
    by_id["B_Color"].default_value = (*lips, 1.0)
    nt.links.new(attr.outputs["Fac"], by_id["Factor_Float"])
    out = next(s for s in mix.outputs if s.identifier == "Result_Color")
    nt.links.new(out, bsdf.inputs["Base Color"])
    return mat


def build_sample(scene, data: SampleData, *, name: str = "Face", lights: bool = True) -> dict:
    """Build the sample shot in ``scene``: the face with its animated performance, the camera, lights.

    Sets the scene's frame range, frame rate and render resolution to the sample's; the face is
    smooth-shaded with a skin material. No FaceLab vertex groups are made (Auto Regions is a step of
    the route the sample is for).

    Parameters
    ----------
    scene : bpy.types.Scene
    data : SampleData
    name : str
        Name of the face object (Blender adds ``.001`` if taken).
    lights : bool
        Add a key and a fill light and a dark world (for renders), when the scene has no world.

    Returns
    -------
    dict
        ``{"face": Object, "camera": Object}``.
    """
    collection = bpy.data.collections.new("FaceLab Sample")
    scene.collection.children.link(collection)
    face = new_mesh_object(name, data.vertices, poly_verts=data.poly_verts, poly_offsets=data.poly_offsets,
                           collection=collection)
    if hasattr(face.data, "shade_smooth"):
        face.data.shade_smooth()
    tint = face.data.attributes.new(LIP_TINT_ATTRIBUTE, "FLOAT", "POINT")
    tint.data.foreach_set("value", _lip_tint(data.vertices, data.inner_lip_loop).astype(np.float32))
    face.data.materials.append(_skin_material("Sample skin", (0.72, 0.5, 0.4), (0.5, 0.16, 0.15)))
    for k, key_name in enumerate(data.expression_names):
        _add_key(face, key_name, data.expression_deltas[k])
    _add_key(face, ERROR_KEY, data.capture_error)
    frames = data.frames
    keys = face.data.shape_keys
    values = np.c_[data.weights, data.capture_error_weights]
    for k, key_name in enumerate([*data.expression_names, ERROR_KEY]):
        path = f'key_blocks["{bpy.utils.escape_identifier(key_name)}"].value'
        key_property_bulk(keys, path, frames, values[:, k], action_name=PERFORMANCE_ACTION)
    scene.frame_start, scene.frame_end = int(frames[0]), int(frames[-1])
    scene.render.fps, scene.render.fps_base = int(data.fps), 1.0
    cam = new_camera_object(scene, data.camera, name="Sample Camera")
    collection.objects.link(cam)
    scene.collection.objects.unlink(cam)
    if lights and scene.world is None:
        add_studio_lights(scene, background=(0.01, 0.01, 0.012))
        scene.view_settings.view_transform = "Standard"
    scene.frame_set(int(frames[0]))
    return {"face": face, "camera": cam}
