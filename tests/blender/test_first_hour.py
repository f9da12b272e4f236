"""docs/first-hour.md walked through the operators, headless, on the sample shot
(:func:`facelab_addon.testing.first_hour.walk`): the shot ends closer to the truth than its capture, each
Propagate round keeps the refined frames, Review shows the capture and gives the corrections back, and the
bake holds the corrected shot."""

import numpy as np
import pytest

pytestmark = pytest.mark.blender


@pytest.mark.slow
def test_first_hour_on_the_sample(addon, tmp_path):
    from facelab_addon.testing.first_hour import walk

    w = walk(tmp_path)
    T0 = w.frames[0]
    assert w.suggested and not set(w.suggested) & set(w.first_round), w.suggested
    # each round keeps the refined frames: a training frame stays where Refine put it
    first = np.array(w.first_round) - T0
    np.testing.assert_allclose(w.round1[first], w.refined, atol=1e-5)

    held = np.setdiff1d(w.frames, w.training) - T0
    cap, r1, r2 = (np.sqrt((w.lip_error_mm(X)[held] ** 2).mean()) for X in (w.captured, w.round1, w.round2))
    print(f"first hour on the sample: held-out inner-lip RMS {cap:.3f} mm captured, {r1:.3f} after round 1 "
          f"({len(w.first_round)} frames), {r2:.3f} after round 2 ({len(w.training)} frames, suggested "
          f"{w.suggested})")
    assert r2 < 0.8 * cap, (cap, r2)
    assert w.lip_error_mm(w.round2).mean() < w.lip_error_mm(w.captured).mean()

    assert w.review["capture_shown"] and w.review["corrected_shown"] and w.review["heat_map"]
    np.testing.assert_allclose(w.review["capture"], w.captured[w.review["frame"] - T0], atol=1e-6)

    assert w.baked.shape == w.round2.shape and w.baked_start == T0
    np.testing.assert_allclose(w.baked, w.round2, atol=1e-5)


def test_the_page_names_the_walked_frames():
    """docs/first-hour.md tells the artist to sketch the frames the walk sketches first."""
    from pathlib import Path

    from facelab_addon.testing.first_hour import FIRST_ROUND

    page = (Path(__file__).resolve().parents[2] / "docs" / "first-hour.md").read_text()
    missing = [f for f in FIRST_ROUND if f"**{f}**" not in page]
    assert not missing, f"docs/first-hour.md does not name frame(s) {missing} of the walk's first round"
