"""Where the camera is relative to the face: a camera inside the head or behind the skin is refused by name.

Used by the sketch views (:mod:`facelab_addon.core.lips.views`) before they ask for strokes over the mouth.
"""

from __future__ import annotations

from ..errors import CameraError
from ..geometry.silhouette import facing

__all__ = ["require_camera_outside"]


def require_camera_outside(cam, V, F, fixed, depth, where: str = "") -> None:
    """Refuse a camera inside the head or behind the face's surface (it sees the skin from within).

    Called when no part of the face projects near the strokes: the message then says what is wrong with the
    camera rather than asking for strokes over the mouth. Behind: fewer than 30 % of the free triangles in
    front of the camera face it; inside the head: the camera centre within the bounding box of the free
    vertices, and it sees their back (or none of them, or has most of them behind it).

    Parameters
    ----------
    cam : Camera
    V : (V,3) float
        Positions, scene units (world).
    F : (F,3) int
        Triangles wound outward.
    fixed : (V,) bool
        Hidden vertices (not judged).
    depth : (V,) float
        ``cam.depth(V)``.
    where : str
        Names the view in messages.

    Raises
    ------
    CameraError
    """
    free = ~fixed
    if not free.any():
        return
    tris = F[(depth[F] > 0).all(axis=1) & free[F].all(axis=1)]
    fs = facing(V, tris, cam)
    away = bool(fs.size) and (fs > 0).mean() < 0.3
    lo, hi = V[free].min(axis=0), V[free].max(axis=0)
    inside = bool(((cam.center >= lo) & (cam.center <= hi)).all()) and (
        away or not fs.size or (depth[free] <= 0).mean() > 0.5)
    if not (inside or away):
        return
    seen = f" ({100 * (fs <= 0).mean():.0f} % of the face in front of it faces away)" if fs.size else ""
    raise CameraError(
        f"The camera{where} is {'inside the head' if inside else 'behind the face'}: it sees the skin from within"
        f"{seen}, so no lip can match the strokes. Move the camera in front of the face (or pick the camera the "
        "backplate and the sketch belong to)."
    )
