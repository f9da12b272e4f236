"""Bind Tracks and Solve Performance (Bhat et al. 2013, §4): tracked footage -> keyed blendshape weights.

:func:`bind_tracks` ties every 2D track (and 3D bundle) of the views to the
face surface on a reference frame and stores the bindings on the face.
:func:`solve_performance` reads the views' markers, the bound bundles and the
views' lip / eyelid contours, solves the rig's weights frame by frame (plus the
out-of-subspace corrective) and writes the weights as ordinary F-curves and
the correctives as compressed ``FL_Solve_*`` keys (or a point cache). Each
frame's corrective goes from the core straight to the storage writer's disk
spool a chunk at a time, so memory does not grow with the shot.

Spaces: the solve runs in world space at the pose frame (cameras are world
objects). The rig (Basis and shape-key deltas, object-local) is mapped there
with the face's ``matrix_world`` (affine maps keep blendshape weights), and
the correctives are mapped back to object-local deltas.

Progress: the per-frame loop runs inside the core solver, which reports
through a ``progress(done, total)`` callback after every frame; the solve is
one uninterruptible call, so there is no step generator.
"""

from __future__ import annotations

import contextlib
import time
from dataclasses import dataclass, field

import numpy as np

from .. import names as fl
from ..blender import compat, tracking
from ..blender.actions import prepare_action
from ..blender.bindings import read_bindings, write_bindings
from ..blender.bundles import bundle_labels, collection_bundles, read_bundles
from ..blender.camera import evaluated_depsgraph
from ..blender.masks import read_curves
from ..blender.mesh import (
    default_fixed_mask,
    evaluated_vertices,
    face_topology,
    mesh_triangles,
    require_mesh,
    vertex_group_mask,
)
from ..blender.objects import require_editable, world_affine, world_matrices
from ..blender.scene_time import require_scene_time
from ..blender.rig import rig_shapes
from ..blender.shapekeys import key_values_bulk, remove_keys
from ..core.errors import BundleError, CameraError, FaceLabError
from ..core.solve.blendshape_solve import SolveParams
from ..core.solve.corrective import CorrectiveParams
from ..core.solve.performance import PerformanceParams
from .correctives import CorrectionWriter, StoredKeys
from .frames import frame_range
from .settings import setting
from .streaming import FrameChunks

__all__ = [
    "DISAGREE_PX",
    "BindSettings",
    "BindResult",
    "SolveSettings",
    "SolveResult",
    "solve_params",
    "require_views",
    "face_axes",
    "bind_tracks",
    "solve_performance",
    "summarise_skips",
]

#: Bind Tracks flags a track whose bound point misses its marker in another view by more than this (pixels).
DISAGREE_PX = 3.0

# the core's defaults: the single source of the defaults of the solve settings below
_FIT, _CORRECTIVE, _PASSES = SolveParams(), CorrectiveParams(), PerformanceParams()


# --------------------------------------------------------------------------- settings and results
@dataclass
class BindSettings:
    """What Bind Tracks reads besides the face.

    views : list of :class:`facelab_addon.blender.tracking.View`
        The tracking cameras (camera object + Movie Clip each).
    bundles : {"NONE", "EMPTIES", "TRACKING"}
        3D bundle source: none, the empties / point meshes of ``bundle_collection``,
        or the first view's clip reconstruction.
    bundle_collection : bpy.types.Collection or None
        For ``EMPTIES`` (None: the collection :data:`~facelab_addon.names.BUNDLES_COLLECTION`).
    fixed_group : str
        Vertex group of hidden vertices (no track binds to a triangle touching one).
    """

    views: list = field(default_factory=list)
    bundles: str = "NONE"
    bundle_collection: object = None
    fixed_group: str = fl.FIXED_GROUP


@dataclass
class BindResult:
    """What Bind Tracks did on ``frame``: names bound, and why the others were not."""

    frame: int
    bound: list            # track names bound to the surface
    untracked: list        # tracks with no marker on the bind frame in any view
    missed: list           # tracked, but no view's ray hit the face
    bundles: int           # bundles bound
    disagree: list         # bound tracks that reproject more than DISAGREE_PX from their marker in another view
    max_err_px: float      # largest such reprojection disagreement among the bound tracks
    warnings: list         # camera calibration warnings of the views
    time_s: float = 0.0


