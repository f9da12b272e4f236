"""Reconstruct from Bundles and Generate Correctives (Cong, Lan & Fedkiw, local geometric indexing).

:func:`reconstruct_from_bundles` rebuilds the face on every frame from
animated 3D bundles and the face's own shape keys (the dataset): by default a
bounded blendshape fit plus the noise-filtered residual at the bundles
(:mod:`facelab_addon.core.lgi.fit_residual`), or the paper's exact local
geometric indexing, optionally with a jaw driving linear blend skinning; the
result is written as compressed ``FL_Recon_*`` keys.
:func:`generate_correctives` adds actor-specific corrective shapes for
combinations of a template rig's shapes (Fig. 7) to the rig, driven by the
product of their components. :func:`bundles_from_clip` turns a Movie Clip's
solved tracks into bundle empties.

Streaming: the core hands each frame's face to the storage writer's disk
spool a chunk at a time (:class:`~facelab_addon.pipeline.streaming.FrameChunks`),
so memory does not grow with the shot; only the per-frame fit (a few numbers
a frame) is kept.

Progress: the per-frame indexing runs inside the core, which reports through
a ``progress(done, total)`` callback; the job is one uninterruptible call, so
there is no step generator.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from .. import names as fl
from ..blender.bundles import (
    bundle_labels,
    bundle_objects,
    empties_from_tracks,
    jaw_poses,
    read_bundles,
    vertex_group_weights,
)
from ..blender.mesh import mesh_triangles, require_mesh
from ..blender.objects import points_to_local, require_editable, triangle_uvs
from ..blender.scene_time import require_scene_time
from ..blender.rig import add_product_driver, dataset_shapes, template_shapes
from ..blender.shapekeys import add_corrective_key, rest_vertices
from ..core.errors import FaceLabError
from .correctives import CorrectionWriter, StoredKeys
from .frames import frame_range
from .settings import setting
from .streaming import FrameChunks

__all__ = [
    "ReconstructSettings",
    "ReconstructResult",
    "CorrectiveSettings",
    "CorrectivesResult",
    "reconstruct_from_bundles",
    "missing_bundles",
    "parse_combinations",
    "generate_correctives",
    "bundles_from_clip",
]


# --------------------------------------------------------------------------- reconstruct
@dataclass
class ReconstructSettings:
    """Options of Reconstruct from Bundles (defaults: FaceLab > Reconstruct's).

    frame_start, frame_end : int or None
        The range (None: the scene's start / end; negative frames are honoured).
    bind_frame : int
        Frame where the face is neutral; the bundles are bound to the surface
        there (-1: the first frame of the range).
    smooth : int
        Central moving average of the barycentric weights over this many frames (1: off).
    method : {"FIT_RESIDUAL", "INDEXING"}
        ``FIT_RESIDUAL`` (default): a bounded blendshape fit of the dataset
        plus the fit's residual at the bundles, spread by natural-neighbour
        weights and filtered by the noise level
        (:class:`~facelab_addon.core.lgi.fit_residual.FitResidual`).
        ``INDEXING``: the paper's local geometric indexing, exact through the
        bundles (:class:`~facelab_addon.core.lgi.indexing.indexer.GeometricIndexer`;
        the only method that uses the jaw settings).
    noise : float
        Bundle noise, standard deviation per axis in millimetres of the
        face's world space (``FIT_RESIDUAL``); negative: estimated from the
        bundles' jitter over the frame range; 0: through every bundle.
    bundle_source : {"SELECTED", "COLLECTION", "MESH"}
        See :func:`facelab_addon.blender.bundles.bundle_objects`; ``selected``
        are the selected objects for ``SELECTED``.
    jaw_source : {"NONE", "BONE", "OBJECT"}
        What drives the jaw: the bone ``jaw_bone`` of ``jaw_armature``, or the
        object ``jaw_object``; the skinning weights are the face's vertex group
        ``jaw_group`` (empty: the bone's name).
    """

    frame_start: int | None = None
    frame_end: int | None = None
    bind_frame: int = setting(-1, label="Bind Frame", min=-1,
                              description="Frame where the face is neutral: bundles are bound to the surface there "
                                          "(-1: the first frame of the range)")
    smooth: int = setting(1, label="Smoothing", min=1, max=15, unit="frames",
                          description="Central moving average of the per-frame weights over this many frames (1: off)")
    method: str = setting("FIT_RESIDUAL", label="Method",
                          description="How the face is rebuilt from the bundles",
                          choices=(("FIT_RESIDUAL", "Fit + Residual",
                                    "Bounded blendshape fit of the shape keys plus the fit's residual at the bundles, "
                                    "spread locally and filtered by the bundle noise (most accurate)"),
                                   ("INDEXING", "Local Indexing (exact)",
                                    "Local geometric indexing: per-bundle dataset shapes, exactly through "
                                    "every bundle; uses the jaw settings")))
    noise: float = setting(-1.0, label="Bundle Noise", min=-1.0, soft_max=2.0, unit="mm",
                           description="Standard deviation of the bundles' noise per axis, in millimetres (-1: "
                                       "estimated from the bundles' jitter; 0: pass exactly through every bundle)")
    bundle_source: str = "SELECTED"
    selected: tuple = ()
    bundle_collection: object = None
    bundle_mesh: object = None
    jaw_source: str = "NONE"
    jaw_armature: object = None
    jaw_bone: str = "jaw"
    jaw_object: object = None
    jaw_group: str = ""


@dataclass
class ReconstructResult:
    """What Reconstruct from Bundles wrote and skipped."""

    frames: np.ndarray     # (T,) scene frames
    keys: list             # corrective keys written (FL_Recon_*)
    skipped: list          # scene frames with missing bundles (shown neutral)
    missing: str           # which bundles were missing on the skipped frames ('' when none was skipped)
    n_bundles: int
    n_shapes: int          # dataset shapes
    jaw: str | None        # what drove the jaw (bone or object name), None without a jaw
    smooth: int
    method: str            # "FIT_RESIDUAL" or "INDEXING"
    noise_mm: float        # the bundle noise used (FIT_RESIDUAL; estimated when the setting is negative), else 0
    live_keys: list        # dataset keys with a non-zero value: they add on top of the reconstruction
    stats: dict            # the reconstructor's statistics (tetrahedra kept for INDEXING, memory, build time...)
    time_s: float


def _frame_range(scene, settings):
    """``(first frame, (T,) frames)`` of the settings' range (None: the scene's start / end)."""
    frames = frame_range(scene, settings.frame_start, settings.frame_end, "Reconstruct")
    return int(frames[0]), frames


def _jaw_setup(scene, obj, settings, neutral, shapes, frames, bind):
    """(JawRig, shape poses (S,4,4), frame poses (T,4,4)) from the jaw settings, or Nones."""
    from ..core.lgi.jaw import JawRig

    if settings.jaw_source == "NONE":
        return None, None, None
    group = settings.jaw_group or (settings.jaw_bone if settings.jaw_source == "BONE" else "")
    w = vertex_group_weights(obj, group) if group else None
    if w is None or w.max() <= 0:
        raise FaceLabError(
            f"The face has no vertex group {group!r} with jaw skinning weights; paint one (1 on the chin and lower "
            "teeth, fading to 0 on the cheeks) and name it in Jaw Weights (for a bone: the bone's name)."
        )
    rig = JawRig(np.zeros(3), [1.0, 0.0, 0.0], w)
    shape_jaw = np.stack([rig.fit_pose(s, neutral) for s in shapes])  # every dataset shape's jaw pose (§6)
    driver = settings.jaw_armature if settings.jaw_source == "BONE" else settings.jaw_object
    J = jaw_poses(scene, obj, frames, bind, source=settings.jaw_source, driver=driver, bone=settings.jaw_bone)
    return rig, shape_jaw, J


def _mm_per_local_unit(scene, obj) -> float:
    """Millimetres of world space per unit of the object's local space (scene unit scale times object scale)."""
    m = np.array(obj.matrix_world.to_3x3(), dtype=np.float64)
    scale = float(np.cbrt(abs(np.linalg.det(m)))) or 1.0
    return 1000.0 * (scene.unit_settings.scale_length or 1.0) * scale


def missing_bundles(Q, labels, skipped) -> str:
    """Which bundles are missing (NaN) on the frame indices ``skipped`` of ``Q`` (T,B,3), for a report."""
    bad = np.flatnonzero((~np.isfinite(Q[skipped])).any(axis=(0, 2)))
    if len(bad) == 0:
        return "no jaw pose"
    return "missing: " + ", ".join(labels[i] for i in bad[:5]) + ("..." if len(bad) > 5 else "")


def reconstruct_from_bundles(scene, obj, settings: ReconstructSettings, progress=None) -> ReconstructResult:
    """Rebuild the face on every frame from animated bundles and its shape-key dataset; key the result.

    Parameters
    ----------
    scene : bpy.types.Scene
    obj : bpy.types.Object
        The face; its shape keys (but FaceLab's) are the dataset.
    settings : ReconstructSettings
    progress : callable(done, total), optional
        Called after every frame is indexed.

    Returns
    -------
    ReconstructResult
        The per-frame displacement from the Basis is written as compressed keys
        ``FL_Recon_NN`` keyed on every frame (neutral on skipped frames).

    Raises
    ------
    FaceLabError
        Bad dataset, no bundles, bundles off the mesh, a missing jaw, or every
        frame missing bundles; nothing is written then.
    """
    from ..core.lgi.binding import bind_points
    from ..core.lgi.fit_residual import FitResidual
    from ..core.lgi.indexing.indexer import GeometricIndexer

    t0 = time.perf_counter()
    f0, frames = _frame_range(scene, settings)
    bind = f0 if settings.bind_frame < 0 else settings.bind_frame
    smooth = settings.smooth
    require_mesh(obj)
    require_editable(obj, "Reconstruct")
    require_scene_time(scene, "Reconstruct", obj)
    tris = mesh_triangles(obj.data)
    neutral = rest_vertices(obj)
    names, shapes = dataset_shapes(obj)
    objs = bundle_objects(settings.selected, settings.bundle_source, collection=settings.bundle_collection,
                          mesh=settings.bundle_mesh, exclude={obj})
    labels = bundle_labels(objs)
    Qw = read_bundles(scene, objs, np.r_[bind, frames])
    q_bind, Q = points_to_local(obj, Qw[0]), points_to_local(obj, Qw[1:])
    bf, bb, _ = bind_points(neutral, tris, q_bind, bundle_names=labels)
    if settings.method not in ("FIT_RESIDUAL", "INDEXING"):
        raise FaceLabError(f"Unknown reconstruction method {settings.method!r}; use 'FIT_RESIDUAL' or 'INDEXING'.")
    noise_mm = 0.0
    jaw, shape_jaw, J = _jaw_setup(scene, obj, settings, neutral, shapes, frames, bind)  # checked for both methods
    uvs = triangle_uvs(obj.data)
    # each frame's displacement from the Basis goes to the writer's disk spool a chunk at a time (skipped
    # frames: zero, the neutral); the writer changes nothing in the scene before finish()
    with CorrectionWriter(scene, obj, fl.RECONSTRUCT_PREFIX, measured_on="rest") as writer:
        sink = FrameChunks(writer, frames, len(neutral), base=neutral, fill=True)
        if settings.method == "INDEXING":
            rec = GeometricIndexer(neutral, tris, shapes, bf, bb, names=names, uvs=uvs, jaw=jaw,
                                   shape_jaw=shape_jaw, bundle_names=labels)
            try:
                skipped = rec.reconstruct_stream(Q, J, sink, smooth=smooth, progress=progress)
            finally:
                rec.close()
        else:
            jaw = None  # the fit takes the jaw from the dataset's jaw shapes
            mm = _mm_per_local_unit(scene, obj)
            rec = FitResidual(neutral, tris, shapes, bf, bb, names=names, uvs=uvs, bundle_names=labels)
            noise = None if settings.noise < 0 else settings.noise / mm
            skipped = rec.reconstruct_stream(Q, sink, noise=noise, smooth=smooth, progress=progress)
            noise_mm = float(rec.noise * mm)
        if len(skipped) == len(frames):
            raise FaceLabError(
                f"Every frame has missing bundles (e.g. {missing_bundles(Q, labels, skipped[:1])}); check the "
                "bundles' animation over the frame range."
            )
        sink.close()
        keys = StoredKeys.of(writer.finish())  # keys, or a cache
    live = [kb.name for kb in obj.data.shape_keys.key_blocks[1:] if not kb.name.startswith(fl.PREFIX) and kb.value]
    jaw_name = None
    if jaw is not None:
        jaw_name = settings.jaw_bone if settings.jaw_source == "BONE" else settings.jaw_object.name
    return ReconstructResult(frames=frames, keys=keys, skipped=[int(frames[i]) for i in skipped],
                             missing=missing_bundles(Q, labels, skipped) if skipped else "", n_bundles=Q.shape[1],
                             n_shapes=len(names), jaw=jaw_name, smooth=smooth, method=settings.method,
                             noise_mm=noise_mm, live_keys=live, stats=dict(rec.stats), time_s=time.perf_counter() - t0)


# --------------------------------------------------------------------------- rig correctives
@dataclass
class CorrectiveSettings:
    """Options of Generate Correctives.

    rig_object : bpy.types.Object
        Mesh whose shape keys are the template rig (the face's vertex order);
        the correctives are added to it.
    combinations : str
        Rig-shape combinations, ``'a+b, c+d+e'`` (see :func:`parse_combinations`).
    n_bundles : int
        Bundles placed automatically over the region the rig moves.
    drivers : bool
        Drive each corrective by the product of its components' values.
    """

    rig_object: object = None
    combinations: str = ""
    n_bundles: int = 100
    drivers: bool = True


@dataclass
class CorrectivesResult:
    """What Generate Correctives added to the rig."""

    rig: str               # the rig object's name
    added: list            # (key name, largest displacement in scene units, goes beyond the dataset somewhere)
    n_dataset: int         # dataset shapes used
    n_bundles: int
    dropped: list          # dataset shapes without rig content, left out
    time_s: float


def parse_combinations(text: str) -> list:
    """'a+b, c+d+e' -> [("a", "b"), ("c", "d", "e")] (commas, semicolons or new lines separate)."""
    out = []
    for part in text.replace(";", ",").replace("\n", ",").split(","):
        names = tuple(n.strip() for n in part.split("+") if n.strip())
        if names:
            out.append(names)
    return out


def generate_correctives(scene, obj, settings: CorrectiveSettings) -> CorrectivesResult:
    """Add a corrective key per combination of template-rig shapes to the rig (Cong et al., Fig. 7).

    The face's own shape keys are the actor's dataset; each corrective is what
    the dataset says the combination adds to the rig's linear sum. New keys
    are named ``FL_Corr_<a>+<b>...`` (never overwriting an existing key).

    Raises
    ------
    FaceLabError
        No rig (or the face itself), no combinations, unknown shape names, a
        rig of another topology; nothing is written then.
    """
    from ..core.lgi.correctives import RigCorrectives

    t0 = time.perf_counter()
    require_mesh(obj)
    rig_obj = settings.rig_object
    if rig_obj is None or rig_obj == obj:
        raise FaceLabError(
            "Pick the template rig (a mesh with the rig's shape keys, same vertex order as the face) in "
            "Reconstruct > Rig; the face's own shape keys are the actor's dataset."
        )
    require_editable(rig_obj, "Generate Correctives")
    combos = parse_combinations(settings.combinations)
    if not combos:
        raise FaceLabError("No combinations: type them as 'shapeA+shapeB, shapeC+shapeD' in Combinations.")
    tris = mesh_triangles(obj.data)
    neutral = rest_vertices(obj)
    names, shapes = dataset_shapes(obj)
    rig = template_shapes(rig_obj, neutral)
    unknown = sorted({n for c in combos for n in c if n not in rig})
    if unknown:
        raise FaceLabError(f"The rig '{rig_obj.name}' has no shape keys {unknown[:5]}; check the names "
                           f"(rig keys: {list(rig)[:8]}...).")
    rc = RigCorrectives(neutral, tris, rig, shapes, dataset_names=names, n_bundles=settings.n_bundles,
                        uvs=triangle_uvs(obj.data))
    try:
        results = [(c,) + rc.corrective(c) for c in combos]
    finally:
        rc.close()
    added = []
    for combo, corr, info in results:
        kb = add_corrective_key(rig_obj, fl.RIG_CORRECTIVE_PREFIX + "+".join(combo), corr)  # unique name
        if settings.drivers:
            add_product_driver(rig_obj.data.shape_keys, kb, combo)
        added.append((kb.name, float(np.linalg.norm(corr, axis=1).max()), info["projected"]))
    return CorrectivesResult(rig=rig_obj.name, added=added, n_dataset=len(rc.dataset_names), n_bundles=rc.indexer.dataset.B,
                             dropped=list(rc.dropped), time_s=time.perf_counter() - t0)


# --------------------------------------------------------------------------- bundles from tracking
def bundles_from_clip(scene, clip) -> list:
    """One bundle empty per solved track of ``clip``, in the collection
    :data:`~facelab_addon.names.BUNDLES_COLLECTION`; returns the new empties.

    The empties sit on Blender's static reconstructed bundles (one 3D point per
    track), constrained to their tracks; animate or re-constrain them per frame
    before Reconstruct.

    Raises
    ------
    FaceLabError
        No clip, or a clip without a valid camera solve.
    """
    if clip is None:
        raise FaceLabError("No Movie Clip: set the scene's active clip (or name one) with a solved camera.")
    return empties_from_tracks(scene, clip)
