"""docs/first-hour.md walked through the operators on the sample shot, headless (``bpy`` needed).

:func:`walk` runs the page's steps in the current Blender: Load Sample, Auto Regions, New Lip Sketch with
the *Upper lip* stroke, Lower Lip and its stroke, Refine Lips from Draw mode (the first frame through Live
Refine + Accept), Propagate, the suggested frames sketched the same way and Propagate again, Show Capture
and Show Corrected, Correction Heat Map, Bake PC2. The strokes trace the truth's inner-lip silhouettes, as
an artist traces the plate. ``tests/blender/test_first_hour.py`` checks the result;
``scripts/first_hour_figures.py`` draws the page's pictures from it.
"""

from dataclasses import dataclass, field
from pathlib import Path

import bpy
import numpy as np

from ..blender.caches import evaluate_frames
from ..blender.camera import camera_from_blender
from ..blender.mesh import vertex_group_mask
from ..blender.review import showing_capture
from ..blender.sample import read_sample
from ..blender.strokes import write_stroke_pixels
from ..core.capture.camera import Camera
from ..core.capture.pointcache import read_pc2
from ..core.lips.mouth import find_mouth
from ..names import CORRECTION_ATTR, LIPS_GROUP, MOUTH_GROUP, SUGGEST_MARKER
from . import synthetic as syn

#: The frames first-hour.md names for the first round (the lips plainly open on the plate).
FIRST_ROUND = (11, 37, 44)


@dataclass
class FirstHour:
    """What the walk made. Arrays are (T,V,3) object-space positions in metres over ``frames`` (T,)."""

    data: object  # the sample (facelab_addon.blender.sample.read_sample())
    camera: Camera
    frames: np.ndarray
    truth: np.ndarray
    captured: np.ndarray
    refined: np.ndarray  # (len(first_round),V,3) the first round's frames just after Refine Lips
    round1: np.ndarray
    round2: np.ndarray
    baked: np.ndarray  # the PC2 Bake wrote
    baked_start: float
    first_round: tuple
    suggested: list
    mouth: np.ndarray  # (V,) bool FL_mouth
    lips: np.ndarray  # (V,) bool FL_lips
    review: dict = field(default_factory=dict)  # frame, capture/corrected shown, heat map made

    @property
    def training(self) -> list:
        return sorted({*self.first_round, *self.suggested})

    def lip_error_mm(self, X) -> np.ndarray:
        """(T,) inner-lip RMS distance to the truth per frame, mm, over the vertices the capture has off by
        more than 0.2 mm."""
        lips = np.linalg.norm(self.data.capture_error, axis=1) > 2e-4
        return 1e3 * np.sqrt((np.linalg.norm(X - self.truth, axis=2)[:, lips] ** 2).mean(1))


def triangles(data) -> np.ndarray:
    """(F,3) triangles of the sample's polygons (fans)."""
    pv, po = data.poly_verts, data.poly_offsets
    return np.array([[pv[s], pv[s + k], pv[s + k + 1]] for s, e in zip(po[:-1], po[1:]) for k in range(1, e - s - 1)])


def walk(out_dir, first_round=FIRST_ROUND) -> FirstHour:
    """Run first-hour.md in a factory-fresh scene; the bake goes to ``out_dir/sample_fixed.pc2``."""
    data = read_sample()
    bpy.ops.wm.read_factory_settings(use_empty=True)
    assert bpy.ops.facelab.load_sample() == {"FINISHED"}
    scene = bpy.context.scene
    face = scene.facelab.face
    F = triangles(data)
    truth, captured, frames = data.truth(), data.captured(), data.frames
    mouth = find_mouth(data.vertices, F, None, near=data.vertices[data.inner_lip_loop].mean(0),
                       units_per_mm=0.001)
    cam = Camera(data.camera.K, data.camera.R, data.camera.t, data.camera.width, data.camera.height)
    bcam = camera_from_blender(scene)

    assert bpy.ops.facelab.auto_regions() == {"FINISHED"}

    def sketch(f, live=False):
        upper, lower = syn.lip_contours(truth[f - frames[0]], F, cam, mouth=mouth)
        scene.frame_set(f)
        bpy.context.view_layer.objects.active = face
        assert bpy.ops.facelab.new_lip_sketch() == {"FINISHED"}
        gp = scene.facelab.sketch
        assert bpy.context.view_layer.objects.active == gp and gp.data.layers.active.name == "Upper lip"
        write_stroke_pixels(gp, "Upper lip", f, [upper], bcam)
        assert bpy.ops.facelab.sketch_lip_layer(lip="lower") == {"FINISHED"}
        assert gp.data.layers.active.name == "Lower lip"
        write_stroke_pixels(gp, "Lower lip", f, [lower], bcam)
        if live:
            assert bpy.ops.facelab.live_refine() == {"FINISHED"}
            assert bpy.ops.facelab.live_refine_update() == {"FINISHED"}
            assert bpy.ops.facelab.live_refine_accept() == {"FINISHED"}
        else:
            assert bpy.ops.facelab.refine_lips() == {"FINISHED"}  # from Draw mode

    def shot():
        if bpy.context.object is not None and bpy.context.object.mode != "OBJECT":
            bpy.ops.object.mode_set(mode="OBJECT")
        bpy.context.view_layer.objects.active = face
        return evaluate_frames(face, frames, mute_shape_keys_prefix=())

    for i, f in enumerate(first_round):
        sketch(f, live=(i == 0))
    refined = shot()[np.array(first_round) - frames[0]]
    assert bpy.ops.facelab.propagate() == {"FINISHED"}
    suggested = sorted(m.frame for m in scene.timeline_markers if m.name.startswith(SUGGEST_MARKER))
    round1 = shot()
    for f in suggested:
        sketch(f)
    bpy.context.view_layer.objects.active = face
    assert bpy.ops.facelab.propagate() == {"FINISHED"}
    round2 = shot()

    held = [int(f) for f in frames if f not in {*first_round, *suggested}]
    f_show = held[0]
    scene.frame_set(f_show)
    review = {"frame": f_show}
    assert bpy.ops.facelab.review_toggle() == {"FINISHED"}
    review["capture_shown"] = showing_capture(face)
    review["capture"] = evaluate_frames(face, [f_show], mute_shape_keys_prefix=())[0]
    assert bpy.ops.facelab.review_toggle() == {"FINISHED"}
    review["corrected_shown"] = not showing_capture(face)
    assert bpy.ops.facelab.correction_heatmap() == {"FINISHED"}
    review["heat_map"] = face.data.color_attributes.get(CORRECTION_ATTR) is not None

    out = Path(out_dir) / "sample_fixed.pc2"
    assert bpy.ops.facelab.bake(format="PC2", filepath=str(out)) == {"FINISHED"}
    baked, start, _rate = read_pc2(str(out))
    return FirstHour(data=data, camera=cam, frames=np.asarray(frames), truth=truth, captured=captured,
                     refined=refined, round1=round1, round2=round2, baked=np.asarray(baked), baked_start=start,
                     first_round=tuple(first_round), suggested=suggested,
                     mouth=vertex_group_mask(face, MOUTH_GROUP), lips=vertex_group_mask(face, LIPS_GROUP),
                     review=review)
