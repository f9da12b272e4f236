"""A face model with its vertices split along seams, as a glTF import or a game export gives it.

Blender's glTF importer (default: Merge Vertices off) and many engine formats keep one vertex per distinct
(position, UV, normal) of the polygon corners: every vertex on a UV seam (or a sharp edge) becomes two or
more coincident vertices and the surface falls into pieces. :func:`split_seams` makes such a face from a
face model (:class:`~facelab_addon.core.capture.ict.ICTModel`, split by its own UVs, or
:class:`~facelab_addon.testing.remeshed.RemeshedFace`, which has no UVs: islands of the mouth area cut out
along their border loops, :func:`mouth_boxes`, or any planes or boxes given); the result is a face model
:func:`~facelab_addon.testing.route.build_route_scene` accepts as it is (``neutral``, ``expressions``,
``faces``, ``poly_verts``, ``poly_offsets``, ``part_vertex_mask``), and ``source`` maps it back.

Vertex order: the split vertices are sorted by (source vertex, corner label), so the first copy of every
source vertex (the representative :func:`facelab_addon.core.geometry.weld.weld` picks) comes in the
source's order. Units are the source model's.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..core.geometry.mesh import triangulate

__all__ = ["SplitFace", "split_seams", "plane_labels", "box_labels", "mouth_boxes"]


@dataclass
class SplitFace:
    """A face model split along seams. Shapes: V split vertices, V0 source vertices, C corners, P polygons.

    Attributes
    ----------
    neutral : (V,3) float
    expressions : dict name -> (V,3) float
    poly_verts : (C,) int64
        The source's polygon corners, re-indexed to the split vertices.
    poly_offsets : (P+1,) int64
    faces : (F,3) int64
        Fan triangulation of the split polygons (the source's triangles, re-indexed).
    source : (V,) int64
        The source vertex of each split vertex.
    base : object
        The source model.
    """

    neutral: np.ndarray
    expressions: dict
    poly_verts: np.ndarray
    poly_offsets: np.ndarray
    faces: np.ndarray
    source: np.ndarray
    base: object = field(repr=False, default=None)

    @property
    def expression_names(self):
        return list(self.expressions)

    @property
    def n_duplicates(self) -> int:
        """Split vertices beyond the source's (the copies made along the seams)."""
        return len(self.source) - len(np.unique(self.source))

    def part_vertex_mask(self, *names):
        """(V,) bool: the source's mask (e.g. ``"M_Face"``) at every copy of its vertices."""
        return np.asarray(self.base.part_vertex_mask(*names))[self.source]

    def duplicates(self) -> np.ndarray:
        """(D,2) int64 pairs ``(first copy, other copy)`` of every vertex split in two or more."""
        first = np.r_[True, np.diff(self.source) != 0]
        head = np.maximum.accumulate(np.where(first, np.arange(len(self.source)), 0))
        dup = np.flatnonzero(~first)
        return np.c_[head[dup], dup]


def plane_labels(face, planes) -> np.ndarray:
    """(C,) int per polygon corner: which side of each plane ``(axis, value)`` (model units) its polygon's centre is on.

    A vertex whose polygons lie on both sides of a plane is split there: the cut runs along the edge loop between
    the polygons on either side.
    """
    V = np.asarray(face.neutral, dtype=np.float64)
    pv, off = np.asarray(face.poly_verts), np.asarray(face.poly_offsets)
    sizes = np.diff(off)
    centre = np.add.reduceat(V[pv], off[:-1], axis=0) / sizes[:, None]
    label = np.zeros(len(sizes), np.int64)
    for k, (a, value) in enumerate(planes):
        label |= (centre[:, int(a)] > float(value)).astype(np.int64) << k
    return np.repeat(label, sizes)


def box_labels(face, boxes) -> np.ndarray:
    """(C,) int per polygon corner: 1 + the index of the first box ``(lo (3,), hi (3,))`` (model units) holding its
    polygon's centre, 0 outside every box: each box's polygons become an island cut out along its border loop."""
    V = np.asarray(face.neutral, dtype=np.float64)
    pv, off = np.asarray(face.poly_verts), np.asarray(face.poly_offsets)
    sizes = np.diff(off)
    centre = np.add.reduceat(V[pv], off[:-1], axis=0) / sizes[:, None]
    label = np.zeros(len(sizes), np.int64)
    for k, (lo, hi) in reversed(list(enumerate(boxes))):
        inside = ((centre >= np.asarray(lo, float)) & (centre <= np.asarray(hi, float))).all(axis=1)
        label[inside] = k + 1
    return np.repeat(label, sizes)


def mouth_boxes(face, up: int = 1, across: int = 0) -> list:
    """Boxes of the mouth area to cut out as islands: the upper lip's skin, the lower lip's and one mouth corner.

    Relative to the inner-lip loop (``core.lips.lip_loop``: centre ``c``, width ``w``) along the ``up`` and
    ``across`` axes (y and x for ICT), unbounded in depth: the upper lip ``0.15 w .. 0.4 w`` above ``c`` and the
    lower lip as far below, each ``0.3 w`` to either side of the middle (in the mouth band of Auto Regions), and the
    left corner (``0.55 w .. 0.8 w`` from the middle, ``0.15 w`` up and down: across the lip band's end). None cuts
    the lips' contact (a cut across it, or too near it on a coarse mesh, leaves no closed loop to find, and the
    route scene needs the loop); the islands stay small, so without welding they would be held as separate parts.
    """
    from ..core.lips.lip_loop import inner_lip_loop, loop_width

    V = np.asarray(face.neutral, dtype=np.float64)
    loop = inner_lip_loop(V, np.asarray(face.faces))
    c, w = V[loop].mean(axis=0), loop_width(V, loop)
    big = 1e3 * w

    def box(a0, a1, u0, u1):
        lo, hi = np.full(3, -big), np.full(3, big)
        lo[across], hi[across] = c[across] + a0 * w, c[across] + a1 * w
        lo[up], hi[up] = c[up] + u0 * w, c[up] + u1 * w
        return lo, hi

    return [box(-0.3, 0.3, 0.15, 0.4), box(-0.3, 0.3, -0.4, -0.15), box(0.55, 0.8, -0.15, 0.15)]


def split_seams(face, labels=None) -> SplitFace:
    """``face`` with every vertex split into one copy per distinct label of its polygon corners.

    Parameters
    ----------
    face : ICTModel or RemeshedFace
        A face model (``neutral``, ``expressions``, ``poly_verts``, ``poly_offsets``, ``part_vertex_mask``).
    labels : (C,) int array_like, optional
        A label per polygon corner; corners of one vertex with different labels get different copies.
        Default: the model's UV index per corner (``poly_uv``: a UV-seam split, as a glTF import) when it has
        one, else islands of the mouth area cut out along their border loops (:func:`box_labels` of
        :func:`mouth_boxes`).

    Returns
    -------
    SplitFace
    """
    pv = np.asarray(face.poly_verts, dtype=np.int64)
    off = np.asarray(face.poly_offsets, dtype=np.int64)
    if labels is None:
        labels = getattr(face, "poly_uv", None)
        if labels is None:
            labels = box_labels(face, mouth_boxes(face))
    labels = np.asarray(labels, dtype=np.int64)
    if labels.shape != pv.shape:
        raise ValueError(f"labels has shape {labels.shape}, the corners {pv.shape}")
    # copies of the unused vertices too, so every source vertex has one (the split keeps the source's order)
    rows = np.r_[np.c_[pv, labels], np.c_[np.arange(len(face.neutral)), np.full(len(face.neutral), labels.min())]]
    pairs, inv = np.unique(rows, axis=0, return_inverse=True)
    inv = inv.ravel()
    # a vertex used only by corners labelled above the minimum got an extra, unused copy: drop those
    used = np.zeros(len(pairs), bool)
    used[inv[: len(pv)]] = True
    first = np.r_[True, np.diff(pairs[:, 0]) != 0]
    keep = used | (first & ~np.isin(pairs[:, 0], pv))
    new = np.cumsum(keep) - 1
    source = pairs[keep, 0]
    cv = new[inv[: len(pv)]]
    tris, _ = triangulate(cv, off)
    return SplitFace(neutral=np.asarray(face.neutral)[source],
                     expressions={n: np.asarray(x)[source] for n, x in face.expressions.items()},
                     poly_verts=cv, poly_offsets=off, faces=np.asarray(tris, dtype=np.int64), source=source,
                     base=face)


def run_route(face, *, frames, train, error=None, strokes=None) -> dict:
    """The Dinev route on ``face``'s route scene: Auto Regions, Refine Lips on each of ``train``, Propagate ``frames``.

    The scene is :func:`~facelab_addon.testing.route.build_route_scene` (metres, head + jaw armature, unposed, the
    ``wide`` capture error, the main camera). Needs ``bpy`` with FaceLab registered.

    Parameters
    ----------
    face : face model
        As ``build_route_scene`` takes it (a :class:`SplitFace` too).
    frames : (T,) int
        The scene's frames, the range Propagate corrects.
    train : sequence of int
        The frames sketched (the truth's silhouettes through the main camera) and refined.
    error : (V,3) float, optional
        The capture error to use instead of the route's (object-local metres at key weight 1): a split face
        takes the welded face's, ``welded["error"][split.source]`` (the route's error model measures along the
        mesh, which a seam would cut, so its own error would be another truth).
    strokes : dict frame -> (upper_px, lower_px), optional
        Sketch pixels to draw instead of the truth's (the welded run's ``"strokes"``: one sketch for both).

    Returns
    -------
    dict
        ``rs`` (the RouteScene), ``error`` (V,3), ``width`` (mouth width, object-local), ``mouth``, ``lips`` (V,)
        bool (the groups Auto Regions wrote), ``strokes``, ``captured`` (T,V,3) evaluated without FaceLab's keys,
        ``refine`` (RefineResult per training frame), ``refined`` (k,V,3) the training frames after Refine,
        ``propagate`` (PropagateResult), ``propagated`` (T,V,3), ``truth`` (T,V,3) the evaluated truth, all
        object-local metres, and ``seconds``. ``rs`` is only alive until the next route scene is built.
    """
    import time

    from ..blender import caches
    from ..blender.camera import camera_from_blender
    from ..blender.mesh import vertex_group_mask
    from ..blender.strokes import new_lip_sketch, write_stroke_pixels
    from ..core.lips.lip_loop import loop_width
    from ..names import LIPS_GROUP, MOUTH_GROUP
    from ..pipeline.propagate import propagate
    from ..pipeline.refine import refine
    from ..pipeline.regions import auto_regions
    from .route import ERROR_KEY, build_route_scene, sketch_truth

    frames = np.asarray(frames)
    rs = build_route_scene(face, units="m", armature=True, frames=frames)
    scene, obj = rs.scene, rs.obj
    if error is not None:
        kb = obj.data.shape_keys.key_blocks[ERROR_KEY]
        co = np.empty(3 * len(obj.data.vertices))
        obj.data.shape_keys.reference_key.data.foreach_get("co", co)
        kb.data.foreach_set("co", (co + np.asarray(error).ravel()).astype(np.float32))
        rs.error = np.asarray(error)
    out = {"rs": rs, "error": rs.error, "width": loop_width(rs.neutral, rs.loop), "strokes": {}, "refine": []}
    t0 = time.perf_counter()
    auto_regions(obj, scene=scene)
    out["mouth"] = vertex_group_mask(obj, MOUTH_GROUP)
    out["lips"] = vertex_group_mask(obj, LIPS_GROUP)
    out["captured"] = caches.evaluate_frames(obj, frames).astype(np.float64)
    gp = None
    for f in train:
        if strokes is None:
            gp, up, lo = sketch_truth(rs, f, rs.cameras[0])
            out["strokes"][f] = (up, lo)
        else:
            scene.frame_set(int(f))
            cam = camera_from_blender(scene, rs.cameras[0])
            gp = new_lip_sketch(scene, rs.cameras[0], name="FL_LipSketch")
            write_stroke_pixels(gp, "Upper lip", int(f), [strokes[f][0]], cam)
            write_stroke_pixels(gp, "Lower lip", int(f), [strokes[f][1]], cam)
        out["refine"].append(refine(scene, obj, int(f), sketch=gp))
    out["refined"] = caches.evaluate_frames(obj, list(train), mute_shape_keys_prefix=()).astype(np.float64)
    out["propagate"] = propagate(scene, obj, frames)
    out["propagated"] = caches.evaluate_frames(obj, frames, mute_shape_keys_prefix=()).astype(np.float64)
    out["seconds"] = time.perf_counter() - t0
    out["truth"] = rs.evaluated_truth(frames)
    return out