@dataclass
class SolveSettings:
    """Options of Solve Performance (defaults: the core's, see :func:`solve_params`).

    ``frame_start`` / ``frame_end`` of None mean the scene's (negative frames are
    honoured); ``annotation_view``
    is the index of the view the scene annotation was drawn through (-1: the
    annotation is ignored); the other fields are those of :class:`BindSettings`
    and the solver's options (weight bounds, dimensionless term weights, sliding
    contours, the corrective) and ``existing_animation`` (see
    :func:`facelab_addon.blender.actions.prepare_action`).
    """

    views: list = field(default_factory=list)
    frame_start: int | None = None
    frame_end: int | None = None
    bundles: str = "NONE"
    bundle_collection: object = None
    fixed_group: str = fl.FIXED_GROUP
    use_contours: bool = True
    annotation_view: int = -1
    use_corrective: bool = True
    sliding: bool = _PASSES.sliding
    weight_min: float = _FIT.bounds[0]
    weight_max: float = _FIT.bounds[1]
    marker_weight: float = _FIT.marker_weight
    contour_weight: float = _FIT.contour_weight
    existing_animation: str = "NEW_ACTION"
    anchor_weight: float = setting(
        _FIT.anchor_weight, label="Markers Anchor", min=0.0, soft_max=1000.0,
        description="How strongly the contour fit keeps the face away from the mouth and eyes where the markers "
                    "alone put it; lower it when the contours are more reliable than the markers (0: contours move the "
                    "whole face)")
    contour_damping: float = setting(
        _CORRECTIVE.region_damping, label="Corrective Damping at Contours", min=0.0, soft_max=1.0,
        description="How strongly the corrective stays near the contours around the mouth and eyes "
                    f"({_CORRECTIVE.damping:g} elsewhere); lower it when lip and lid corrections stop short of their "
                    "contours")
    lip_passes: int = setting(
        _PASSES.lip_passes, label="Lip Passes", min=0, max=10, soft_max=4,
        description="Times the contours are matched again on the corrected mesh and the lips alone solved again "
                    "(0: one pass); raise it when the inner lips still miss their contour")
    lip_line_weight: float = setting(
        _CORRECTIVE.lip_contour_weight, label="Lip Line Weight", min=0.0, soft_max=50.0,
        description="Weight of the tracked lip lines in the lip passes, relative to the markers (1); raise it "
                    "when the lips miss the tracked lip lines")
    lip_damping: float = setting(
        _CORRECTIVE.lip_damping, label="Lip Pass Damping", min=0.0, soft_max=3.0,
        description="How strongly the lip passes keep the lip correction on the lip rim; raise it when the lip "
                    "passes dent the lips")


def solve_params(settings: SolveSettings) -> tuple[SolveParams, CorrectiveParams, PerformanceParams]:
    """The core's options of Solve Performance from its settings (the one place they are mapped).

    Returns
    -------
    fit : SolveParams
        Weight bounds, marker / contour weights and the markers anchor of the blendshape fit.
    corrective : CorrectiveParams
        Damping at the contours and the lip passes' contour weight and damping.
    passes : PerformanceParams
        Sliding contours and the number of lip passes.
    """
    fit = SolveParams(bounds=(settings.weight_min, settings.weight_max), marker_weight=settings.marker_weight,
                      contour_weight=settings.contour_weight, anchor_weight=settings.anchor_weight)
    corrective = CorrectiveParams(region_damping=settings.contour_damping,
                                  lip_contour_weight=settings.lip_line_weight, lip_damping=settings.lip_damping)
    passes = PerformanceParams(sliding=settings.sliding, lip_passes=settings.lip_passes)
    return fit, corrective, passes


@dataclass
class SolveResult:
    """What Solve Performance wrote, skipped and measured."""

    frames: np.ndarray     # (T,) scene frames of the range
    solved: np.ndarray     # scene frames solved and keyed
    skipped: dict          # {scene frame: reason} of frames with nothing to fit
    rig_keys: list         # rig shape keys whose weights were keyed
    keys: list             # corrective keys written (FL_Solve_*)
    action_note: str       # what happened to an existing action ('' when nothing needed saying)
    notes: list            # other warnings for the report
    missing: dict          # {scene frame: markers unseen in every view} on solved frames
    curve_stats: dict | None  # contours read (read_curves' stats), None without contours
    n_markers: int         # bound tracks
    n_views: int
    gather_s: float        # reading the scene
    fit_s: float           # the core solve
    time_s: float          # everything
    core: object = None    # the core's PerformanceResult (per-frame info in ``core.info``; correctives None: streamed)


