"""Refine Lips: deform the lips so their silhouettes match the sketched contours on one frame
(Dinev et al. 2018 §5), from one camera or several.

:func:`refine` reads the camera(s), the lip sketch(es) (:func:`read_views`) and the face on a frame
(:func:`refine_problem`, which Live Refine uses too), runs
:func:`facelab_addon.core.lips.sketch.refine_lips_views` with the settings' :class:`RefineParams` and
stores the refined shape, relative to the frame without FaceLab's lip corrections, as a new
corrective key ``FL_Refine_<frame>`` (:data:`~facelab_addon.names.REFINE_PREFIX`) keyed 1 on
the frame and 0 on its neighbours
(:func:`~facelab_addon.pipeline.training.store_training_frame`): the frame becomes a training
frame of Propagate, an earlier correction of the frame no longer adds there, and the frame shows
the refined shape now and after every later Propagate.

Views: every Grease Pencil lip sketch keyed on the frame whose camera is known
(:func:`facelab_addon.blender.sketch_views.sketch_views`: one sketch per camera, as New Lip Sketch
makes them) is one view of one solve; with a single sketch the scene camera (or ``camera_obj``)
is the view, as before. Regions: when the face has ``FL_lips`` / ``FL_mouth``
(:mod:`facelab_addon.pipeline.regions`), only the interior of ``FL_lips`` moves, its border and
``FL_mouth`` are held, so every correction is one Propagate's Poisson solve can reproduce.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ..assets import load_preset
from ..blender import cache_integrate, caches
from ..blender.camera import camera_from_blender, evaluated_depsgraph
from ..blender.mesh import (
    default_fixed_mask,
    evaluated_vertices,
    face_topology,
    require_mesh,
    vertex_group_mask,
    world_to_local_deltas,
    world_winding,
)
from ..blender.objects import ModifierState, require_editable, world_affine
from ..blender.rest_space import to_rest_space
from ..blender.scene_time import require_scene_time
from ..blender.shapekeys import rest_vertices
from ..blender.sketch_views import sketch_camera, sketch_views
from ..blender.strokes import read_lip_strokes, require_sketch_keyed_on
from ..core.errors import CameraError
from ..core.lips.refine_params import RefineParams
from ..core.lips.sketch import refine_lips_views
from ..core.lips.sketch_session import SketchSolver
from ..core.lips.views import SketchView, square_pixels
from ..names import FIXED_GROUP, LIPS_GROUP, MOUTH_GROUP, REFINE_PREFIX
from .training import store_training_frame, uncorrected_frame
from .settings import setting

__all__ = ["REFINE_DEFAULTS", "RefineSettings", "RefineResult", "RefineProblem", "refine", "refine_problem",
           "checked_view_sources", "read_views", "view_sources", "lip_region"]

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
    prior : str
        ``"band"`` (default: as ``"smooth"``, and inside ``FL_lips`` a reach of at least 3 edge lengths,
        so the correction carries across the band on a coarse mesh too), ``"smooth"`` (the correction carries about *Smooth Reach*
        across the lips) or ``"paper"`` (Eq. 1 as written); see :mod:`facelab_addon.core.lips.sketch`.
    smooth_reach : float
        How far the correction of a silhouette carries across the lips, in mouth widths.
    free_radius : float
        How far from the sketched lips the mesh may move, in mouth widths.
    use_regions : bool
        When ``FL_lips`` / ``FL_mouth`` exist, move only the interior of ``FL_lips``.
    crossings : str
        ``"follow"`` a crossing drawing as an overlap, or ``"press"`` the lips together there.
    all_views : bool
        Use every camera with a lip sketch keyed on the frame (one solve), not only one.
    depth_reg : float
        With several views, the extra stiffness of the correction along the main camera's rays
        (``refine_lips_views``' ``depth_reg``); no effect with one view.
    rest_depth_reg : float
        With one view, how strongly the depth it cannot see follows the face's rest pose (its Basis) turned
        with the head (``refine_lips_views``' ``rest_depth_reg``); no effect with several views.
    """

    iterations: int = setting(REFINE_DEFAULTS["iterations"], label="Iterations", min=1, max=100,
                              description="How often the lips are solved and matched to the sketch again; raise it when "
                                          "the result stops short of a strongly curved sketch")
    lambda_pos: float = setting(REFINE_DEFAULTS["lambda_pos"], label="Position Weight", min=0.0, soft_max=10.0,
                                description="How strongly vertices keep their captured position; lower it when the lips "
                                            "do not reach the sketch, raise it when the face around them moves")
    lambda_reg: float = setting(REFINE_DEFAULTS["lambda_reg"], label="Rigidity Weight", min=0.0, soft_max=100.0,
                                description="How strongly the lips keep their local shape; raise it when the refined lips "
                                            "get dents or kinks, lower it when they do not bend to the sketch")
    lambda_silh: float = setting(REFINE_DEFAULTS["lambda_silh"], label="Silhouette Weight", min=0.0,
                                 soft_max=100.0, description="Pull of the sketched contours; raise it when the lips stop short "
                                                             "of the sketch, lower it when they overshoot or wrinkle")
    fixed_group: str = setting(FIXED_GROUP, label="Fixed Group",
                               description="Vertex group of hidden vertices that must not move (inner mouth, "
                                           "teeth, back of the head); without it, separate mesh parts are fixed")

    prior: str = setting("band", label="Prior", choices=(
        ("band", "Band", "As Smooth, and inside FL_lips (its border held) the correction carries at least 3 edge "
                         "lengths, so it crosses the lip band on a coarse mesh too (FaceLab's default)"),
        ("smooth", "Smooth", "The correction of the silhouettes carries smoothly across the lip band "
                             "(about Smooth Reach from the silhouettes)"),
        ("paper", "Paper", "Every vertex anchored with the Position Weight, nothing carried across the lips "
                           "(the published method, for comparison)")),
        description="How the vertices away from the sketched silhouettes follow them; change it when the inside "
                    "of the lips lags behind the corrected silhouette")
    smooth_reach: float = setting(0.12, label="Smooth Reach", min=0.01, soft_max=1.0, unit="mouth",
                                  description="How far the correction of a silhouette carries across the lips, "
                                              "in mouth widths (Band and Smooth priors); raise it when the lip "
                                              "surface behind the silhouette stays behind")
    free_radius: float = setting(0.1, label="Free Region", min=0.01, soft_max=2.0, unit="mouth",
                                 description="How far from the sketched lips the mesh may move, in mouth widths; "
                                             "everything farther is held exactly")
    use_regions: bool = setting(True, label="Only FL_lips",
                                description=f"When the face has {LIPS_GROUP} / {MOUTH_GROUP} (Auto Regions), move "
                                            f"only the inside of {LIPS_GROUP}; its border and {MOUTH_GROUP} are "
                                            "held, as Propagate holds them")
    crossings: str = setting("follow", label="Crossing Contours", choices=(
        ("follow", "Follow", "A lower contour drawn above the upper one is an overlap: one lip in front of the "
                             "other, as drawn"),
        ("press", "Press", "A lower contour drawn above the upper one presses the lips together (to their "
                           "mid-line)")),
        description="How a crossing drawing (lower lip above the upper lip) is read")
    all_views: bool = setting(True, label="All Camera Sketches",
                              description="Use the lip sketches of every camera keyed on this frame in one solve "
                                          "(a stereo pair or witness camera fixes the depth of the lips)")
    depth_reg: float = setting(3.0, label="Depth Stiffness", min=0.0, soft_max=20.0,
                               description="With more than one camera: how much more stiffly the correction "
                                           "bends along the main camera's rays (the depth it cannot see) than "
                                           "across them (0: as stiff as across); raise it when a second view "
                                           "dents the lips")
    rest_depth_reg: float = setting(10.0, label="Depth From Rest", min=0.0, soft_max=100.0,
                                    description="With one camera: how strongly the depth it cannot see follows "
                                                "the face's rest pose turned with the head, so a nodded head's "
                                                "correction keeps its depth (0: it moves across the camera's rays "
                                                "only); lower it when the rest pose's depth is wrong for the shot")

    def params(self) -> RefineParams:
        """The core solver's settings (:class:`~facelab_addon.core.lips.refine_params.RefineParams`): these
        fields, and the core's defaults for the rest."""
        return RefineParams(iterations=self.iterations, lambda_pos=self.lambda_pos, lambda_reg=self.lambda_reg,
                            lambda_silh=self.lambda_silh, prior=self.prior, smooth_reach=self.smooth_reach,
                            free_radius=self.free_radius, crossings=self.crossings, depth_reg=self.depth_reg,
                            rest_depth_reg=self.rest_depth_reg)


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
    cameras : list of str
        The camera objects whose sketches were used (one view each).
    lips_region : bool
        Whether only the inside of ``FL_lips`` was free.
    note : str
        What was changed so the key shows over a cache (empty without one).
    head_turn_deg : float or None
        With one view: how far the head is turned from its rest pose (the Basis), degrees; the depth the
        camera cannot see was taken from the rest pose turned so far. None with several views, or when the
        rest pose does not fit the frame rigidly or ``rest_depth_reg`` is 0.
    seconds : float
    warnings : list of str
        What the artist should check in the sketch (strokes that may be on swapped layers); the key is
        written as drawn.
    """

    frame: int
    shape_key: str
    moved_vertices: int
    max_move: float
    fixed_source: str
    cameras: list = field(default_factory=list)
    lips_region: bool = False
    note: str = ""
    head_turn_deg: float | None = None
    seconds: float = 0.0
    warnings: list = field(default_factory=list)


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
    pairs = checked_view_sources(scene, frame, sketch, camera_obj, settings.all_views)
    if scene.frame_current != frame or scene.frame_subframe:  # a subframe left on would be read as the frame
        scene.frame_set(frame)
    obj = require_mesh(obj)
    require_editable(obj, "Refine Lips")
    require_scene_time(scene, "Refine Lips", obj)
    caches.check_capture_files(obj)  # never the static mesh in place of a broken cache
    dg = evaluated_depsgraph(scene)
    views = read_views(scene, frame, pairs, dg)
    problem = refine_problem(scene, obj, frame, settings, depsgraph=dg)
    V, shown = problem.capture, problem.shown
    X, info = problem.solve(views, settings.params())
    note = ""
    on_cache = caches.sequence_source(obj) in _CACHE_SOURCES
    state = ModifierState(obj)
    try:
        if on_cache:
            note = cache_integrate.cache_to_shape_key_ready(obj)  # so the corrective key shows on the cache
        # the training frame is the refined shape relative to the frame without FaceLab's lip corrections
        # (uncorrected_frame), not to what Propagate happened to show here: it then holds through later rounds
        d_world = X - V
        d_local = world_to_local_deltas(obj, d_world)
        if on_cache:
            captured = caches.read_captured_frames(obj, [frame])[0]
            d_local = cache_integrate.correction_to_key_offsets(obj, captured, d_local)
    except BaseException:
        state.restore()  # a failure leaves the cache modifiers as they were
        raise
    d_local = to_rest_space(obj, [frame], d_local[None], depsgraph=dg)[0]  # through an Armature: rest-space offsets
    kb = store_training_frame(scene, obj, frame, d_local, REFINE_PREFIX, "sketch")
    moved = np.linalg.norm(X - shown, axis=1)  # what the artist sees change
    return RefineResult(frame=frame, shape_key=kb.name, moved_vertices=int((moved > 1e-9).sum()),
                        max_move=float(moved.max()), fixed_source=problem.fixed_source, cameras=[v.name for v in views],
                        lips_region=problem.lips is not None, note=note, head_turn_deg=info["head_turn_deg"],
                        seconds=time.perf_counter() - t0, warnings=list(info.get("warnings", [])))


@dataclass
class RefineProblem:
    """One frame of one face as the sketch solve sees it: what Refine Lips and Live Refine both solve.

    Made by :func:`refine_problem`. Positions are world space, scene units; ``V`` is the face's vertex count.

    Attributes
    ----------
    frame : int
    capture : (V,3) float
        Where the solve starts: the frame without FaceLab's lip corrections
        (:func:`~facelab_addon.pipeline.training.uncorrected_frame`), world positions.
    shown : (V,3) float
        What the viewport shows on the frame (earlier corrections included), world positions.
    affine : ((3,3) float, (3,) float)
        ``(A, b)``: world = local @ A.T + b.
    topo : FaceTopology
        Triangles and the weld of split seams (:func:`~facelab_addon.blender.mesh.face_topology`): twins that
        coincide at rest and on this frame are one vertex for the solve.
    tris : (F,3) int
        Triangles of the whole mesh, wound for world space (a mirrored object keeps its normals outward).
    fixed : (V,) bool
        Hidden vertices, held (:func:`~facelab_addon.blender.mesh.default_fixed_mask`).
    fixed_source : str
        What fixed them (the vertex group, or separate mesh parts).
    lips : (V,) bool or None
        ``FL_lips`` when the settings use the regions and the face has them (:func:`lip_region`), else None.
    rest : (V,3) float
        The face's Basis where the object is (the head unturned), world positions.
    """

    frame: int
    capture: np.ndarray
    shown: np.ndarray
    affine: tuple
    topo: object
    tris: np.ndarray
    fixed: np.ndarray
    fixed_source: str
    lips: np.ndarray | None
    rest: np.ndarray

    def __post_init__(self):
        w = self.weld
        if w is None:
            self._face = (self.capture, self.tris, self.fixed, self.lips, self.rest)
        else:  # the solver sees the welded surface alone (no duplicate weighs in a fit twice)
            Vc, tris_c = w.compact(self.capture)
            self._face = (Vc, world_winding(tris_c, self.affine[0]), self.fixed[w.kept],
                          None if self.lips is None else self.lips[w.kept], self.rest[w.kept])

    @property
    def weld(self):
        """The seam weld (``topo.weld``), or None when the mesh has no split seam."""
        return self.topo.weld if self.topo.n_duplicates else None

    def solver_face(self) -> tuple:
        """``(vertices (W,3), triangles (G,3), fixed (W,), lips (W,) or None, rest (W,3))`` of the surface the
        solver sees: the welded one (``W`` kept vertices) when the mesh has split seams, else the whole mesh."""
        return self._face

    def solver(self, params: RefineParams, width_tol: float = 0.0) -> SketchSolver:
        """A :class:`~facelab_addon.core.lips.sketch_session.SketchSolver` of :meth:`solver_face`."""
        V, tris, fixed, lips, rest = self._face
        return SketchSolver(V, tris, params, fixed=fixed, lips=lips, rest_vertices=rest, width_tol=width_tol)

    def expand(self, X, info=None):
        """The solver's result ``X`` (on :meth:`solver_face`) on the whole mesh, world positions: each duplicate of
        a welded seam moves with its twin, so the seams stay closed. ``info['region']``, when given, is expanded
        in place."""
        w = self.weld
        if w is None:
            return X
        if info is not None:
            info["region"] = w.uncompact(np.asarray(info["region"], bool))
        return self.capture + w.uncompact(X - self._face[0])

    def solve(self, views, params: RefineParams):
        """Refine the lips to ``views`` from the capture: ``(X (V,3) world positions, info)`` of
        :func:`~facelab_addon.core.lips.sketch.refine_lips_views` (its ``region`` on the whole mesh)."""
        V, tris, fixed, lips, rest = self._face
        X, info = refine_lips_views(V, tris, views, params, fixed=fixed, lips=lips, rest_vertices=rest,
                                    return_info=True)
        return self.expand(X, info), info


def refine_problem(scene, obj, frame: int, settings: RefineSettings, *, depsgraph=None) -> RefineProblem:
    """Read ``obj`` on ``frame`` as the sketch solve sees it (the scene already on ``frame``).

    Parameters
    ----------
    scene : bpy.types.Scene
    obj : bpy.types.Object
        The face mesh (checked by the caller).
    frame : int
    settings : RefineSettings
        Its ``fixed_group`` and ``use_regions``.
    depsgraph : bpy.types.Depsgraph, optional
        Default: the scene's evaluated one.

    Returns
    -------
    RefineProblem
    """
    dg = depsgraph if depsgraph is not None else evaluated_depsgraph(scene)
    shown = evaluated_vertices(obj, dg)
    A, b = world_affine(obj, dg)
    # the solve starts from the frame without FaceLab's lip corrections (uncorrected_frame: the capture), not from
    # what an earlier Propagate or Refine shows on it: the drawing alone decides the result, so a propagated error
    # the sketch does not see is not carried into the training frame
    V = uncorrected_frame(obj, frame) @ A.T + b
    # split seams welded where the twins coincide at rest, in every key and on this frame (a lip cut stays cut)
    topo = face_topology(obj, _local_frame(V, A, b))
    tris = world_winding(topo.tris, A)  # V is in world space: a mirrored object keeps its normals outward
    fixed, fixed_src = default_fixed_mask(obj, topo, settings.fixed_group)
    lips = lip_region(obj) if settings.use_regions else None
    rest = rest_vertices(obj) @ A.T + b  # the Basis, where the object is: the head unturned
    return RefineProblem(frame=int(frame), capture=V, shown=shown, affine=(A, b), topo=topo, tris=tris, fixed=fixed,
                         fixed_source=fixed_src, lips=lips, rest=rest)


def checked_view_sources(scene, frame, sketch, camera_obj, all_views) -> list:
    """:func:`view_sources`, each sketch checked to be keyed on ``frame`` (never a drawing held from an earlier
    frame)."""
    pairs = view_sources(scene, frame, sketch, camera_obj, all_views)
    for gp, _ in pairs:
        require_sketch_keyed_on(scene, frame, gp)
    return pairs


def read_views(scene, frame, pairs, depsgraph=None) -> list:
    """One :class:`~facelab_addon.core.lips.sketch.SketchView` per ``(sketch, camera object)`` of ``pairs``: the
    camera and its lip strokes on ``frame``, read now, in square pixels (:func:`~facelab_addon.core.lips.views.square_pixels`:
    a render pixel aspect not 1 is undone, so the solve's pixel sizes mean one length across and along the image)."""
    dg = depsgraph if depsgraph is not None else evaluated_depsgraph(scene)
    views = []
    for gp, cam_obj in pairs:
        cam = camera_from_blender(scene, cam_obj, dg)
        strokes = read_lip_strokes(scene, cam, frame, gp_obj=gp, depsgraph=dg)
        views.append(square_pixels(SketchView(cam, strokes["upper"], strokes["lower"], name=cam_obj.name)))
    return views


def _local_frame(V, A, b):
    """The world positions ``V`` (V,3) in the object's local space, as a one-pose generator (read lazily)."""
    yield np.linalg.solve(A, (V - b).T).T


def view_sources(scene, frame, sketch, camera_obj, all_views) -> list:
    """``[(sketch or None, camera object), ...]``: one view per camera with a sketch on ``frame``.

    With ``all_views`` and two or more cameras sketched on the frame (the given ``sketch`` among
    them, drawn through ``camera_obj`` or its own camera), each is a view. Otherwise the one
    view of the single-camera route: ``sketch`` (or the one found in the scene, else the
    annotation) through ``camera_obj``, else the scene camera.
    """
    found = sketch_views(scene, frame) if all_views else []
    if sketch is not None and found:
        own = camera_obj or sketch_camera(sketch) or scene.camera
        found = [(gp, cam) for gp, cam in found if gp != sketch and cam != own]
        found.insert(0, (sketch, own))
    if len(found) >= 2:
        return found
    cam_obj = camera_obj if camera_obj is not None else scene.camera
    if cam_obj is None:
        raise CameraError(f"Scene '{scene.name}' has no camera; set the camera the sketch was drawn in.")
    return [(sketch, cam_obj)]


def lip_region(obj):
    """(V,) bool ``FL_lips`` when both ``FL_lips`` and ``FL_mouth`` exist, else None.

    Only the inside of ``FL_lips`` moves (:func:`~facelab_addon.core.lips.sketch_prior.free_region`):
    its border, the ring ``FL_mouth`` shares with it, is held, so ``FL_mouth`` never moves.
    """
    lips = vertex_group_mask(obj, LIPS_GROUP)
    if lips is None or vertex_group_mask(obj, MOUTH_GROUP) is None or not lips.any():
        return None
    return lips
