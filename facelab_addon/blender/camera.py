"""Blender camera <-> core :class:`~facelab_addon.core.capture.camera.Camera`.

Thin adapter: reads a Blender perspective camera and the scene's render
settings into a pixel pinhole camera (OpenCV convention, see
``facelab_addon/core/capture/camera.py``), and writes a core camera back into a
Blender camera object and the render settings.

How Blender maps a camera to pixels (``BKE_camera_params_compute_viewplane``,
``Camera.view_frame`` and ``bpy_extras.object_utils.world_to_camera_view``):

* The frame's aspect uses the *unscaled* render size and the pixel aspect:
  ``ax = resolution_x * pixel_aspect_x``, ``ay = resolution_y * pixel_aspect_y``.
* Sensor fit ``AUTO`` resolves to horizontal if ``ax >= ay`` else vertical,
  but always uses ``sensor_width``; ``HORIZONTAL`` uses ``sensor_width``;
  ``VERTICAL`` uses ``sensor_height``.
* At unit depth the fitted side of the frame is ``sensor / lens`` long; the
  other side follows from ``ax : ay``.
* ``shift_x`` / ``shift_y`` move the frame by that many *fitted-side*
  lengths (right / up).
* The pixel grid is the frame split into ``resolution * percentage // 100``
  pixels per side (``BKE_render_resolution``); pixels are therefore
  ``(u * width, (1 - v) * height)`` for ``world_to_camera_view``'s ``(u, v)``.
* Object scale is ignored (Blender normalises ``matrix_world`` for cameras).
"""

from __future__ import annotations

import bpy
import numpy as np
from mathutils import Matrix

from ..core.capture.camera import Camera
from ..core.errors import CameraError

__all__ = ["camera_from_blender", "apply_camera_to_blender", "render_size", "evaluated_depsgraph"]

# Blender camera axes (x right, y up, looking down -z) -> OpenCV (x right, y down, +z forward).
_BLENDER_TO_CV = np.diag([1.0, -1.0, -1.0])


def render_size(scene) -> tuple[int, int]:
    """Rendered image size ``(width, height)`` in pixels, resolution percentage applied."""
    r = scene.render
    pct = r.resolution_percentage
    return (r.resolution_x * pct) // 100, (r.resolution_y * pct) // 100


def evaluated_depsgraph(scene):
    """The evaluated depsgraph of ``scene`` (the context's if it is the context scene)."""
    ctx_scene = getattr(bpy.context, "scene", None)
    if ctx_scene is not None and ctx_scene == scene:
        return bpy.context.evaluated_depsgraph_get()
    view_layer = scene.view_layers[0]
    depsgraph = view_layer.depsgraph
    depsgraph.update()
    return depsgraph


def camera_from_blender(scene, cam_obj=None, depsgraph=None) -> Camera:
    """Build the core camera of a Blender camera object at the current frame.

    Parameters
    ----------
    scene : bpy.types.Scene
        Gives the render size (resolution, percentage, pixel aspect).
    cam_obj : bpy.types.Object, optional
        A camera object; defaults to ``scene.camera``.
    depsgraph : bpy.types.Depsgraph, optional
        Used to read the evaluated (animated, constrained) camera. Defaults to
        the context's evaluated depsgraph. Set the frame first
        (``scene.frame_set``) to read another frame.

    Returns
    -------
    Camera
        ``K`` in pixels, ``R, t`` world-to-camera (scene units), and the
        rendered image size. Agrees with ``world_to_camera_view``.

    Raises
    ------
    CameraError
        No scene camera, not a camera object, not a perspective camera, a
        mirrored or sheared camera transform, or a zero render size.
    """
    if cam_obj is None:
        cam_obj = scene.camera
        if cam_obj is None:
            raise CameraError(
                f"Scene '{scene.name}' has no active camera; add a camera and make it the scene "
                "camera (Scene properties > Camera, or Ctrl+Numpad 0 with the camera selected)."
            )
    if cam_obj.type != "CAMERA":
        raise CameraError(
            f"Object '{cam_obj.name}' is a {cam_obj.type.lower()}, not a camera; "
            "set the scene camera to a camera object."
        )
    if depsgraph is None:
        depsgraph = evaluated_depsgraph(scene)
    cam_eval = cam_obj.evaluated_get(depsgraph)
    cam = cam_eval.data
    if cam.type != "PERSP":
        raise CameraError(
            f"Camera '{cam_obj.name}' is {cam.type.lower()}; FaceLab needs a perspective camera: "
            "set Camera properties > Lens > Type to Perspective."
        )

    r = scene.render
    width, height = render_size(scene)
    if width <= 0 or height <= 0:
        raise CameraError("The render size is zero; set Output properties > Resolution and its percentage.")
    ax = r.resolution_x * r.pixel_aspect_x
    ay = r.resolution_y * r.pixel_aspect_y
    fit = cam.sensor_fit
    sensor = cam.sensor_height if fit == "VERTICAL" else cam.sensor_width
    if fit == "AUTO":
        fit = "HORIZONTAL" if ax >= ay else "VERTICAL"
    if cam.lens <= 0 or sensor <= 0:
        raise CameraError(
            f"Camera '{cam_obj.name}' has a non-positive focal length or sensor size; fix the lens settings."
        )
    fitted = sensor / cam.lens  # frame side length at unit depth along the fitted axis
    if fit == "HORIZONTAL":
        frame_w, frame_h = fitted, fitted * ay / ax
    else:
        frame_w, frame_h = fitted * ax / ay, fitted
    fx = width / frame_w
    fy = height / frame_h
    cx = width * (0.5 - cam.shift_x * fitted / frame_w)
    cy = height * (0.5 + cam.shift_y * fitted / frame_h)
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])

    M = np.array(cam_eval.matrix_world, dtype=np.float64)
    A = M[:3, :3]
    norms = np.linalg.norm(A, axis=0)
    if np.any(norms < 1e-12):
        raise CameraError(f"Camera '{cam_obj.name}' has zero scale; set its scale to 1.")
    A = A / norms  # Blender ignores camera scale (matrix_world.normalized())
    if np.linalg.det(A) < 0:
        raise CameraError(
            f"Camera '{cam_obj.name}' is mirrored (negative scale); set its scale to positive values "
            "(Object > Apply > Scale, or clear the scale of the camera and its parents)."
        )
    if np.abs(A.T @ A - np.eye(3)).max() > 1e-5:
        raise CameraError(
            f"Camera '{cam_obj.name}' is sheared by a non-uniformly scaled parent; "
            "give the camera and its parents uniform scale."
        )
    R = (A @ _BLENDER_TO_CV).T
    t = -R @ M[:3, 3]
    return Camera(K, R, t, width, height)