# --------------------------------------------------------------------------- shared helpers
def require_views(views) -> list:
    """``views`` if every one has a camera and a clip; raises ``CameraError`` naming the fix otherwise."""
    views = list(views)
    for i, v in enumerate(views):
        if v.camera is None:
            raise CameraError(f"Solve view {i + 1} has no camera; pick its camera object in FaceLab > Solve > Views.")
        if v.clip is None:
            raise CameraError(
                f"Camera '{v.camera.name}' (view {i + 1}) has no Movie Clip; pick the footage it filmed in FaceLab > "
                "Solve > Views (open it in the Clip editor first)."
            )
    if not views:
        raise CameraError(
            "No solve views: press Add View in FaceLab > Solve with the tracking camera as the scene camera and its "
            "footage as the scene's active clip (or pick them in the list)."
        )
    return views


def face_axes(cameras):
    """World ``(up, forward)`` unit vectors of the face from the cameras looking at it."""
    fwd = -np.mean([c.forward for c in cameras], axis=0)
    up = -np.mean([c.R[1] for c in cameras], axis=0)  # OpenCV y is down
    return up / np.linalg.norm(up), fwd / np.linalg.norm(fwd)


def _skin_triangles(obj, tris, fixed_group):
    """(F,) bool: triangles that may carry markers/contours (no fixed vertex: teeth, eyes, mouth bag...).

    Without the fixed group, the separate parts are those of the surface welded along split seams (a glTF import's
    UV islands are not teeth)."""
    fixed, src = default_fixed_mask(obj, face_topology(obj), fixed_group)
    return ~fixed[tris].any(axis=1), fixed, src


def _read_scene_bundles(scene, settings, frames, views):
    """``(names, (T,B,3) world positions)`` of the configured bundle source, or ``(None, None)``."""
    if settings.bundles == "NONE":
        return None, None
    if settings.bundles == "TRACKING":
        pts, names = tracking.clip_bundles(views[0].clip)
        return names, np.broadcast_to(pts, (len(frames),) + pts.shape).copy()
    objs = collection_bundles(settings.bundle_collection)
    return bundle_labels(objs), read_bundles(scene, objs, frames)


def summarise_skips(skipped: dict) -> str:
    """``{frame: reason}`` -> one phrase per reason with the first frames, for a report."""
    by = {}
    for f, r in skipped.items():
        by.setdefault(r, []).append(f)
    return "; ".join(f"{len(v)} skipped: {r} ({', '.join(map(str, v[:5]))}{'...' if len(v) > 5 else ''})"
                     for r, v in by.items())


