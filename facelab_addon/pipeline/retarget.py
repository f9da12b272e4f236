"""Retarget (Bhat et al. 2013, §5.1): carry the actor's solved performance to a creature mesh.

The actor's rig is transferred to the creature by deformation transfer (new
creature keys with the rig's names, created only where missing), the keyed
weights are copied, the actor's per-frame correctives are transferred and
written as compressed ``FL_Retarget_*`` keys (or a point cache, see
:mod:`facelab_addon.pipeline.correctives`), and the lip-sync heuristic
seals the creature's lip corners so its talking portion matches the actor's.

Streaming: the core's :func:`~facelab_addon.core.solve.retarget.retarget_performance`
mixes the actor's correctives from their keys one frame at a time and hands
each frame's creature corrective to a ``corrective_sink`` that spools it to
the storage writer a chunk of frames at a time, so memory does not grow with
the shot.

Progress: the core reports each frame done through a ``progress(done, total)``
callback; the job is one uninterruptible call, so there is no step generator.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from .. import names as fl
from ..blender import tracking
from ..blender.actions import prepare_action
from ..blender.bindings import read_bindings
from ..blender.mesh import mesh_triangles, require_mesh
from ..blender.objects import require_editable, same_polygons
from ..blender.scene_time import require_scene_time
from ..blender.rig import rig_animation
from ..blender.shapekeys import (
    add_corrective_key,
    key_values_bulk,
    remove_keys,
    rest_vertices,
)
from ..core.errors import FaceLabError
from ..core.solve.retarget import RetargetParams
from .correctives import CorrectionWriter, StoredKeys
from .frames import frame_range
from .solve import face_axes
from .streaming import FrameChunks

__all__ = ["RetargetSettings", "RetargetResult", "retarget_params", "retarget"]

_DEFAULTS = RetargetParams()  # the core's defaults: the single source of the defaults below


@dataclass
class RetargetSettings:
    """Options of Retarget (defaults: the core's, see :func:`retarget_params`).

    frame_start, frame_end : int or None
        The range (None: the scene's start / end; negative frames are honoured).
    correspondence : {"AUTO", "TOPOLOGY", "MARKERS"}
        Same topology (vertex i is vertex i), empties on the creature named
        like the actor's bound tracks, or the first when the meshes share
        their polygons and the second otherwise.
    creature_markers : bpy.types.Collection or None
        The empties for ``MARKERS``.
    lip_sync : bool
    lip_threshold : float
        Extra talking length allowed before the corners are sealed, scene units.
    end_points_upper, end_points_lower : (2,) or (T,2) array_like, or None
        Talking portion of each lip set by hand (fractions of its length from
        the left corner), constant or one row per frame of the range; None:
        found automatically.
    existing_animation : {"NEW_ACTION", "REPLACE"}
        See :func:`facelab_addon.blender.actions.prepare_action`.
    views : list of :class:`facelab_addon.blender.tracking.View`
        The tracking cameras; the face's up / forward axes come from those with
        a readable calibration (views without camera or clip are skipped).
    """

    frame_start: int | None = None
    frame_end: int | None = None
    correspondence: str = "AUTO"
    creature_markers: object = None
    lip_sync: bool = _DEFAULTS.lip_sync
    lip_threshold: float = _DEFAULTS.threshold
    end_points_upper: object = None
    end_points_lower: object = None
    existing_animation: str = "NEW_ACTION"
    views: list = field(default_factory=list)


@dataclass
class RetargetResult:
    """What Retarget wrote on the creature."""

    frames: np.ndarray     # (T,) scene frames
    created: list          # creature shape keys transferred from the rig
    kept: list             # rig names the creature already had (its own keys, left as they are)
    keys: list             # corrective keys written (FL_Retarget_*)
    correspondence: str    # "same topology" or "<n> markers"
    action_note: str       # what happened to an existing action ('' when nothing needed saying)
    time_s: float
    core: object = None    # the core's RetargetResult (deltas, end points, info; correctives None: streamed)


def _marker_correspondence(actor, creature, coll, a_rest, ta, c_rest, tc):
    """Triangle correspondence from the creature's empties named like the actor's bound tracks."""
    from ..core.solve.deformation_transfer import triangle_correspondence_from_markers

    if coll is None:
        raise FaceLabError(
            f"'{creature.name}' has no correspondence with '{actor.name}': its topology differs and no Creature "
            "Markers collection is set. Put empties named like the actor's bound tracks on the creature's "
            "matching points, in a collection, and pick it as Creature Markers."
        )
    m_names, m_v, m_b = read_bindings(actor, "MARKER")
    src_vertex = {n: int(v[np.argmax(b)]) for n, v, b in zip(m_names, m_v, m_b)}
    emp = {o.name: o for o in coll.all_objects if o.type == "EMPTY"}
    common = [n for n in m_names if n in emp]
    if len(common) < 4:
        raise FaceLabError(
            f"Only {len(common)} creature marker empties match the actor's bound tracks (need >= 4); name the "
            f"empties in '{coll.name}' like the tracks ({', '.join(m_names[:4])}...) and bind the tracks first."
        )
    Mc = np.array(creature.matrix_world, dtype=np.float64)
    P = np.array([np.array(emp[n].matrix_world, dtype=np.float64)[:3, 3] for n in common])
    P_local = (P - Mc[:3, 3]) @ np.linalg.inv(Mc[:3, :3]).T
    corr = triangle_correspondence_from_markers(a_rest, ta, c_rest, tc, np.array([src_vertex[n] for n in common]),
                                                P_local)
    return corr, f"{len(common)} markers"


def retarget_params(settings: RetargetSettings) -> RetargetParams:
    """The core's retargeting options from Retarget's settings (the one place they are mapped)."""
    return RetargetParams(lip_sync=settings.lip_sync, threshold=settings.lip_threshold)


def _end_points(settings, T):
    """{frame index: EndPoints} from the settings' hand-set talking portions, or None."""
    from ..core.solve.lip_contours import EndPoints

    if not settings.lip_sync or settings.end_points_upper is None or settings.end_points_lower is None:
        return None
    up_ = np.array(np.broadcast_to(np.asarray(settings.end_points_upper, dtype=np.float64), (T, 2)))
    lo_ = np.array(np.broadcast_to(np.asarray(settings.end_points_lower, dtype=np.float64), (T, 2)))
    return {t: EndPoints(up_[t], lo_[t]) for t in range(T)}


def retarget(scene, actor, creature, settings: RetargetSettings, progress=None) -> RetargetResult:
    """Retarget the actor's solved animation to ``creature`` and write it there.

    Parameters
    ----------
    scene : bpy.types.Scene
    actor : bpy.types.Object
        The solved face: a shape-key rig with keyed weights (and ``FL_Solve_*``
        correctives, if any).
    creature : bpy.types.Object
        The mesh to carry the performance to.
    settings : RetargetSettings
    progress : callable(done, total), optional

    Returns
    -------
    RetargetResult
        On the creature: the rig's keys (missing ones created by deformation
        transfer), the weights keyed on the range, the correctives as
        ``FL_Retarget_NN`` keys.

    Raises
    ------
    FaceLabError
        No creature, the face itself, no correspondence, no rig; nothing is
        written then.
    """
    from ..core.solve.retarget import Retargeter, retarget_performance

    t0 = time.perf_counter()
    require_mesh(actor)
    if creature is None:
        raise FaceLabError("No creature: pick the creature mesh in FaceLab > Retarget.")
    require_mesh(creature)
    if creature == actor:
        raise FaceLabError("The creature is the face itself; pick another mesh to retarget to.")
    require_editable(creature, "Retarget")
    require_scene_time(scene, "Retarget", creature)
    frames = frame_range(scene, settings.frame_start, settings.frame_end, "Retarget")
    names, a_rest, a_deltas, W, C = rig_animation(actor, frames, fl.SOLVE_PREFIX, factored=True)
    ta = mesh_triangles(actor.data)
    c_rest = rest_vertices(creature)
    same = same_polygons(actor.data, creature.data)
    tc = ta if same else mesh_triangles(creature.data)  # quads may split along other diagonals: use one triangulation
    mode = settings.correspondence
    corr = None
    how = "same topology"
    if mode == "TOPOLOGY" and not same:
        raise FaceLabError(
            f"'{creature.name}' does not share the topology of '{actor.name}' ({len(c_rest)} vs {len(a_rest)} "
            "vertices): set Correspondence to Markers and mark the actor's tracks on the creature with empties."
        )
    if mode == "MARKERS" or (mode == "AUTO" and not same):
        corr, how = _marker_correspondence(actor, creature, settings.creature_markers, a_rest, ta, c_rest, tc)
    ep = _end_points(settings, len(frames))
    axes = {}
    cams = []
    for v in settings.views:  # the face's up / forward axes from the tracking cameras when they can be read
        if v.camera is None or v.clip is None:
            continue
        try:
            cams.append(tracking.clip_camera(scene, v.camera, v.clip)[0])
        except FaceLabError:
            pass
    if cams:
        up, fwd = face_axes(cams)
        Ai = np.linalg.inv(np.array(actor.matrix_world, dtype=np.float64)[:3, :3])
        axes = dict(up=Ai @ up, forward=Ai @ fwd)
    # each frame's creature corrective goes to the writer's disk spool a chunk at a time (the writer changes
    # nothing in the scene before finish()); the actor's correctives stay factored as keys and values
    with CorrectionWriter(scene, creature, fl.RETARGET_PREFIX, measured_on="rest") as writer:
        sink = FrameChunks(writer, frames, len(c_rest), fill=True)
        rt = Retargeter(a_rest, ta, a_deltas, c_rest, tc, params=retarget_params(settings), correspondence=corr,
                        **axes)
        res = retarget_performance(rt, W, corrective_keys=C, end_points=ep, progress=progress, corrective_sink=sink)
        sink.close()
        # write: the creature's parallel rig (missing keys only), weights, correctives
        created, kept = [], []
        if creature.data.shape_keys is None:
            creature.shape_key_add(name="Basis", from_mix=False)
        existing = set(creature.data.shape_keys.key_blocks.keys())
        for k, n in enumerate(names):
            if n in existing:
                kept.append(n)
            else:
                add_corrective_key(creature, n, res.deltas[k])
                created.append(n)
        note = prepare_action(creature.data.shape_keys, names, settings.existing_animation, fl.RETARGET_ACTION)
        remove_keys(creature, fl.RETARGET_PREFIX)
        key_values_bulk(creature, names, frames, W)
        keys = []
        if res.info["nonzero"]:
            keys = StoredKeys.of(writer.finish())  # keys, or a cache
    creature.data.update()
    return RetargetResult(frames=frames, created=created, kept=kept, keys=keys, correspondence=how,
                          action_note=note, time_s=time.perf_counter() - t0, core=res)
