"""Live Refine: the lips follow the sketch stroke by stroke, as a preview, until the artist accepts it.

:class:`LiveRefine` is a synchronous session on one frame of one face. It reads the face, its fixed
and lip regions and its rest pose once, with Refine's own reader
(:func:`facelab_addon.pipeline.refine.refine_problem`, so both solve the same welded, wound surface);
:meth:`LiveRefine.update` (after each stroke, or each edited
point) reads the lip sketch(es) of the frame as Refine Lips reads them (snapped to the plate when the
sketch asks for it), solves with one :class:`facelab_addon.core.lips.sketch_session.SketchSolver` kept
for the session (its free region, operators and factorisation are made again only when the strokes
change the free region or the mouth's width, or the settings change; see :data:`WIDTH_TOL`) and shows
the result on the face as the shape key :data:`PREVIEW_KEY`, which nothing else reads: it is not one
of FaceLab's recorded keys (:func:`facelab_addon.blender.ownership.owned_keys`), no training frame
points to it, and the capture readers leave it out (``shapekeys.key_matches``).
:meth:`LiveRefine.accept` removes the preview and runs :func:`facelab_addon.pipeline.refine.refine`
on the same strokes and settings, so the result has exactly a Refine's meaning and storage;
:meth:`LiveRefine.discard` removes the preview and leaves nothing behind.

*Influence*: how far from the sketched lips the mesh may move, in millimetres, like the radius of
proportional editing. It is Refine's ``free_radius`` (in mouth widths) through the width of this
face's own sketched mouth (``refine_lips_views``' ``mouth_width``) and the scene's unit scale; 0
keeps Refine's setting. :meth:`LiveRefine.region` is the free region of the last solve (what the
viewport draws).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np

from ..blender import caches
from ..blender.mesh import require_mesh, world_to_local_deltas
from ..blender.objects import require_editable
from ..blender.rest_space import to_rest_space
from ..blender.scene_time import require_scene_time
from ..core.errors import FaceLabError
from ..core.lips.refine_params import RefineParams
from ..core.lips.sketch_session import SketchSolver
from ..names import LIVE_PREVIEW_KEY
from .refine import RefineResult, RefineSettings, checked_view_sources, read_views, refine, refine_problem

__all__ = ["PREVIEW_KEY", "LiveUpdate", "LiveRefine", "remove_preview", "influence_to_mouth_widths"]

#: The preview's shape key (on the face, value 1 while a session is open).
PREVIEW_KEY = LIVE_PREVIEW_KEY
#: The preview keeps its solve's system for strokes that leave the free region as it was and move the sketched
#: mouth's width by at most this fraction (``SketchSolver``'s ``width_tol``), as a point edited inside the sketch
#: does.
WIDTH_TOL = 1e-3


@dataclass
class LiveUpdate:
    """What one :meth:`LiveRefine.update` did.

    Attributes
    ----------
    seconds : float
        Stroke to preview: reading the strokes, solving, writing the preview key.
    solve_seconds : float
        Of which the solve(s).
    solves : int
        Linear solves of the solve/re-match iterations (fewer than the iterations once a matching repeats).
    rebuilt : bool
        Whether the solve made its system (free region, operators, factorisation) anew: the first update,
        new settings, or strokes that changed the free region or the mouth width by more than
        :data:`WIDTH_TOL`.
    free_radius : float
        The free region's reach used, mouth widths.
    influence_mm : float
        The same in millimetres.
    n_free : int
        Vertices free to move (the region drawn in the viewport).
    max_move : float
        Largest displacement of the preview, world scene units.
    silhouette_px : float
        Mean distance of the sketch from the preview's silhouettes, pixels.
    warnings : list of str
        What the solve asks the artist to check (e.g. strokes that may sit on swapped layers); Accept's
        Refine reports the same.
    """

    seconds: float
    solve_seconds: float
    solves: int
    rebuilt: bool
    free_radius: float
    influence_mm: float
    n_free: int
    max_move: float
    silhouette_px: float
    warnings: list = field(default_factory=list)


def influence_to_mouth_widths(influence_mm: float, mouth_width: float, mm_per_unit: float) -> float:
    """An Influence in millimetres as Refine's ``free_radius``: mouth widths of this face's sketched mouth.

    Parameters
    ----------
    influence_mm : float
    mouth_width : float
        The sketched mouth's width, scene units (``refine_lips_views``' ``mouth_width``).
    mm_per_unit : float
        Millimetres per scene unit (``1000 * scene.unit_settings.scale_length``).
    """
    if not (mouth_width > 0 and mm_per_unit > 0):
        raise FaceLabError("The mouth width and the unit scale must be positive; check the scene's Unit Scale.")
    return float(influence_mm) / (float(mouth_width) * float(mm_per_unit))


def remove_preview(obj) -> bool:
    """Remove the face's :data:`PREVIEW_KEY` if it has one (and the Basis, when it is the only key left and
    the session made it: ``obj["facelab_live_basis"]``). Returns whether a key was removed."""
    key = obj.data.shape_keys
    made_basis = bool(obj.get("facelab_live_basis", False))
    if "facelab_live_basis" in obj:
        del obj["facelab_live_basis"]
    if key is None or key.key_blocks.get(PREVIEW_KEY) is None:
        return False
    obj.shape_key_remove(key.key_blocks[PREVIEW_KEY])
    key = obj.data.shape_keys
    if made_basis and key is not None and len(key.key_blocks) == 1:
        obj.shape_key_remove(key.key_blocks[0])
    return True


class LiveRefine:
    """A Live Refine session on one frame: :meth:`update` after each stroke, then :meth:`accept` or
    :meth:`discard`.

    Parameters
    ----------
    scene : bpy.types.Scene
    obj : bpy.types.Object
        The face mesh.
    frame : int, optional
        Default: the scene's current frame (the scene is set to it).
    settings : RefineSettings, optional
        Refine Lips' settings (Accept refines with them, ``free_radius`` from the Influence).
    sketch : bpy.types.Object, optional
        The Grease Pencil sketch (default found as Refine finds it).
    camera_obj : bpy.types.Object, optional
        Default: the sketch's camera, else the scene camera.
    influence_mm : float
        How far from the sketched lips the mesh may move, millimetres; 0 keeps ``settings.free_radius``.

    Raises
    ------
    MeshError, CameraError
        Not a mesh with faces, no camera.
    FaceLabError
        The face plays a mesh cache (the preview key would not show over it: use Refine Lips).
    """

    def __init__(self, scene, obj, frame: int | None = None, settings: RefineSettings | None = None, *,
                 sketch=None, camera_obj=None, influence_mm: float = 0.0):
        self.scene = scene
        self.obj = require_mesh(obj)
        require_editable(self.obj, "Live Refine")
        require_scene_time(scene, "Live Refine", self.obj)
        if caches.sequence_source(self.obj) in ("mesh_cache", "mesh_sequence_cache"):
            raise FaceLabError(f"'{self.obj.name}' plays a mesh cache, which a preview key does not show over; "
                               "use Refine Lips (it prepares the cache) instead of Live Refine.")
        self.frame = int(scene.frame_current if frame is None else frame)
        self.settings = settings or RefineSettings()
        self.sketch = sketch
        self.camera_obj = camera_obj
        self.influence_mm = float(influence_mm)
        self.mm_per_unit = 1000.0 * float(scene.unit_settings.scale_length or 1.0)
        remove_preview(self.obj)  # a stale preview (an undo, a crash) is never read as the capture
        if scene.frame_current != self.frame:
            scene.frame_set(self.frame)
        #: The frame's face as Refine reads it (capture, weld, fixed and lip regions, rest pose).
        self.problem = refine_problem(scene, self.obj, self.frame, self.settings)
        self.X = None
        self.info = None
        self._solver = None  # the frame's SketchSolver, kept between updates (see _session)
        self._solver_key = None
        self.mouth_width = None
        self.closed = False

    # ------------------------------------------------------------------ reading
    def views(self) -> list:
        """The :class:`~facelab_addon.core.lips.sketch.SketchView` s of the frame's strokes, read now."""
        pairs = checked_view_sources(self.scene, self.frame, self.sketch, self.camera_obj, self.settings.all_views)
        return read_views(self.scene, self.frame, pairs)

    # ------------------------------------------------------------------ solving
    def free_radius(self, mouth_width: float | None = None) -> float:
        """Refine's ``free_radius`` (mouth widths) of the Influence, for a sketched mouth ``mouth_width`` wide
        (scene units; default the last solve's); ``settings.free_radius`` with no Influence or no solve yet."""
        w = self.mouth_width if mouth_width is None else mouth_width
        if self.influence_mm <= 0 or w is None:
            return self.settings.free_radius
        return influence_to_mouth_widths(self.influence_mm, w, self.mm_per_unit)

    def refine_settings(self) -> RefineSettings:
        """The settings a Refine of the current strokes uses: ``settings`` with the Influence's ``free_radius``."""
        return replace(self.settings, free_radius=self.free_radius())

    def _session(self) -> SketchSolver:
        """The frame's :class:`~facelab_addon.core.lips.sketch_session.SketchSolver`, kept while the settings are
        unchanged (the face, its regions and the frame are the session's own)."""
        # each solve sets free_radius from the Influence: a change of it alone keeps the solver
        params = replace(self.settings.params(), free_radius=RefineParams.free_radius)
        if self._solver is None or self._solver_key != params:
            self._solver = None
            self._solver = self.problem.solver(params, width_tol=WIDTH_TOL)
            self._solver_key = params
        return self._solver

    def _solve(self, views):
        X, info = self._session().solve(views, free_radius=self.free_radius, return_info=True)
        return self.problem.expand(X, info), info

    def update(self) -> LiveUpdate:
        """Re-solve the frame from the strokes drawn now and show the result as the preview key.

        Raises
        ------
        SketchError, CameraError
            As Refine Lips (no stroke yet on a lip, strokes behind the camera...); the preview is left
            as it was.
        """
        self._require_open()
        t0 = time.perf_counter()
        views = self.views()
        ts = time.perf_counter()
        X, info = self._solve(views)
        solve_s = time.perf_counter() - ts
        self.X, self.info, self.mouth_width = X, info, float(info["mouth_width"])
        self._write_preview(X - self.problem.shown)  # the preview key adds to what the face shows
        d = np.linalg.norm(X - self.problem.shown, axis=1)
        r = self.free_radius()
        return LiveUpdate(seconds=time.perf_counter() - t0, solve_seconds=solve_s, solves=int(info["solves"]),
                          rebuilt=bool(info["rebuilt"]), free_radius=r,
                          influence_mm=r * self.mouth_width * self.mm_per_unit, n_free=int(info["n_free"]),
                          max_move=float(d.max()), silhouette_px=float(info["silhouette_px"][-1]),
                          warnings=list(info.get("warnings", [])))

    def _write_preview(self, d_world):
        obj = self.obj
        d_local = world_to_local_deltas(obj, d_world)
        d_local = to_rest_space(obj, [self.frame], d_local[None])[0]
        key = obj.data.shape_keys
        if key is None:
            obj.shape_key_add(name="Basis", from_mix=False)
            obj["facelab_live_basis"] = True
            key = obj.data.shape_keys
        kb = key.key_blocks.get(PREVIEW_KEY)
        if kb is None:
            kb = obj.shape_key_add(name=PREVIEW_KEY, from_mix=False)
            kb.relative_key = key.reference_key
        n = len(obj.data.vertices)
        base = np.empty(n * 3, np.float32)
        key.reference_key.data.foreach_get("co", base)
        kb.data.foreach_set("co", (base.reshape(-1, 3) + d_local).astype(np.float32).ravel())
        kb.slider_min = min(kb.slider_min, 0.0)
        kb.value = 1.0
        kb.mute = False
        obj.data.update()

    # ------------------------------------------------------------------ results
    def region(self):
        """(V,) bool: the vertices the last solve could move (the Influence drawn in the viewport), or None
        before the first :meth:`update`."""
        return None if self.info is None else np.asarray(self.info["region"], bool)

    def preview_vertices(self):
        """(V,3) world positions of the preview (the last solve), or None before the first :meth:`update`."""
        return None if self.X is None else self.X.copy()

    def accept(self) -> RefineResult:
        """Remove the preview and Refine the frame from the same strokes and settings (a new ``FL_Refine_*``
        key, keyed on the frame, and a training frame). Closes the session."""
        self._require_open()
        remove_preview(self.obj)
        self.closed = True
        return refine(self.scene, self.obj, self.frame, self.refine_settings(), camera_obj=self.camera_obj,
                      sketch=self.sketch)

    def discard(self) -> None:
        """Remove the preview; nothing of the session is left. Closes the session."""
        if not self.closed:
            remove_preview(self.obj)
        self.closed = True

    def _require_open(self):
        if self.closed:
            raise FaceLabError("This Live Refine session is closed (accepted or discarded); start a new one.")