# --------------------------------------------------------------------------- bind
def bind_tracks(scene, obj, frame: int, settings: BindSettings) -> BindResult:
    """Bind every track (and bundle) to the face surface on ``frame`` and store the bindings on ``obj``.

    Each marker's camera ray is cast onto the evaluated mesh in every view; the
    view whose surface point reprojects closest to the track's markers in the
    other views wins. Bundles take their nearest surface point. Triangles
    touching a fixed vertex (``settings.fixed_group``) are never used.

    Parameters
    ----------
    scene : bpy.types.Scene
    obj : bpy.types.Object
        The face mesh; its ``facelab_solve.bindings`` and ``bind_frame`` are replaced.
    frame : int
        Scene frame where the mesh matches the footage (e.g. the neutral pose).
    settings : BindSettings

    Raises
    ------
    FaceLabError
        Not a mesh, views without camera / clip / calibration, no bundles
        where bundles are enabled; nothing is written then.
    """
    from ..core.capture.markers import bind_surface_points, nearest_surface_points

    t0 = time.perf_counter()
    require_mesh(obj)
    require_editable(obj, "Bind Tracks")
    require_scene_time(scene, "Bind Tracks", obj)
    views = require_views(settings.views)
    keep = scene.frame_current
    scene.frame_set(int(frame))
    try:
        vd = tracking.read_views(scene, views, [frame])
        dg = evaluated_depsgraph(scene)
        V = evaluated_vertices(obj, dg)
        tris = mesh_triangles(obj.data)
        fmask, _, _ = _skin_triangles(obj, tris, settings.fixed_group)
        M = len(vd.names)
        best_v = np.full((M, 3), -1, np.int64)
        best_b = np.zeros((M, 3))
        best_e = np.full(M, np.inf)
        tracked = np.isfinite(vd.markers[0, :, :, 0])  # (C,M)
        for c, cam in enumerate(vd.cameras):
            sp, hit = bind_surface_points(V, tris, cam, vd.markers[0, c], face_mask=fmask)
            X = sp.evaluate(V)
            err = np.zeros(M)
            for c2, cam2 in enumerate(vd.cameras):
                if c2 != c:
                    e = np.linalg.norm(cam2.project(np.nan_to_num(X)) - vd.markers[0, c2], axis=1)
                    err += np.where(tracked[c2] & hit, np.nan_to_num(e, nan=0.0), 0.0)
            better = hit & (err < best_e)
            best_v[better], best_b[better], best_e[better] = sp.vertices[better], sp.bary[better], err[better]
        bound = best_e < np.inf
        if settings.bundles != "NONE":
            bnames, P = _read_scene_bundles(scene, settings, [frame], views)
            bsp = nearest_surface_points(V, tris, P[0], face_mask=fmask)
        names = [n for n, b in zip(vd.names, bound) if b]
        write_bindings(obj, "MARKER", names, best_v[bound], best_b[bound])
        untracked = [n for n, t in zip(vd.names, tracked.any(axis=0)) if not t]
        missed = [n for n, t, b in zip(vd.names, tracked.any(axis=0), bound) if t and not b]
        n_bundles = 0
        if settings.bundles != "NONE":
            ok = bsp.bound
            write_bindings(obj, "BUNDLE", [n for n, o in zip(bnames, ok) if o], bsp.vertices[ok], bsp.bary[ok])
            n_bundles = int(ok.sum())
        else:
            write_bindings(obj, "BUNDLE", [], np.zeros((0, 3)), np.zeros((0, 3)))
        obj.facelab_solve.bind_frame = int(frame)
    finally:
        scene.frame_set(keep)
    # tracks whose chosen surface point reprojects far from their marker in another view: mislabelled or
    # mis-tracked (or the mesh does not match the footage on the bind frame)
    disagree = [n for n, b, e in zip(vd.names, bound, best_e) if b and e > DISAGREE_PX]
    return BindResult(frame=int(frame), bound=names, untracked=untracked, missed=missed, bundles=n_bundles,
                      disagree=disagree, max_err_px=float(best_e[bound].max()) if bound.any() else 0.0,
                      warnings=vd.warnings, time_s=time.perf_counter() - t0)


# --------------------------------------------------------------------------- solve
@dataclass
class _SolveInputs:
    """Everything the core solve needs, in world space at the pose frame."""

    frames: np.ndarray
    views: list
    cameras: list
    names: list
    neutral: np.ndarray
    deltas: np.ndarray
    A: np.ndarray
    tris: np.ndarray
    fixed: np.ndarray
    markers: np.ndarray | None
    marker_names: list
    marker_points: object
    bundles: np.ndarray | None
    bundle_points: object
    loops: object
    curves: list | None
    curve_stats: dict | None
    notes: list


def _has_curve_sources(scene, settings, views) -> bool:
    return any(v.mask is not None or v.sketch is not None for v in views) or (
        0 <= settings.annotation_view < len(views) and compat.scene_annotation(scene) is not None)


