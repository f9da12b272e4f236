"""docs/first-hour.md walked through the operators, headless, on the sample shot: Load Sample, Auto Regions,
New Lip Sketch and the two lip layers, Refine Lips (and once Live Refine + Accept), Propagate, the suggested
frames sketched and Propagate again, Review (Show Capture / Show Corrected, Heat Map), Bake PC2. The
sketches trace the truth's inner-lip silhouettes, as an artist traces the plate. The shot ends closer to
the truth than its capture, and each Propagate round keeps the refined frames."""

import bpy
import numpy as np
import pytest

from facelab_addon.blender.caches import evaluate_frames
from facelab_addon.blender.camera import camera_from_blender
from facelab_addon.blender.review import showing_capture
from facelab_addon.blender.sample import read_sample
from facelab_addon.blender.strokes import write_stroke_pixels
from facelab_addon.core.capture.camera import Camera
from facelab_addon.core.capture.pointcache import read_pc2
from facelab_addon.names import CORRECTION_ATTR, SUGGEST_MARKER

pytestmark = [pytest.mark.blender, pytest.mark.slow]

#: The frames first-hour.md names for the first round (the lips plainly open on the plate).
FIRST_ROUND = (11, 37, 44)


def _triangles(data):
    pv, po = data.poly_verts, data.poly_offsets
    return np.array([[pv[s], pv[s + k], pv[s + k + 1]] for s, e in zip(po[:-1], po[1:]) for k in range(1, e - s - 1)])


def test_first_hour_on_the_sample(addon, tmp_path):
    from facelab_addon.testing import synthetic as syn

    data = read_sample()
    bpy.ops.wm.read_factory_settings(use_empty=True)
    assert bpy.ops.facelab.load_sample() == {"FINISHED"}
    scene = bpy.context.scene
    face = scene.facelab.face
    F = _triangles(data)
    truth, captured, frames = data.truth(), data.captured(), data.frames
    mouth = syn.find_mouth(data.vertices, F, None, near=data.vertices[data.inner_lip_loop].mean(0),
                           units_per_mm=0.001)
    cam = Camera(data.camera.K, data.camera.R, data.camera.t, data.camera.width, data.camera.height)
    bcam = camera_from_blender(scene)

    assert bpy.ops.facelab.auto_regions() == {"FINISHED"}

    def sketch(f, live=False):
        """New Lip Sketch on frame f, the upper lip drawn, Lower Lip, the lower drawn, then Refine Lips from
        Draw mode (or Live Refine + Accept)."""
        upper, lower = syn.lip_contours(truth[f - 1], F, cam, mouth=mouth)
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

    def rms_mm(X, idx):
        lips = np.linalg.norm(data.capture_error, axis=1) > 2e-4  # where the capture is off by > 0.2 mm
        return 1e3 * np.sqrt((np.linalg.norm(X[idx] - truth[idx], axis=2)[:, lips] ** 2).mean())

    def shot():
        bpy.ops.object.mode_set(mode="OBJECT") if bpy.context.object and bpy.context.object.mode != "OBJECT" else None
        bpy.context.view_layer.objects.active = face
        return evaluate_frames(face, frames, mute_shape_keys_prefix=())

    for i, f in enumerate(FIRST_ROUND):
        sketch(f, live=(i == 0))
    assert sorted(t.frame for t in face.facelab.training_frames) == list(FIRST_ROUND)
    refined = shot()[np.array(FIRST_ROUND) - frames[0]]
    bpy.context.view_layer.objects.active = face
    assert bpy.ops.facelab.propagate() == {"FINISHED"}
    suggested = sorted(m.frame for m in scene.timeline_markers if m.name.startswith(SUGGEST_MARKER))
    assert suggested and not set(suggested) & set(FIRST_ROUND), suggested
    round1 = shot()
    # each round keeps the refined frames: a training frame stays close to what Refine showed
    kept = np.abs(round1[np.array(FIRST_ROUND) - frames[0]] - refined).max()

    for f in suggested:
        sketch(f)
    bpy.context.view_layer.objects.active = face
    assert bpy.ops.facelab.propagate() == {"FINISHED"}
    round2 = shot()

    train = sorted({*FIRST_ROUND, *suggested})
    held = np.setdiff1d(frames, train) - frames[0]
    every = frames - frames[0]
    before, after1, after2 = rms_mm(captured, held), rms_mm(round1, held), rms_mm(round2, held)
    print(f"first hour on the sample: inner-lip RMS of held-out frames {before:.3f} mm captured, "
          f"{after1:.3f} after round 1 ({len(FIRST_ROUND)} frames), {after2:.3f} after round 2 "
          f"({len(train)} frames; suggested {suggested}); all frames {rms_mm(captured, every):.3f} -> "
          f"{rms_mm(round2, every):.3f}; training frames kept within {kept * 1e3:.3f} mm")
    assert after2 < 0.8 * before, (before, after2)
    assert rms_mm(round2, every) < rms_mm(captured, every)

    # Review: Show Capture shows the capture, Show Corrected gives the corrections back
    f_show = int(held[0] + frames[0])
    scene.frame_set(f_show)
    assert bpy.ops.facelab.review_toggle() == {"FINISHED"} and showing_capture(face)
    np.testing.assert_allclose(evaluate_frames(face, [f_show], mute_shape_keys_prefix=())[0],
                               captured[f_show - frames[0]], atol=1e-6)
    assert bpy.ops.facelab.review_toggle() == {"FINISHED"} and not showing_capture(face)
    assert bpy.ops.facelab.correction_heatmap() == {"FINISHED"}
    assert face.data.color_attributes.get(CORRECTION_ATTR) is not None

    # Bake: the PC2 holds the corrected shot
    out = tmp_path / "sample_fixed.pc2"
    assert bpy.ops.facelab.bake(format="PC2", filepath=str(out)) == {"FINISHED"}
    baked, start, _rate = read_pc2(str(out))
    assert baked.shape[0] == len(frames) and start == frames[0]
    np.testing.assert_allclose(baked, round2, atol=1e-5)