def apply_camera_to_blender(camera: Camera, cam_obj, scene, sensor_width: float = 36.0) -> None:
    """Make a Blender camera object and the render settings match a core camera.

    Sets ``cam_obj.matrix_world`` (unit scale), a perspective lens with
    horizontal sensor fit, the shift for the principal point, the render
    resolution (100 %), and the pixel aspect for ``fx != fy``. The principal
    point may be anywhere (shift is unbounded here, Blender clamps to ±10).
    Animation, drivers or constraints on the camera override what is set here.

    Parameters
    ----------
    camera : Camera
        Zero-skew intrinsics in pixels.
    cam_obj : bpy.types.Object
        A camera object (its data is modified).
    scene : bpy.types.Scene
        Its render resolution and pixel aspect are modified.
    sensor_width : float
        Horizontal sensor size in millimetres; the lens follows from it.

    Raises
    ------
    CameraError
        ``cam_obj`` is not a camera, or ``K`` has skew.
    """
    if cam_obj is None or cam_obj.type != "CAMERA":
        raise CameraError("apply_camera_to_blender needs a camera object; create one with Add > Camera.")
    K = camera.K
    fx, fy, cx, cy, skew = K[0, 0], K[1, 1], K[0, 2], K[1, 2], K[0, 1]
    if abs(skew) > 1e-9 * fx:
        raise CameraError("Blender cameras have no skew; re-calibrate with zero skew.")
    W, H = camera.width, camera.height
    # fy / fx == pixel_aspect_x / pixel_aspect_y; Blender needs both >= 1.
    if fy >= fx:
        asp_x, asp_y = fy / fx, 1.0
    else:
        asp_x, asp_y = 1.0, fx / fy
    r = scene.render
    r.resolution_x = W
    r.resolution_y = H
    r.resolution_percentage = 100
    r.pixel_aspect_x = asp_x
    r.pixel_aspect_y = asp_y

    cam = cam_obj.data
    cam.type = "PERSP"
    cam.lens_unit = "MILLIMETERS"
    cam.sensor_fit = "HORIZONTAL"
    cam.sensor_width = sensor_width
    cam.sensor_height = sensor_width * (H * asp_y) / (W * asp_x)
    frame_w = W / fx  # frame width at unit depth (horizontal fit: fitted side)
    cam.lens = sensor_width / frame_w
    cam.shift_x = (W / 2.0 - cx) / W
    frame_h = H / fy
    cam.shift_y = (cy - H / 2.0) / H * frame_h / frame_w

    A = camera.R.T @ _BLENDER_TO_CV  # camera-to-world rotation, Blender camera axes
    M = np.eye(4)
    M[:3, :3] = A
    M[:3, 3] = camera.center
    cam_obj.matrix_world = Matrix(M.tolist())


def new_camera_object(scene, camera: Camera, name: str = "Camera", *, make_active: bool = True):
    """A new camera object in ``scene`` that matches ``camera`` (see :func:`apply_camera_to_blender`).

    Parameters
    ----------
    scene : bpy.types.Scene
        The object is linked to its master collection; its render resolution follows ``camera``.
    camera : Camera
        Intrinsics in pixels and pose (OpenCV convention).
    name : str
        Name of the object and its camera data (Blender adds ``.001`` if taken).
    make_active : bool
        Also make it ``scene.camera``.

    Returns
    -------
    bpy.types.Object
    """
    cam_obj = bpy.data.objects.new(name, bpy.data.cameras.new(name))
    scene.collection.objects.link(cam_obj)
    apply_camera_to_blender(camera, cam_obj, scene)
    if make_active:
        scene.camera = cam_obj
    return cam_obj
