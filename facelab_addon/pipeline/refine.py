"""Refine Lips: deform the lips so their silhouettes match the sketched contours on one frame
(Dinev et al. 2018 §5).

:func:`refine` reads the camera, the lip sketch and the evaluated face on a frame, runs
:func:`facelab_addon.core.lips.sketch.refine_lips` and stores the correction as a new
corrective key ``FL_Refine_<frame>`` (:data:`~facelab_addon.names.REFINE_PREFIX`) keyed 1 on
the frame and 0 on its neighbours; the frame becomes a training frame of Propagate.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ..assets import load_preset
from ..blender import cache_integrate, caches
from ..blender.camera import camera_from_blender, evaluated_depsgraph
from ..blender.mesh import (
    default_fixed_mask,
    evaluated_vertices,
    mesh_triangles,
    require_mesh,
    world_to_local_deltas,
)
from ..blender.objects import ModifierState, require_editable
from ..blender.rest_space import to_rest_space
from ..blender.shapekeys import add_corrective_key, key_spike
from ..blender.strokes import read_lip_strokes, require_sketch_keyed_on
from ..core.errors import CameraError
from ..core.lips.sketch import refine_lips
from ..names import FIXED_GROUP, REFINE_PREFIX
from .propagate import record_training_frame
from .settings import setting

__all__ = ["REFINE_DEFAULTS", "RefineSettings", "RefineResult", "refine"]

_CACHE_SOURCES = ("mesh_cache", "mesh_sequence_cache")

#: The solver weights of ``assets/presets/sketch_refine.json`` (the paper's): the defaults of
#: :class:`RefineSettings` and of the add-on preferences.
REFINE_DEFAULTS = load_preset("sketch_refine", {"iterations": int, "lambda_pos": float, "lambda_reg": float,
                                                "lambda_silh": float})


@dataclass
class RefineSettings:
    """Weights of the sketch refinement (Dinev et al. 2018, Eq. 1; paper defaults) and the fixed group.

    Attributes
    ----------
    iterations : int
        Solve / re-match iterations.
    lambda_pos : float
        How strongly vertices keep their captured position (fixed vertices use 1).
    lambda_reg : float
        Preservation of the local shape (Laplacian coordinates).
    lambda_silh : float
        Pull of the sketched contours.
    fixed_group : str
        Vertex group of hidden vertices that must not move; without it, the
        parts separate from the largest piece of the mesh are fixed.
    """

    iterations: int = setting(REFINE_DEFAULTS["iterations"], label="Iterations", min=1, max=100,
                              description="Solve / re-match iterations of the sketch refinement (paper: 5)")
    lambda_pos: float = setting(REFINE_DEFAULTS["lambda_pos"], label="Position Weight", min=0.0, soft_max=10.0,
                                description="How strongly vertices keep their captured position "
                                            "(paper: 0.1; fixed vertices use 1)")
    lambda_reg: float = setting(REFINE_DEFAULTS["lambda_reg"], label="Rigidity Weight", min=0.0, soft_max=100.0,
                                description="Preservation of the local shape (Laplacian coordinates) (paper: 3)")
    lambda_silh: float = setting(REFINE_DEFAULTS["lambda_silh"], label="Silhouette Weight", min=0.0,
                                 soft_max=100.0, description="Pull of the sketched contours (paper: 1)")
    fixed_group: str = setting(FIXED_GROUP, label="Fixed Group",
                               description="Vertex group of hidden vertices that must not move (inner mouth, "
                                           "teeth, back of the head); without it, separate mesh parts are fixed")

    def solver_weights(self) -> dict:
        """The keyword arguments of :func:`~facelab_addon.core.lips.sketch.refine_lips`."""
        return dict(iterations=self.iterations, lambda_pos=self.lambda_pos, lambda_reg=self.lambda_reg,
                    lambda_silh=self.lambda_silh)


@dataclass
class RefineResult:
    """What :func:`refine` did.

    Attributes
    ----------
    frame : int
    shape_key : str
        The corrective key written (a new one: an existing key is never overwritten).
    moved_vertices : int
        Vertices the refinement moved.
    max_move : float
        Largest displacement, world scene units.
    fixed_source : str
        What fixed the hidden vertices (a vertex group, or separate mesh parts).
    note : str
        What was changed so the key shows over a cache (empty without one).
    seconds : float
    """

    frame: int
    shape_key: str
    moved_vertices: int
    max_move: float
    fixed_source: str
    note: str = ""
    seconds: float = 0.0


def refine(scene, obj, frame: int, settings: RefineSettings | None = None, *, camera_obj=None,
           sketch=None) -> RefineResult:
    """Refine the lips of ``obj`` on ``frame`` to the sketch; write and key the corrective key.

    Parameters
    ----------
    scene : bpy.types.Scene
        Set to ``frame`` first when it is not the current frame.
    obj : bpy.types.Object
        The face mesh.
    frame : int
    settings : RefineSettings, optional
    camera_obj : bpy.types.Object, optional
        The camera the sketch was drawn through; default ``scene.camera``.
    sketch : bpy.types.Object, optional
        The Grease Pencil sketch; default found in the scene
        (:func:`facelab_addon.blender.strokes.find_sketch_object`), else the annotation.

    Returns
    -------
    RefineResult

    Raises
    ------
    SketchError, CameraError, MeshError
        No or incomplete sketch on the frame, no sketch keyframe on the frame
        (strokes held from an earlier one), strokes outside the frame or
        behind the camera, no camera, not a mesh with faces. Nothing is
        changed then.
    CacheFileError
        The face's cache file is missing or broken.
    """
    settings = settings or RefineSettings()
    t0 = time.perf_counter()
    require_sketch_keyed_on(scene, frame, sketch)  # never a drawing held from an earlier frame
    if scene.frame_current != frame:
        scene.frame_set(frame)
    cam_obj = camera_obj if camera_obj is not None else scene.camera
    if cam_obj is None:
        raise CameraError(f"Scene '{scene.name}' has no camera; set the camera the sketch was drawn in.")
    obj = require_mesh(obj)
    require_editable(obj, "Refine Lips")
    caches.check_capture_files(obj)  # never the static mesh in place of a broken cache
    dg = evaluated_depsgraph(scene)
    cam = camera_from_blender(scene, cam_obj, dg)
    strokes = read_lip_strokes(scene, cam, frame, gp_obj=sketch, depsgraph=dg)
    V = evaluated_vertices(obj, dg)
    tris = mesh_triangles(obj.data)
    fixed, fixed_src = default_fixed_mask(obj, tris, settings.fixed_group)
    X, _ = refine_lips(V, tris, cam, strokes["upper"], strokes["lower"], fixed=fixed, return_info=True,
                       **settings.solver_weights())
    note = ""
    on_cache = caches.sequence_source(obj) in _CACHE_SOURCES
    state = ModifierState(obj)
    try:
        if on_cache:
            note = cache_integrate.cache_to_shape_key_ready(obj)  # so the corrective key shows on the cache
        d_world = X - V
        d_local = world_to_local_deltas(obj, d_world)
        if on_cache:
            captured = caches.read_captured_frames(obj, [frame])[0]
            d_local = cache_integrate.correction_to_key_offsets(obj, captured, d_local)
    except BaseException:
        state.restore()  # a failure leaves the cache modifiers as they were
        raise
    d_local = to_rest_space(obj, [frame], d_local[None], depsgraph=dg)[0]  # through an Armature: rest-space offsets
    kb = add_corrective_key(obj, f"{REFINE_PREFIX}{frame:04d}", d_local)
    key_spike(kb, frame)
    record_training_frame(scene, obj, frame, kb.name, "sketch")
    moved = np.linalg.norm(d_world, axis=1)
    return RefineResult(frame=frame, shape_key=kb.name, moved_vertices=int((moved > 1e-9).sum()),
                        max_move=float(moved.max()), fixed_source=fixed_src, note=note,
                        seconds=time.perf_counter() - t0)