def _gather(scene, obj, settings: SolveSettings) -> _SolveInputs:
    from ..core.capture.markers import SurfacePoints
    from ..core.solve.contour_loops import contour_loops

    require_mesh(obj)
    require_editable(obj, "Solve")
    require_scene_time(scene, "Solve", obj)
    frames = frame_range(scene, settings.frame_start, settings.frame_end, "Solve")
    views = require_views(settings.views)
    notes = []
    names, neutral_l, deltas_l = rig_shapes(obj)
    m_names, m_v, m_b = read_bindings(obj, "MARKER")
    b_names, b_v, b_b = read_bindings(obj, "BUNDLE")
    pose_frame = int(frames[0])
    vd = tracking.read_views(scene, views, frames, pose_frame=pose_frame, check_static=obj,
                             track_names=m_names or None)
    notes += vd.warnings
    all_tracks = {t.name for v in views for t in v.clip.tracking.tracks}
    unbound = sorted(all_tracks - set(m_names))
    markers = vd.markers if m_names else None
    if unbound:
        notes.append(f"{len(unbound)} tracks have no mesh binding and are ignored ({', '.join(unbound[:6])}"
                     f"{'...' if len(unbound) > 6 else ''}): press Bind Tracks to use them")
    # bundles (bound by name, mapped into the pose frame's world if the face moves)
    bundles = None
    if settings.bundles != "NONE":
        if not b_names:
            raise BundleError("Bundles are enabled but none is bound to the face; press Bind Tracks (it binds the "
                              "bundles too) or set Bundles to None.")
        bn, P = _read_scene_bundles(scene, settings, frames, views)
        col = {n: i for i, n in enumerate(bn)}
        missing = [n for n in b_names if n not in col]
        if missing:
            raise BundleError(f"Bound bundles {missing[:5]} no longer exist; press Bind Tracks again.")
        P = P[:, [col[n] for n in b_names]]
        Mf = world_matrices(scene, obj, frames)
        M0 = Mf[0] if Mf.shape[0] else np.eye(4)
        if not np.allclose(Mf, Mf[0]):
            loc = np.einsum("tij,tbj->tbi", np.linalg.inv(Mf)[:, :3, :3], P - Mf[:, None, :3, 3])
            P = loc @ M0[:3, :3].T + M0[:3, 3]
        bundles = P
    has_curves = settings.use_contours and _has_curve_sources(scene, settings, views)
    if markers is None and bundles is None and not has_curves:
        raise FaceLabError(
            "Nothing to solve from: no track is bound to the face (press Bind Tracks on a frame where the mesh "
            "matches the footage), no bundles and no contours."
        )
    # rig in world space at the pose frame
    keep = scene.frame_current
    scene.frame_set(pose_frame)
    try:
        A, b = world_affine(obj, evaluated_depsgraph(scene))
    finally:
        scene.frame_set(keep)
    neutral = neutral_l @ A.T + b
    deltas = deltas_l @ A.T
    tris = mesh_triangles(obj.data)
    _, fixed, _ = _skin_triangles(obj, tris, settings.fixed_group)
    loops, curves, curve_stats = None, None, None
    if has_curves:
        ann = settings.annotation_view if 0 <= settings.annotation_view < len(views) else None
        curves, curve_stats = read_curves(scene, views, vd.cameras, frames, annotation_view=ann)
        if curve_stats["frames_with_curves"]:
            up, fwd = face_axes(vd.cameras)
            eyeballs = {}
            for side, g in fl.EYEBALL_GROUPS.items():
                m = vertex_group_mask(obj, g)
                if m is not None and m.sum() >= 4:
                    eyeballs[side] = np.flatnonzero(m)
            eyelid_curves = [k for k in curve_stats["by_name"] if k.startswith("eyelid")]
            if eyelid_curves and not eyeballs:
                notes.append(f"eyelid curves ignored: add vertex groups {fl.EYEBALL_GROUPS['left']} / "
                             f"{fl.EYEBALL_GROUPS['right']} with the eyeball vertices")
                curves = [[c for c in fr if not c.name.startswith("eyelid")] for fr in curves]
            try:
                loops = contour_loops(neutral, tris, fixed=fixed if fixed.any() else None,
                                      eyeballs=eyeballs or None, up=up, forward=fwd)
            except FaceLabError as e:
                raise type(e)(f"{e} (or turn off Contours in FaceLab > Solve to solve from markers only)") from e
        else:
            curves = None
    return _SolveInputs(frames=frames, views=views, cameras=vd.cameras, names=names, neutral=neutral, deltas=deltas,
                        A=A, tris=tris, fixed=fixed, markers=markers, marker_names=m_names,
                        marker_points=SurfacePoints(m_v, m_b) if m_names else None, bundles=bundles,
                        bundle_points=SurfacePoints(b_v, b_b) if bundles is not None else None, loops=loops,
                        curves=curves, curve_stats=curve_stats, notes=notes)


def _missing_markers(g: _SolveInputs, skipped) -> dict:
    """Scene frames where some bound marker was missing/off-screen in every view (solved frames only)."""
    if g.markers is None or g.markers.shape[2] == 0:
        return {}
    seen = np.isfinite(g.markers[..., 0]).any(axis=1)  # (T,M)
    out = {}
    for i in np.flatnonzero(~seen.all(axis=1)):
        if i not in skipped:
            out[int(g.frames[i])] = int((~seen[i]).sum())
    return out


