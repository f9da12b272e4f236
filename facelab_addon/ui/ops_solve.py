"""Operators for the contour-based performance solve and retargeting (Bhat et al. 2013, §4-5).

Add View / Remove View manage the tracking cameras (``Scene.facelab_solve.views``);
Bind Tracks ties each track (and bundle) to the face surface on a reference
frame; Solve Performance writes shape-key weight animation (ordinary F-curves)
plus compressed per-frame correctives (``FL_Solve_*`` keys); Retarget carries
the result to a creature mesh. Operators gather inputs through the
``blender/`` adapters, call the core, write, and report; no math here beyond
moving arrays between spaces.

Spaces: the solve runs in world space at the pose frame (cameras are world
objects). The rig (Basis and shape-key deltas, object-local) is mapped there
with the face's ``matrix_world`` (affine maps keep blendshape weights), and
the correctives are mapped back to object-local deltas.
"""

from __future__ import annotations

import time

import bpy
import numpy as np
from bpy.props import IntProperty

from ..blender import tracking
from ..blender.bundles import bundle_labels, read_bundles
from ..blender.camera import evaluated_depsgraph
from ..blender.masks import read_curves
from ..blender.mesh import default_fixed_mask, evaluated_vertices, mesh_triangles, require_mesh, vertex_group_mask
from ..blender.shapekeys import add_corrective_key, add_keys_from_deltas, key_values_bulk, remove_keys, rest_vertices
from ..core.errors import BundleError, CameraError, FaceLabError
from ..core.geometry.compress import compress
from .ops import face_object, poll_face, progress_callback
from .props_solve import read_bindings, write_bindings

SOLVE_PREFIX = "FL_Solve_"
RETARGET_PREFIX = "FL_Retarget_"
SOLVE_ACTION = "FL_Solve"
RETARGET_ACTION = "FL_Retarget"
ACTION_TAG = "facelab_solve"  # custom property marking actions FaceLab made (re-runs replace them in place)
DISAGREE_PX = 3.0  # Bind Tracks flags tracks whose bound point misses their marker in another view by more
EYEBALL_GROUPS = {"left": "FL_eyeball_left", "right": "FL_eyeball_right"}

# Last solve's timings and counts (for tests and the benchmark).
LAST: dict = {}
# What each operator's worker returned on its last successful run, by operator name ("solve_performance"...):
# the numbers behind the one-sentence reports, for the batch CLI's JSON summary.
RESULTS: dict = {}


# --------------------------------------------------------------------------- gathering
def solve_settings(context):
    return context.scene.facelab_solve


def solve_views(scene) -> list:
    """The scene's solve views as ``tracking.View``; each must have a camera and a clip."""
    out = []
    for i, v in enumerate(scene.facelab_solve.views):
        if v.camera is None:
            raise CameraError(f"Solve view {i + 1} has no camera; pick its camera object in FaceLab > Solve > Views.")
        if v.clip is None:
            raise CameraError(
                f"Camera '{v.camera.name}' (view {i + 1}) has no Movie Clip; pick the footage it filmed in FaceLab > "
                "Solve > Views (open it in the Clip editor first)."
            )
        out.append(tracking.View(v.camera, v.clip, mask=v.mask, sketch=v.sketch, name=v.camera.name))
    if not out:
        raise CameraError(
            "No solve views: press Add View in FaceLab > Solve with the tracking camera as the scene camera and its "
            "footage as the scene's active clip (or pick them in the list)."
        )
    return out


def frame_range(scene, s) -> np.ndarray:
    f0 = scene.frame_start if s.frame_start < 0 else s.frame_start
    f1 = scene.frame_end if s.frame_end < 0 else s.frame_end
    if f1 < f0:
        raise FaceLabError(f"The solve range {f0}-{f1} is empty; set End >= Start (FaceLab > Solve).")
    return np.arange(f0, f1 + 1)


