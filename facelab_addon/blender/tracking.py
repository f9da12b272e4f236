"""Blender motion tracking -> FaceLab arrays (Bhat et al. 2013, §4.1 inputs).

Thin adapters for the contour-based blendshape solve:

* :func:`read_track_markers` -- a Movie Clip's 2D tracks as ``(T,M,2)`` pixels;
* :func:`clip_camera` -- the clip's camera calibration combined with a camera
  object's pose, as a core :class:`~facelab_addon.core.capture.camera.Camera`;
* :func:`read_views` -- several (camera object, Movie Clip) views at once:
  cameras and ``(T,C,M,2)`` markers over the union of their track names;
* :func:`clip_bundles` -- the clip's reconstructed 3D bundles with names.

Conventions (checked against Blender 5.0 source, ``tracking.cc``,
``tracking_solver.cc``, ``movieclip.cc``):

* ``marker.co`` is normalised to the clip frame, origin bottom-left, y up;
  Blender's own solver uses ``(co + track.offset) * (width, height)``, so the
  FaceLab pixel (top-left origin, y down, see ``core/capture/camera.py``) is
  ``x = (co_x + off_x) * W``, ``y = (1 - co_y - off_y) * H``.
* Marker frames are *clip* frames: scene frame ``f`` shows clip frame
  ``f - clip.frame_start + 1`` (``BKE_movieclip_remap_scene_to_clip_frame``).
* A track has a value on a frame only where it has a marker on exactly that
  frame that is not disabled (``marker.mute``); Blender's camera solver uses
  the same rule. Anything else is NaN: no marker (the track was not tracked
  there: Blender would *display* the previous marker), disabled, or off-screen
  (outside the frame).
* The tracking camera: ``focal_length_pixels`` is the focal length in pixels
  (``focal_length * W / sensor_width``); ``principal_point_pixels`` is in
  frame pixels with bottom-left origin; ``pixel_aspect`` scales y
  (``fy = f * pixel_aspect``, the solver works in ``(W, H / pixel_aspect)``).
  Lens distortion (polynomial k1..k3, division, Nuke, Brown) is **ignored**:
  FaceLab's camera is a pinhole, so markers are used as tracked (distorted);
  :func:`clip_camera` warns when a distortion coefficient is non-zero.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..core.capture.camera import Camera
from ..core.errors import BundleError, CameraError, FaceLabError
from .camera import camera_from_blender, evaluated_depsgraph

__all__ = [
    "clip_frame",
    "clip_size",
    "read_track_markers",
    "clip_intrinsics",
    "clip_camera",
    "camera_pose",
    "distortion_coefficients",
    "View",
    "ViewData",
    "read_views",
    "clip_bundles",
]

# Distortion coefficients per model; any non-zero one is reported (and ignored).
_DISTORTION = {
    "POLYNOMIAL": ("k1", "k2", "k3"),
    "DIVISION": ("division_k1", "division_k2"),
    "NUKE": ("nuke_k1", "nuke_k2"),
    "BROWN": ("brown_k1", "brown_k2", "brown_k3", "brown_k4", "brown_p1", "brown_p2"),
}
_BLENDER_TO_CV = np.diag([1.0, -1.0, -1.0])


# --------------------------------------------------------------------------- clip basics
def clip_frame(clip, scene_frame):
    """Clip frame number(s) shown on scene frame(s) ``scene_frame`` (int or array)."""
    return np.asarray(scene_frame) - int(clip.frame_start) + 1


def clip_size(clip) -> tuple[int, int]:
    """``(width, height)`` of the clip's footage in pixels.

    Raises
    ------
    CameraError
        The footage cannot be read (missing file): Blender reports size 0.
    """
    w, h = int(clip.size[0]), int(clip.size[1])
    if w <= 0 or h <= 0:
        raise CameraError(
            f"Movie Clip '{clip.name}' has no readable footage ({clip.filepath!r}); its image size is unknown. "
            "Fix the file path in the Clip editor (Footage Settings) or reload the clip."
        )
    return w, h


# --------------------------------------------------------------------------- markers
def _tracks(clip, tracking_object=None):
    tr = clip.tracking
    if tracking_object is None:
        return tr.tracks
    if isinstance(tracking_object, str):
        obj = tr.objects.get(tracking_object)
        if obj is None:
            raise FaceLabError(
                f"Movie Clip '{clip.name}' has no tracking object '{tracking_object}'; "
                f"pick one of {[o.name for o in tr.objects]}."
            )
        return obj.tracks
    return tracking_object.tracks


def read_track_markers(clip, frames, *, names=None, tracking_object=None, margin: float = 0.0,
                       skip_zero_weight: bool = True):
    """Pixel positions of a clip's tracks on scene frames, in bulk.

    Parameters
    ----------
    clip : bpy.types.MovieClip
    frames : (T,) array_like of int
        *Scene* frames (the clip's Start Frame maps them to clip frames).
    names : sequence of str, optional
        Tracks to read, in this order; a name the clip lacks gives an all-NaN
        column. Default: every track of the tracking object, in clip order.
    tracking_object : bpy.types.MovieTrackingObject or str, optional
        Default: the camera's tracks (``clip.tracking.tracks``).
    margin : float
        Markers closer than this to the frame border (pixels) count as
        off-screen; negative values accept markers slightly outside.
    skip_zero_weight : bool
        Tracks whose *Weight* (Track > Weight, "influence on the solve") is 0
        are left out (all NaN), as Blender's camera solver leaves them out.

    Returns
    -------
    pixels : (T,M,2) float64 ndarray
        FaceLab pixels (top-left origin, y down) of the clip's footage; NaN
        where the track has no marker on that frame, the marker is disabled,
        or it lies off-screen.
    names : list of str
        The ``M`` track names.

    Notes
    -----
    Three ``foreach_get`` calls per track, then NumPy: 100 tracks x 1000
    frames take a few milliseconds.
    """
    W, H = clip_size(clip)
    frames = np.asarray(frames, dtype=np.int64).reshape(-1)
    cframes = clip_frame(clip, frames)
    tracks = _tracks(clip, tracking_object)
    if names is None:
        names = [t.name for t in tracks]
    names = list(names)
    T, M = len(frames), len(names)
    out = np.full((T, M, 2), np.nan)
    if T == 0:
        return out, names
    lo, hi = int(cframes.min()), int(cframes.max())
    lut = np.full(hi - lo + 1, -1, dtype=np.int64)  # clip frame -> row
    lut[cframes - lo] = np.arange(T)
    for j, name in enumerate(names):
        track = tracks.get(name)
        if track is None or (skip_zero_weight and track.weight == 0.0):
            continue
        mk = track.markers
        n = len(mk)
        if n == 0:
            continue
        fr = np.empty(n, dtype=np.int32)
        co = np.empty(2 * n, dtype=np.float32)
        mute = np.empty(n, dtype=bool)
        mk.foreach_get("frame", fr)
        mk.foreach_get("co", co)
        mk.foreach_get("mute", mute)
        keep = (~mute) & (fr >= lo) & (fr <= hi)
        rows = np.full(n, -1, dtype=np.int64)
        rows[keep] = lut[fr[keep] - lo]
        keep &= rows >= 0
        co = co.reshape(n, 2).astype(np.float64) + np.asarray(track.offset, dtype=np.float64)
        out[rows[keep], j, 0] = co[keep, 0] * W
        out[rows[keep], j, 1] = (1.0 - co[keep, 1]) * H
    x, y = out[..., 0], out[..., 1]
    off = ~((x >= margin) & (x <= W - margin) & (y >= margin) & (y <= H - margin))  # NaN compares False
    out[off] = np.nan
    return out, names


# --------------------------------------------------------------------------- cameras
def distortion_coefficients(clip) -> dict:
    """Non-zero lens distortion coefficients of the clip's camera model, ``{name: value}``."""
    cam = clip.tracking.camera
    return {k: float(getattr(cam, k)) for k in _DISTORTION.get(cam.distortion_model, ()) if getattr(cam, k) != 0.0}


def clip_intrinsics(clip) -> tuple[np.ndarray, int, int]:
    """``(K, width, height)`` from the clip's camera calibration (Clip editor > Track > Camera).

    Raises
    ------
    CameraError
        Non-positive focal length or sensor width (an uncalibrated camera),
        or no readable footage.
    """
    W, H = clip_size(clip)
    cam = clip.tracking.camera
    if not (cam.focal_length > 0 and cam.sensor_width > 0 and cam.pixel_aspect > 0):
        raise CameraError(
            f"Movie Clip '{clip.name}' has no camera calibration (focal length {cam.focal_length:g} mm, sensor "
            f"width {cam.sensor_width:g} mm, pixel aspect {cam.pixel_aspect:g}); enter the lens in the Clip "
            "editor's Track tab > Camera (sensor width and focal length, or solve the camera with 'Refine' focal "
            "length)."
        )
    f = float(cam.focal_length_pixels)
    pp = np.asarray(cam.principal_point_pixels, dtype=np.float64)
    K = np.array([[f, 0.0, pp[0]], [0.0, f * cam.pixel_aspect, H - pp[1]], [0.0, 0.0, 1.0]])
    return K, W, H


def camera_pose(cam_obj, depsgraph) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera ``(R, t)`` (OpenCV axes) of a camera object, evaluated."""
    M = np.array(cam_obj.evaluated_get(depsgraph).matrix_world, dtype=np.float64)
    A = M[:3, :3]
    norms = np.linalg.norm(A, axis=0)
    if np.any(norms < 1e-12):
        raise CameraError(f"Camera '{cam_obj.name}' has zero scale; set its scale to 1.")
    A = A / norms
    if np.linalg.det(A) < 0 or np.abs(A.T @ A - np.eye(3)).max() > 1e-5:
        raise CameraError(
            f"Camera '{cam_obj.name}' is mirrored or sheared by its scale; give it and its parents a uniform "
            "positive scale (Object > Apply > Scale)."
        )
    R = (A @ _BLENDER_TO_CV).T
    return R, -R @ M[:3, 3]


def clip_camera(scene, cam_obj, clip, depsgraph=None, *, tolerance: float = 0.01):
    """The core camera of a view: the clip's intrinsics and the camera object's pose.

    The clip's calibration wins for the intrinsics because the markers are
    measured in its pixels. The camera object's own lens (``camera_from_blender``
    with the scene's render size, rescaled to the clip size) is compared with
    it, and a disagreement is reported as a warning.

    Parameters
    ----------
    scene : bpy.types.Scene
    cam_obj : bpy.types.Object
        A camera object (its pose at the depsgraph's frame is used).
    clip : bpy.types.MovieClip
        The footage this camera filmed, with its tracks.
    depsgraph : bpy.types.Depsgraph, optional
    tolerance : float
        Relative disagreement (focal length, principal point as a fraction of
        the image width) above which a warning is issued.

    Returns
    -------
    camera : Camera
        ``K`` from the clip, ``R, t`` from ``cam_obj``, size = the clip's.
    warnings : list of str
        Ignored lens distortion; lens or aspect that differ from the camera
        object's; a render aspect different from the clip's.

    Raises
    ------
    CameraError
        ``cam_obj`` missing or not a camera, no clip, an uncalibrated clip,
        unreadable footage, or a mirrored/sheared camera.
    """
    if cam_obj is None or cam_obj.type != "CAMERA":
        what = "nothing" if cam_obj is None else f"'{cam_obj.name}' ({cam_obj.type.lower()})"
        raise CameraError(
            f"A solve view has {what} as its camera; pick a camera object for every view in FaceLab > Solve > Views."
        )
    if clip is None:
        raise CameraError(
            f"Camera '{cam_obj.name}' has no Movie Clip: FaceLab reads its calibration and tracks from the clip. "
            "Set the view's clip in FaceLab > Solve > Views (open the footage in the Clip editor first)."
        )
    if depsgraph is None:
        depsgraph = evaluated_depsgraph(scene)
    K, W, H = clip_intrinsics(clip)
    R, t = camera_pose(cam_obj, depsgraph)
    cam = Camera(K, R, t, W, H)
    warnings = []
    dist = distortion_coefficients(clip)
    if dist:
        warnings.append(
            f"Movie Clip '{clip.name}' has lens distortion ({clip.tracking.camera.distortion_model.lower()}: "
            + ", ".join(f"{k}={v:g}" for k, v in dist.items())
            + "); FaceLab ignores it and uses the tracked (distorted) marker positions with a pinhole camera. "
            "Undistort the footage and re-track, or set the coefficients to 0, for an exact solve."
        )
    try:
        bl = camera_from_blender(scene, cam_obj, depsgraph)
    except CameraError as e:  # an orthographic scene camera etc.: the clip still defines the camera
        warnings.append(f"Camera object '{cam_obj.name}' could not be read as a lens ({e}); using the clip's.")
        return cam, warnings
    sx, sy = W / bl.width, H / bl.height
    if abs(sx - sy) > tolerance * max(sx, sy):
        warnings.append(
            f"The render size {bl.width}x{bl.height} has another aspect than clip '{clip.name}' ({W}x{H}); FaceLab "
            "uses the clip's. Press 'Set Scene Frames'/'Setup Tracking Scene' or set the resolution to match."
        )
        return cam, warnings
    Kb = np.diag([sx, sy, 1.0]) @ bl.K
    df = abs(Kb[0, 0] - K[0, 0]) / K[0, 0]
    dp = np.abs(Kb[:2, 2] - K[:2, 2]).max() / W
    if df > tolerance or dp > tolerance:
        warnings.append(
            f"Camera object '{cam_obj.name}' (lens {cam_obj.data.lens:g} mm, sensor {cam_obj.data.sensor_width:g} mm: "
            f"{Kb[0, 0]:.1f} px) disagrees with clip '{clip.name}' ({K[0, 0]:.1f} px, principal point "
            f"{K[0, 2]:.1f}, {K[1, 2]:.1f} px vs {Kb[0, 2]:.1f}, {Kb[1, 2]:.1f}); FaceLab uses the clip's calibration. "
            "Copy the clip's lens to the camera (Clip editor > Setup Tracking Scene) so the 3D view shows what is solved."
        )
    return cam, warnings


# --------------------------------------------------------------------------- views
@dataclass
class View:
    """One camera of a solve: a camera object and the Movie Clip it filmed.

    ``mask`` (a Mask drawn over this clip) and ``sketch`` (a Grease Pencil
    object drawn in this camera's view) are optional contour sources.
    """

    camera: object
    clip: object
    mask: object = None
    sketch: object = None
    name: str = ""


@dataclass
class ViewData:
    """What :func:`read_views` returns: cameras, markers and bookkeeping."""

    cameras: list                      # [Camera] * C
    markers: np.ndarray                # (T,C,M,2) pixels, NaN = missing
    names: list                        # M marker names (union of the views' tracks, first-seen order)
    frames: np.ndarray                 # (T,) scene frames
    warnings: list = field(default_factory=list)

    def missing_report(self) -> dict:
        """``{'off_or_missing': (T,M) bool where no view sees a marker, 'frames_without': [...]}``."""
        seen = np.isfinite(self.markers[..., 0]).any(axis=1)
        return {"unseen": ~seen, "frames_without": [int(f) for f in self.frames[~seen.any(axis=1)]]}


def _pose_matrix(obj, depsgraph):
    return np.array(obj.evaluated_get(depsgraph).matrix_world, dtype=np.float64)


def read_views(scene, views, frames, *, pose_frame=None, track_names=None, check_static=None, margin=0.0):
    """Cameras and markers of several views over the scene frames ``frames``.

    Parameters
    ----------
    scene : bpy.types.Scene
    views : sequence of :class:`View` (or objects with ``camera`` and ``clip``)
    frames : (T,) array_like of int
    pose_frame : int, optional
        Scene frame whose camera poses are used; default: the current frame.
    track_names : sequence of str, optional
        Marker names to read (default: the union of every view's tracks, in the
        order first seen).
    check_static : bpy.types.Object, optional
        When given (the face), the pose of each camera *relative to this
        object* is compared on the first, middle and last frame; a camera that
        moves relative to the face raises ``CameraError`` (the solve uses one
        camera per view).
    margin : float
        See :func:`read_track_markers`.

    Returns
    -------
    ViewData
    """
    views = list(views)
    if not views:
        raise CameraError(
            "No solve views: add at least one view (a camera object and the Movie Clip it filmed) in "
            "FaceLab > Solve > Views."
        )
    frames = np.asarray(frames, dtype=np.int64).reshape(-1)
    keep = scene.frame_current
    if pose_frame is not None and pose_frame != keep:
        scene.frame_set(int(pose_frame))
    try:
        dg = evaluated_depsgraph(scene)
        cameras, warnings = [], []
        for v in views:
            cam, w = clip_camera(scene, v.camera, v.clip, dg)
            cameras.append(cam)
            warnings += w
        if check_static is not None and len(frames) > 1:
            _check_static(scene, views, check_static, frames)
    finally:
        if scene.frame_current != keep:
            scene.frame_set(keep)
    if track_names is None:
        track_names = []
        seen = set()
        for v in views:
            for t in v.clip.tracking.tracks:
                if t.name not in seen:
                    seen.add(t.name)
                    track_names.append(t.name)
    track_names = list(track_names)
    M = np.full((len(frames), len(views), len(track_names), 2), np.nan)
    for c, v in enumerate(views):
        M[:, c], _ = read_track_markers(v.clip, frames, names=track_names, margin=margin)
    return ViewData(cameras, M, track_names, frames, warnings)


def _check_static(scene, views, face_obj, frames):
    keep = scene.frame_current
    probe = sorted({int(frames[0]), int(frames[len(frames) // 2]), int(frames[-1])})
    rel = []
    try:
        for f in probe:
            scene.frame_set(f)
            dg = evaluated_depsgraph(scene)
            F = _pose_matrix(face_obj, dg)
            rel.append([np.linalg.solve(F, _pose_matrix(v.camera, dg)) for v in views])
    finally:
        scene.frame_set(keep)
    for c, v in enumerate(views):
        mats = np.stack([r[c] for r in rel])
        scale = max(1.0, float(np.abs(mats[0, :3, 3]).max()))
        if np.abs(mats - mats[0]).max() > 1e-5 * scale:
            raise CameraError(
                f"Camera '{v.camera.name}' moves relative to the face '{face_obj.name}' between frames {probe[0]} and "
                f"{probe[-1]}; the solve needs each camera fixed relative to the head (a head-mounted rig, or a "
                "stabilised face). Parent the camera to the face, or remove its animation/constraints."
            )


# --------------------------------------------------------------------------- bundles
def clip_bundles(clip, tracking_object=None):
    """Reconstructed 3D bundles of a clip, with their track names.

    Returns
    -------
    points : (B,3) float64 ndarray
        Bundle positions in the reconstruction's space, scene units. With the
        camera's "Camera Solver" constraint (Setup Tracking Scene) this is the
        world space the 3D view shows them in.
    names : list of str

    Raises
    ------
    BundleError
        No valid camera solve, or no track with a bundle.
    """
    tracks = _tracks(clip, tracking_object)
    obj = clip.tracking.objects.active if tracking_object is None else (
        clip.tracking.objects.get(tracking_object) if isinstance(tracking_object, str) else tracking_object)
    if obj is None or not obj.reconstruction.is_valid:
        raise BundleError(
            f"Movie Clip '{clip.name}' has no valid camera solve, so it has no 3D bundles; press Solve Camera Motion "
            "in the Clip editor, or use empties as bundles instead."
        )
    with_b = [t for t in tracks if t.has_bundle]
    if not with_b:
        raise BundleError(f"Movie Clip '{clip.name}' has no reconstructed bundles; solve the camera first.")
    return np.asarray([t.bundle[:] for t in with_b], dtype=np.float64), [t.name for t in with_b]