def solve_performance(scene, obj, settings: SolveSettings, progress=None) -> SolveResult:
    """Solve the rig's weights on every frame of the range and key them (Bhat et al. 2013 §4).

    Parameters
    ----------
    scene : bpy.types.Scene
    obj : bpy.types.Object
        The face: a shape-key rig (:func:`facelab_addon.blender.rig.rig_shapes`)
        with bindings from :func:`bind_tracks`.
    settings : SolveSettings
    progress : callable(done, total), optional
        Called after every frame is solved (``done`` frames of ``total``).

    Returns
    -------
    SolveResult
        The rig keys' weights are keyed on the solved frames (in the action
        :func:`~facelab_addon.blender.actions.prepare_action` picks), the
        corrective as compressed keys ``FL_Solve_NN`` (object-local).

    Raises
    ------
    FaceLabError
        Bad input (no rig, no views, nothing bound, cameras moving relative to
        the face...) or no frame could be solved; nothing is written then.
    """
    from ..core.solve.blendshape_solve import BlendshapeSolver, contour_region
    from ..core.solve.corrective import OutOfSubspaceCorrective, lip_band
    from ..core.solve.performance import solve_performance as core_solve

    t0 = time.perf_counter()
    g = _gather(scene, obj, settings)
    t_gather = time.perf_counter() - t0
    fit, corrective, passes = solve_params(settings)
    solver = BlendshapeSolver(g.neutral, g.deltas, g.tris, g.cameras, g.marker_points, g.bundle_points, g.loops,
                              params=fit)
    corr = None
    if settings.use_corrective:
        boundary = OutOfSubspaceCorrective.default_boundary(g.neutral, g.tris, g.marker_points, g.bundle_points)
        region = None if g.loops is None else contour_region(g.neutral, g.tris, g.loops)
        band = lip_band(g.tris, g.loops, len(g.neutral)) if g.loops is not None and g.loops.mouth else None
        corr = OutOfSubspaceCorrective(g.neutral, g.tris, g.cameras, g.marker_points, g.bundle_points,
                                       params=corrective, boundary=boundary | g.fixed, region=region, lip_band=band)
    frames = g.frames
    markers = g.markers
    if markers is None:
        markers = np.full((len(frames), len(g.cameras), 0, 2), np.nan)
    t1 = time.perf_counter()
    # each solved frame's corrective (world, at the pose frame) goes to the writer's disk spool a chunk at a
    # time as an object-local delta; the writer changes nothing in the scene before finish()
    with contextlib.ExitStack() as stack:
        sink, writer = None, None
        if corr is not None:
            writer = stack.enter_context(CorrectionWriter(scene, obj, fl.SOLVE_PREFIX, measured_on="rest"))
            sink = FrameChunks(writer, frames, len(g.neutral), matrix=np.linalg.inv(g.A), fill=False)
        # the core reports the index of the frame just solved; report frames done
        res = core_solve(solver, corr, markers, g.bundles, g.curves, params=passes,
                         progress=(lambda i, n: progress(i + 1, n)) if progress is not None else None,
                         corrective_sink=sink)
        t_fit = time.perf_counter() - t1
        solved = np.array([i for i in range(len(frames)) if i not in res.skipped], dtype=np.int64)
        if len(solved) == 0:
            reasons = sorted(set(res.skipped.values()))
            raise FaceLabError(f"No frame could be solved ({'; '.join(reasons)}); check the tracks cover the range "
                               f"{frames[0]}-{frames[-1]} and are bound (Bind Tracks).")
        # write: weights as ordinary F-curves, correctives as compressed keys (or a cache)
        note = prepare_action(obj.data.shape_keys, g.names, settings.existing_animation, fl.SOLVE_ACTION)
        remove_keys(obj, fl.SOLVE_PREFIX)
        key_values_bulk(obj, g.names, frames[solved], res.weights[solved])
        keys = []
        if writer is not None:
            sink.close()
            keys = StoredKeys.of(writer.finish())
    obj.data.update()
    return SolveResult(frames=frames, solved=frames[solved],
                       skipped={int(frames[i]): r for i, r in res.skipped.items()}, rig_keys=list(g.names),
                       keys=keys, action_note=note, notes=g.notes, missing=_missing_markers(g, res.skipped),
                       curve_stats=g.curve_stats, n_markers=len(g.marker_names), n_views=len(g.views),
                       gather_s=t_gather, fit_s=t_fit, time_s=time.perf_counter() - t0, core=res)