def rig_shapes(obj):
    """``(names, neutral (V,3), deltas (S,V,3))`` of the rig, object-local.

    The rig is the object's shape keys except the Basis, muted keys and
    FaceLab's own keys (``FL_*``); each delta is relative to its key's
    relative key.
    """
    key = obj.data.shape_keys
    if key is None or len(key.key_blocks) < 2:
        raise FaceLabError(
            f"'{obj.name}' has no shape keys: the solve needs a blendshape rig. Add the expressions as shape keys "
            "(Object Data > Shape Keys) on top of a Basis."
        )
    if not key.use_relative:
        raise FaceLabError(f"The shape keys of '{obj.name}' are absolute; enable Relative in Object Data > Shape Keys.")
    n = len(obj.data.vertices)
    basis = key.reference_key

    def co(kb):
        a = np.empty(3 * n, np.float32)
        kb.data.foreach_get("co", a)
        return a.reshape(n, 3).astype(np.float64)

    names, deltas = [], []
    for kb in key.key_blocks:
        if kb == basis or kb.mute or kb.name.startswith("FL_"):
            continue
        names.append(kb.name)
        deltas.append(co(kb) - co(kb.relative_key))
    if not names:
        raise FaceLabError(
            f"'{obj.name}' has only a Basis (or only muted / FaceLab keys): add the blendshape expressions as shape "
            "keys to solve for."
        )
    return names, co(basis), np.stack(deltas)


def _affine(obj, depsgraph=None):
    M = np.array((obj.evaluated_get(depsgraph) if depsgraph else obj).matrix_world, dtype=np.float64)
    return M[:3, :3], M[:3, 3]


def skin_triangles(obj, tris, scene):
    """(F,) bool: triangles that may carry markers/contours (no fixed vertex: teeth, eyes, mouth bag...)."""
    fixed, src = default_fixed_mask(obj, tris, scene.facelab.fixed_group)
    return ~fixed[tris].any(axis=1), fixed, src


def face_axes(cameras):
    """World ``(up, forward)`` of the face from the cameras looking at it."""
    fwd = -np.mean([c.forward for c in cameras], axis=0)
    up = -np.mean([c.R[1] for c in cameras], axis=0)  # OpenCV y is down
    return up / np.linalg.norm(up), fwd / np.linalg.norm(fwd)


def _bundle_objects(scene):
    s = scene.facelab_solve
    coll = s.bundle_collection or bpy.data.collections.get("FL_bundles")
    objs = sorted([o for o in coll.all_objects if o.type in ("EMPTY", "MESH")], key=lambda o: o.name) if coll else []
    if not objs:
        raise BundleError(
            "Bundles are set to Empties but there are none: put the bundle empties in a collection and pick it as "
            "the Bundle Collection (or name it 'FL_bundles'), or set Bundles to None."
        )
    return objs


def read_scene_bundles(scene, frames, views):
    """``(names, (T,B,3) world positions)`` of the configured bundle source, or ``(None, None)``."""
    s = scene.facelab_solve
    if s.bundles == "NONE":
        return None, None
    if s.bundles == "TRACKING":
        pts, names = tracking.clip_bundles(views[0].clip)
        return names, np.broadcast_to(pts, (len(frames),) + pts.shape).copy()
    objs = _bundle_objects(scene)
    return bundle_labels(objs), read_bundles(scene, objs, frames)


def _face_matrices(scene, obj, frames):
    """(T,4,4) world matrices of the face on ``frames`` (one read when it is not animated)."""
    keep = scene.frame_current
    probe = sorted({int(frames[0]), int(frames[len(frames) // 2]), int(frames[-1])})
    mats = {}
    try:
        for f in probe:
            scene.frame_set(f)
            mats[f] = np.array(obj.evaluated_get(evaluated_depsgraph(scene)).matrix_world, dtype=np.float64)
        if all(np.allclose(mats[f], mats[probe[0]], atol=1e-9) for f in probe):
            return np.broadcast_to(mats[probe[0]], (len(frames), 4, 4))
        out = []
        for f in frames:
            scene.frame_set(int(f))
            out.append(np.array(obj.evaluated_get(evaluated_depsgraph(scene)).matrix_world, dtype=np.float64))
        return np.stack(out)
    finally:
        scene.frame_set(keep)


# --------------------------------------------------------------------------- actions
def _fcurve_paths(action):
    paths = set()
    for layer in getattr(action, "layers", ()):
        for strip in layer.strips:
            for cb in strip.channelbags:
                paths.update(fc.data_path for fc in cb.fcurves)
    return paths


def _key_path(name):
    return f'key_blocks["{bpy.utils.escape_identifier(name)}"].value'


def prepare_action(key, names, mode: str, action_name: str) -> str:
    """Make sure writing the rig keys' curves never silently destroys the artist's animation.

    * no action: a new one ``action_name`` (tagged as FaceLab's);
    * FaceLab's own action (a previous run): reused, its curves replaced;
    * an artist's action animating none of ``names``: written into in place;
    * an artist's action animating some of ``names``: ``mode == 'NEW_ACTION'``
      copies it to ``action_name`` (everything else keeps playing), keeps the
      original with a fake user and assigns the copy; ``'REPLACE'`` writes
      into it.

    Returns a note for the report ('' when nothing needed saying).
    """
    ad = key.animation_data or key.animation_data_create()
    act = ad.action
    if act is None:
        act = bpy.data.actions.new(action_name)
        act[ACTION_TAG] = True
        ad.action = act
        return ""
    if act.get(ACTION_TAG):
        return ""
    animated = sorted(n for n in names if _key_path(n) in _fcurve_paths(act))
    if not animated:
        return ""
    if mode == "REPLACE":
        return f"replaced the curves of {len(animated)} animated keys in action '{act.name}'"
    slot_id = ad.action_slot.identifier if ad.action_slot is not None else None
    new = act.copy()
    new.name = action_name
    new[ACTION_TAG] = True
    act.use_fake_user = True
    ad.action = new
    if ad.action_slot is None and len(new.slots):
        match = [s for s in new.slots if s.identifier == slot_id]
        ad.action_slot = match[0] if match else new.slots[0]
    return (f"kept your action '{act.name}' (fake user; {len(animated)} keys were animated) and wrote the result "
            f"to the new action '{new.name}'")


def _curve_values(key, names, frames):
    """(T,K) values of shape keys ``names`` on ``frames`` from their F-curves (constant value if not animated)."""
    from bpy_extras import anim_utils

    ad = key.animation_data
    cb = None
    if ad is not None and ad.action is not None and ad.action_slot is not None:
        cb = anim_utils.action_get_channelbag_for_slot(ad.action, ad.action_slot)
    out = np.empty((len(frames), len(names)))
    for k, n in enumerate(names):
        fc = cb.fcurves.find(_key_path(n)) if cb is not None else None
        if fc is not None and not fc.mute:
            out[:, k] = [fc.evaluate(float(f)) for f in frames]
        else:
            out[:, k] = key.key_blocks[n].value
    return out


def _scene_vector_values(scene, path, current, frames):
    """(T,n) values of a scene vector property on ``frames``: its F-curves if keyed, else ``current``."""
    from bpy_extras import anim_utils

    cur = np.array(current, dtype=np.float64)
    out = np.broadcast_to(cur, (len(frames), len(cur))).copy()
    ad = scene.animation_data
    if ad is None or ad.action is None or ad.action_slot is None:
        return out
    cb = anim_utils.action_get_channelbag_for_slot(ad.action, ad.action_slot)
    for i in range(len(cur)):
        fc = cb.fcurves.find(path, index=i) if cb is not None else None
        if fc is not None and not fc.mute:
            out[:, i] = [fc.evaluate(float(f)) for f in frames]
    return out


# --------------------------------------------------------------------------- bind
def bind_tracks(context, obj, bind_frame: int) -> dict:
    """Bind every track (and bundle) to the face surface on ``bind_frame``; store on ``obj``."""
    from ..core.capture.markers import bind_surface_points, nearest_surface_points

    scene = context.scene
    require_mesh(obj)
    views = solve_views(scene)
    keep = scene.frame_current
    scene.frame_set(int(bind_frame))
    try:
        vd = tracking.read_views(scene, views, [bind_frame])
        dg = evaluated_depsgraph(scene)
        V = evaluated_vertices(obj, dg)
        tris = mesh_triangles(obj.data)
        fmask, _, _ = skin_triangles(obj, tris, scene)
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
        names = [n for n, b in zip(vd.names, bound) if b]
        write_bindings(obj, "MARKER", names, best_v[bound], best_b[bound])
        untracked = [n for n, t in zip(vd.names, tracked.any(axis=0)) if not t]
        missed = [n for n, t, b in zip(vd.names, tracked.any(axis=0), bound) if t and not b]
        n_bundles = 0
        if scene.facelab_solve.bundles != "NONE":
            bnames, P = read_scene_bundles(scene, [bind_frame], views)
            sp = nearest_surface_points(V, tris, P[0], face_mask=fmask)
            ok = sp.bound
            write_bindings(obj, "BUNDLE", [n for n, o in zip(bnames, ok) if o], sp.vertices[ok], sp.bary[ok])
            n_bundles = int(ok.sum())
        else:
            write_bindings(obj, "BUNDLE", [], np.zeros((0, 3)), np.zeros((0, 3)))
        obj.facelab_solve.bind_frame = int(bind_frame)
    finally:
        scene.frame_set(keep)
    # tracks whose chosen surface point reprojects far from their marker in another view: mislabelled or
    # mis-tracked (or the mesh does not match the footage on the bind frame)
    disagree = [n for n, b, e in zip(vd.names, bound, best_e) if b and e > DISAGREE_PX]
    return dict(bound=names, untracked=untracked, missed=missed, bundles=n_bundles, warnings=vd.warnings,
                disagree=disagree, max_err_px=float(best_e[bound].max()) if bound.any() else 0.0)


# --------------------------------------------------------------------------- solve
def gather_solve_inputs(context, obj) -> dict:
    """Everything the core solve needs, in world space at the pose frame."""
    from ..core.capture.markers import SurfacePoints
    from ..core.solve.contour_loops import contour_loops

    scene = context.scene
    s = scene.facelab_solve
    require_mesh(obj)
    frames = frame_range(scene, s)
    views = solve_views(scene)
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
    markers = None
    if m_names:
        markers = vd.markers
    if unbound:
        notes.append(f"{len(unbound)} tracks have no mesh binding and are ignored ({', '.join(unbound[:6])}"
                     f"{'...' if len(unbound) > 6 else ''}): press Bind Tracks to use them")
    # bundles (bound by name, mapped into the pose frame's world if the face moves)
    bundles = None
    if s.bundles != "NONE":
        if not b_names:
            raise BundleError("Bundles are enabled but none is bound to the face; press Bind Tracks (it binds the "
                              "bundles too) or set Bundles to None.")
        bn, P = read_scene_bundles(scene, frames, views)
        col = {n: i for i, n in enumerate(bn)}
        missing = [n for n in b_names if n not in col]
        if missing:
            raise BundleError(f"Bound bundles {missing[:5]} no longer exist; press Bind Tracks again.")
        P = P[:, [col[n] for n in b_names]]
        Mf = _face_matrices(scene, obj, frames)
        M0 = Mf[0] if Mf.shape[0] else np.eye(4)
        if not np.allclose(Mf, Mf[0]):
            loc = np.einsum("tij,tbj->tbi", np.linalg.inv(Mf)[:, :3, :3], P - Mf[:, None, :3, 3])
            P = loc @ M0[:3, :3].T + M0[:3, 3]
        bundles = P
    if markers is None and bundles is None and not (s.use_contours and _has_curve_sources(scene, views)):
        raise FaceLabError(
            "Nothing to solve from: no track is bound to the face (press Bind Tracks on a frame where the mesh "
            "matches the footage), no bundles and no contours."
        )
    # rig in world space at the pose frame
    keep = scene.frame_current
    scene.frame_set(pose_frame)
    try:
        A, b = _affine(obj, evaluated_depsgraph(scene))
    finally:
        scene.frame_set(keep)
    neutral = neutral_l @ A.T + b
    deltas = deltas_l @ A.T
    tris = mesh_triangles(obj.data)
    fmask, fixed, fixed_src = skin_triangles(obj, tris, scene)
    loops, curves, curve_stats = None, None, None
    if s.use_contours and _has_curve_sources(scene, views):
        ann = s.annotation_view if 0 <= s.annotation_view < len(views) else None
        curves, curve_stats = read_curves(scene, views, vd.cameras, frames, annotation_view=ann)
        if curve_stats["frames_with_curves"]:
            up, fwd = face_axes(vd.cameras)
            eyeballs = {}
            for side, g in EYEBALL_GROUPS.items():
                m = vertex_group_mask(obj, g)
                if m is not None and m.sum() >= 4:
                    eyeballs[side] = np.flatnonzero(m)
            eyelid_curves = [k for k in curve_stats["by_name"] if k.startswith("eyelid")]
            if eyelid_curves and not eyeballs:
                notes.append(f"eyelid curves ignored: add vertex groups {EYEBALL_GROUPS['left']} / "
                             f"{EYEBALL_GROUPS['right']} with the eyeball vertices")
                curves = [[c for c in fr if not c.name.startswith("eyelid")] for fr in curves]
            try:
                loops = contour_loops(neutral, tris, fixed=fixed if fixed.any() else None,
                                      eyeballs=eyeballs or None, up=up, forward=fwd)
            except FaceLabError as e:
                raise type(e)(f"{e} (or turn off Contours in FaceLab > Solve to solve from markers only)") from e
        else:
            curves = None
    return dict(frames=frames, views=views, cameras=vd.cameras, names=names, neutral=neutral, deltas=deltas,
                A=A, b=b, tris=tris, fixed=fixed, fmask=fmask, markers=markers, marker_names=m_names,
                marker_points=SurfacePoints(m_v, m_b) if m_names else None, bundles=bundles,
                bundle_points=SurfacePoints(b_v, b_b) if bundles is not None else None, loops=loops,
                curves=curves, curve_stats=curve_stats, notes=notes, fixed_src=fixed_src)


def _has_curve_sources(scene, views) -> bool:
    s = scene.facelab_solve
    return any(v.mask is not None or v.sketch is not None for v in views) or (
        0 <= s.annotation_view < len(views) and scene.annotation is not None)


def solve(context, obj, progress=None) -> dict:
    """Run the solve and write its animation. Returns a summary for the report."""
    from ..core.solve.blendshape_solve import BlendshapeSolver
    from ..core.solve.corrective import OutOfSubspaceCorrective
    from ..core.solve.performance import solve_performance

    scene = context.scene
    s = scene.facelab_solve
    t0 = time.perf_counter()
    g = gather_solve_inputs(context, obj)
    t_gather = time.perf_counter() - t0
    solver = BlendshapeSolver(g["neutral"], g["deltas"], g["tris"], g["cameras"], g["marker_points"],
                              g["bundle_points"], g["loops"], bounds=(s.weight_min, s.weight_max),
                              marker_weight=s.marker_weight, contour_weight=s.contour_weight)
    corr = None
    if s.use_corrective:
        boundary = OutOfSubspaceCorrective.default_boundary(g["neutral"], g["tris"], g["marker_points"],
                                                            g["bundle_points"])
        corr = OutOfSubspaceCorrective(g["neutral"], g["tris"], g["cameras"], g["marker_points"], g["bundle_points"],
                                       boundary=boundary | g["fixed"])
    frames = g["frames"]
    markers = g["markers"]
    if markers is None:
        markers = np.full((len(frames), len(g["cameras"]), 0, 2), np.nan)
    t1 = time.perf_counter()
    res = solve_performance(solver, corr, markers, g["bundles"], g["curves"], progress=progress, sliding=s.sliding)
    t_solve = time.perf_counter() - t1
    solved = np.array([i for i in range(len(frames)) if i not in res.skipped], dtype=np.int64)
    if len(solved) == 0:
        reasons = sorted(set(res.skipped.values()))
        raise FaceLabError(f"No frame could be solved ({'; '.join(reasons)}); check the tracks cover the range "
                           f"{frames[0]}-{frames[-1]} and are bound (Bind Tracks).")
    # write: weights as ordinary F-curves, correctives as compressed keys
    key = obj.data.shape_keys
    note = prepare_action(key, g["names"], s.existing_animation, SOLVE_ACTION)
    remove_keys(obj, SOLVE_PREFIX)
    key_values_bulk(obj, g["names"], frames[solved], res.weights[solved])
    keys = []
    if res.correctives is not None:
        Ainv = np.linalg.inv(g["A"])
        D = res.correctives[solved] @ Ainv.T
        basis, cw = compress(D, metres_per_unit=scene.unit_settings.scale_length or 1.0)
        if len(basis):
            keys = add_keys_from_deltas(obj, SOLVE_PREFIX, basis)
            key_values_bulk(obj, keys, frames[solved], cw)
    obj.data.update()
    # report data
    offscreen = _missing_markers(g, res)
    LAST.clear()
    LAST.update(gather_s=t_gather, solve_s=t_solve, total_s=time.perf_counter() - t0, info=res.info)
    return dict(frames=frames, solved=frames[solved], skipped={int(frames[i]): r for i, r in res.skipped.items()},
                keys=keys, action_note=note, notes=g["notes"], missing=offscreen, curve_stats=g["curve_stats"],
                n_markers=len(g["marker_names"]), n_views=len(g["views"]), time_s=time.perf_counter() - t0,
                result=res)


def _missing_markers(g, res) -> dict:
    """Frames (scene numbers) where some bound marker was missing/off-screen in every view."""
    if g["markers"] is None or g["markers"].shape[2] == 0:
        return {}
    seen = np.isfinite(g["markers"][..., 0]).any(axis=1)  # (T,M)
    out = {}
    for i in np.flatnonzero(~seen.all(axis=1)):
        if i not in res.skipped:
            out[int(g["frames"][i])] = int((~seen[i]).sum())
    return out


def _summarise_skips(skipped: dict) -> str:
    by = {}
    for f, r in skipped.items():
        by.setdefault(r, []).append(f)
    return "; ".join(f"{len(v)} skipped: {r} ({', '.join(map(str, v[:5]))}{'...' if len(v) > 5 else ''})"
                     for r, v in by.items())


# --------------------------------------------------------------------------- retarget
def actor_performance(scene, obj, frames):
    """The actor's animation as the core needs it: rig, (T,S) weights, (T,V,3) correctives (object-local)."""
    names, neutral, deltas = rig_shapes(obj)
    key = obj.data.shape_keys
    W = _curve_values(key, names, frames)
    sk = [kb for kb in key.key_blocks if kb.name.startswith(SOLVE_PREFIX)]
    C = None
    if sk:
        n = len(neutral)
        basis = np.empty((len(sk), n, 3))
        for i, kb in enumerate(sk):
            a = np.empty(3 * n, np.float32)
            kb.data.foreach_get("co", a)
            basis[i] = a.reshape(n, 3) - neutral
        cw = _curve_values(key, [kb.name for kb in sk], frames)
        C = np.einsum("tr,rvd->tvd", cw, basis)
    return names, neutral, deltas, W, C


def same_polygons(me_a, me_b) -> bool:
    """Whether two meshes share their topology: vertex count and every polygon's vertex list."""
    if len(me_a.vertices) != len(me_b.vertices) or len(me_a.loops) != len(me_b.loops) \
            or len(me_a.polygons) != len(me_b.polygons):
        return False
    out = []
    for me in (me_a, me_b):
        lv = np.empty(len(me.loops), np.int32)
        me.loops.foreach_get("vertex_index", lv)
        ls = np.empty(len(me.polygons), np.int32)
        me.polygons.foreach_get("loop_start", ls)
        out.append((lv, ls))
    return bool(np.array_equal(out[0][0], out[1][0]) and np.array_equal(out[0][1], out[1][1]))


def retarget(context, actor, creature, progress=None) -> dict:
    """Retarget the actor's solved animation to ``creature`` and write it there."""
    from ..core.solve.deformation_transfer import triangle_correspondence_from_markers
    from ..core.solve.lip_contours import EndPoints
    from ..core.solve.retarget import retarget_performance

    scene = context.scene
    s = scene.facelab_solve
    t0 = time.perf_counter()
    require_mesh(actor)
    if creature is None:
        raise FaceLabError("No creature: pick the creature mesh in FaceLab > Retarget.")
    require_mesh(creature)
    if creature == actor:
        raise FaceLabError("The creature is the face itself; pick another mesh to retarget to.")
    frames = frame_range(scene, s)
    names, a_rest, a_deltas, W, C = actor_performance(scene, actor, frames)
    ta = mesh_triangles(actor.data)
    c_rest = rest_vertices(creature)
    same = same_polygons(actor.data, creature.data)
    tc = ta if same else mesh_triangles(creature.data)  # quads may split along other diagonals: use one triangulation
    mode = s.correspondence
    corr = None
    how = "same topology"
    if mode == "TOPOLOGY" and not same:
        raise FaceLabError(
            f"'{creature.name}' does not share the topology of '{actor.name}' ({len(c_rest)} vs {len(a_rest)} "
            "vertices): set Correspondence to Markers and mark the actor's tracks on the creature with empties."
        )
    if mode == "MARKERS" or (mode == "AUTO" and not same):
        coll = s.creature_markers
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
        how = f"{len(common)} markers"
    ep = None
    if s.lip_sync and s.use_end_points:
        up_ = _scene_vector_values(scene, "facelab_solve.end_points_upper", s.end_points_upper, frames)
        lo_ = _scene_vector_values(scene, "facelab_solve.end_points_lower", s.end_points_lower, frames)
        ep = {t: EndPoints(up_[t], lo_[t]) for t in range(len(frames))}
    kw = {}
    views = [v for v in scene.facelab_solve.views if v.camera is not None and v.clip is not None]
    cams = []
    for v in views:  # the face's up / forward axes from the tracking cameras when they can be read
        try:
            cams.append(tracking.clip_camera(scene, v.camera, v.clip)[0])
        except FaceLabError:
            pass
    if cams:
        up, fwd = face_axes(cams)
        A = np.array(actor.matrix_world, dtype=np.float64)[:3, :3]
        Ai = np.linalg.inv(A)
        kw = dict(up=Ai @ up, forward=Ai @ fwd)
    res = retarget_performance(a_rest, ta, a_deltas, W, c_rest, tc, correctives=C, correspondence=corr,
                               lip_sync=s.lip_sync, threshold=s.lip_threshold, end_points=ep, progress=progress,
                               **kw)
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
    note = prepare_action(creature.data.shape_keys, names, s.existing_animation, RETARGET_ACTION)
    remove_keys(creature, RETARGET_PREFIX)
    key_values_bulk(creature, names, frames, W)
    keys = []
    if np.any(res.correctives):
        basis, cw = compress(res.correctives.astype(np.float64), metres_per_unit=scene.unit_settings.scale_length or 1.0)
        if len(basis):
            keys = add_keys_from_deltas(creature, RETARGET_PREFIX, basis)
            key_values_bulk(creature, keys, frames, cw)
    creature.data.update()
    return dict(frames=frames, created=created, kept=kept, keys=keys, correspondence=how, action_note=note,
                time_s=time.perf_counter() - t0, result=res)


# --------------------------------------------------------------------------- operators
class FACELAB_OT_solve_add_view(bpy.types.Operator):
    """Add a tracking camera: the scene camera and the scene's active Movie Clip (edit them in the list)"""

    bl_idname = "facelab.solve_add_view"
    bl_label = "Add View"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        scene = context.scene
        s = scene.facelab_solve
        used = {v.camera for v in s.views}
        cam = scene.camera if scene.camera not in used else None
        if cam is None:
            cam = next((o for o in scene.objects if o.type == "CAMERA" and o not in used), None)
        v = s.views.add()
        v.camera = cam
        v.clip = scene.active_clip
        s.active_view_index = len(s.views) - 1
        missing = [w for w, x in (("camera", v.camera), ("movie clip", v.clip)) if x is None]
        if missing:
            self.report({"WARNING"}, f"View {len(s.views)} added without a {' and '.join(missing)}; pick them in the list")
        else:
            self.report({"INFO"}, f"View {len(s.views)}: camera '{v.camera.name}', clip '{v.clip.name}'")
        return {"FINISHED"}


class FACELAB_OT_solve_remove_view(bpy.types.Operator):
    """Remove the selected tracking camera from the solve"""

    bl_idname = "facelab.solve_remove_view"
    bl_label = "Remove View"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        if not len(context.scene.facelab_solve.views):
            cls.poll_message_set("No views to remove")
            return False
        return True

    def execute(self, context):
        s = context.scene.facelab_solve
        i = min(s.active_view_index, len(s.views) - 1)
        s.views.remove(i)
        s.active_view_index = max(0, i - 1)
        return {"FINISHED"}


class FACELAB_OT_bind_tracks(bpy.types.Operator):
    """Tie every track (and bundle) to the face surface: on the bind frame, each marker's camera ray is cast onto the mesh (Bhat et al. 2013 §4.1); bundles take their nearest surface point"""

    bl_idname = "facelab.bind_tracks"
    bl_label = "Bind Tracks"
    bl_options = {"REGISTER", "UNDO"}

    frame: IntProperty(name="Frame", default=-1, description="Bind frame (-1: FaceLab > Solve > Bind Frame, "
                                                             "or the current frame)")

    @classmethod
    def poll(cls, context):
        if not poll_face(cls, context):
            return False
        if not len(context.scene.facelab_solve.views):
            cls.poll_message_set("Add a view (tracking camera + Movie Clip) first")
            return False
        return True

    def execute(self, context):
        scene = context.scene
        f = self.frame if self.frame >= 0 else scene.facelab_solve.bind_frame
        f = scene.frame_current if f < 0 else f
        obj = face_object(context)
        try:
            r = bind_tracks(context, obj, f)
            RESULTS["bind_tracks"] = r
        except FaceLabError as e:
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        n_all = len(r["bound"]) + len(r["missed"]) + len(r["untracked"])
        msg = f"Bound {len(r['bound'])} of {n_all} tracks to '{obj.name}' on frame {f}"
        if r["bundles"]:
            msg += f", {r['bundles']} bundles"
        if r["missed"]:
            msg += f"; missed the face: {', '.join(r['missed'][:8])}{'...' if len(r['missed']) > 8 else ''}"
        if r["untracked"]:
            msg += (f"; no marker on frame {f}: {', '.join(r['untracked'][:8])}"
                    f"{'...' if len(r['untracked']) > 8 else ''} (bind on a frame where they are tracked)")
        if r["disagree"]:
            msg += (f"; the views disagree by more than {DISAGREE_PX:g} px on {', '.join(r['disagree'][:8])}"
                    f"{'...' if len(r['disagree']) > 8 else ''} (same name for different markers, a tracking slip, "
                    "or the mesh does not match the footage on this frame)")
        if r["warnings"]:
            msg += "; " + "; ".join(r["warnings"])
        warn = r["missed"] or r["untracked"] or r["warnings"] or r["disagree"]
        self.report({"WARNING"} if warn else {"INFO"}, msg)
        return {"FINISHED"} if r["bound"] or r["bundles"] else {"CANCELLED"}


class FACELAB_OT_solve_performance(bpy.types.Operator):
    """Solve blendshape weights for every frame from the bound tracks, bundles and lip/eyelid contours (Bhat et al. 2013 §4), keyed as ordinary F-curves, plus a per-frame corrective as FL_Solve_ shape keys"""

    bl_idname = "facelab.solve_performance"
    bl_label = "Solve Performance"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        if not poll_face(cls, context):
            return False
        if not len(context.scene.facelab_solve.views):
            cls.poll_message_set("Add a view (tracking camera + Movie Clip) first")
            return False
        if context.mode != "OBJECT":
            cls.poll_message_set("Switch to Object Mode to solve")
            return False
        return True

    def execute(self, context):
        obj = face_object(context)
        try:
            frames = frame_range(context.scene, context.scene.facelab_solve)
            prog = progress_callback(context, len(frames), "FaceLab Solve")
            r = solve(context, obj, progress=lambda i, n: prog(i + 1, n))  # the solver reports the frame index
            RESULTS["solve_performance"] = r
        except FaceLabError as e:
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        finally:
            context.window_manager.progress_end()
        msg = f"Solved {len(r['solved'])} frames in {r['time_s']:.1f} s"
        if r["skipped"]:
            msg += f" ({_summarise_skips(r['skipped'])})"
        msg += f", {len(r['keys'])} corrective shapes" if context.scene.facelab_solve.use_corrective else ""
        if r["curve_stats"] and r["curve_stats"]["frames_with_curves"]:
            msg += f", contours on {r['curve_stats']['frames_with_curves']} frames"
        if r["missing"]:
            fr = sorted(r["missing"])
            msg += (f"; markers missing or off-screen on {len(fr)} frames (those markers skipped: "
                    f"{', '.join(map(str, fr[:6]))}{'...' if len(fr) > 6 else ''})")
        for n in [r["action_note"]] + r["notes"]:
            if n:
                msg += f"; {n}"
        warn = bool(r["skipped"] or r["missing"] or r["notes"])
        self.report({"WARNING"} if warn else {"INFO"}, msg)
        return {"FINISHED"}


class FACELAB_OT_retarget(bpy.types.Operator):
    """Carry the solved performance to the creature (Bhat et al. 2013 §5.1): transfer the blendshapes by deformation transfer, copy the weights, transfer the correctives, and keep the lips talking (lip-sync heuristic)"""

    bl_idname = "facelab.retarget"
    bl_label = "Retarget"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        if not poll_face(cls, context):
            return False
        if context.scene.facelab_solve.creature is None:
            cls.poll_message_set("Pick the creature mesh in FaceLab > Retarget")
            return False
        return True

    def execute(self, context):
        obj = face_object(context)
        creature = context.scene.facelab_solve.creature
        try:
            frames = frame_range(context.scene, context.scene.facelab_solve)
            r = retarget(context, obj, creature, progress=progress_callback(context, len(frames), "FaceLab Retarget"))
            RESULTS["retarget"] = r
        except FaceLabError as e:
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        finally:
            context.window_manager.progress_end()
        msg = (f"Retargeted {len(r['frames'])} frames to '{creature.name}' in {r['time_s']:.1f} s ({r['correspondence']}): "
               f"{len(r['created'])} shape keys transferred, {len(r['keys'])} corrective shapes ({RETARGET_PREFIX}*)")
        if r["kept"]:
            msg += f"; kept the creature's own keys {', '.join(r['kept'][:5])}{'...' if len(r['kept']) > 5 else ''}"
        if r["action_note"]:
            msg += f"; {r['action_note']}"
        self.report({"WARNING"} if r["kept"] else {"INFO"}, msg)
        return {"FINISHED"}


classes = (FACELAB_OT_solve_add_view, FACELAB_OT_solve_remove_view, FACELAB_OT_bind_tracks,
           FACELAB_OT_solve_performance, FACELAB_OT_retarget)
register, unregister = bpy.utils.register_classes_factory(classes)
