"""The pictures of docs/first-hour.md drawn from a headless walk of the page on the sample shot
(:func:`facelab_addon.testing.first_hour.walk`):

    python scripts/first_hour_figures.py [--images docs/images]

Writes ``first_hour_regions.png`` (Auto Regions' FL_mouth and FL_lips over the plate) and
``first_hour_timeline.png`` (inner-lip error per frame: the capture, after the first Propagate, and the
baked shot after the second).
"""

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--images", default=str(ROOT / "docs" / "images"))
    args = ap.parse_args(argv)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from facelab_addon import register
    from facelab_addon.testing.first_hour import walk

    register()
    with tempfile.TemporaryDirectory() as tmp:
        w = walk(tmp)
    img = Path(args.images)
    T0 = int(w.frames[0])

    # Auto Regions over the plate of the first sketched frame
    f = w.first_round[0]
    plate = plt.imread(str(ROOT / "assets" / "sample" / "plate" / f"plate_{f:04d}.jpg"))
    P = w.camera.project(w.captured[f - T0])
    sel = w.mouth | w.lips
    lo, hi = P[sel].min(0) - 60, P[sel].max(0) + 60
    fig, ax = plt.subplots(figsize=(7, 3.6))
    ax.imshow(plate)
    ax.scatter(*P[w.mouth & ~w.lips].T, s=4, c="tab:blue", label="FL_mouth (read to predict)")
    ax.scatter(*P[w.lips].T, s=4, c="tab:orange", label="FL_lips (corrected)")
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(hi[1], lo[1])
    ax.set_axis_off()
    ax.legend(loc="lower right", fontsize=8, markerscale=3)
    ax.set_title(f"Auto Regions on the sample (frame {f})")
    fig.savefig(img / "first_hour_regions.png", dpi=90, bbox_inches="tight")
    plt.close(fig)

    # the timeline: capture, round 1, the baked round 2
    fig, ax = plt.subplots(figsize=(10, 3.2))
    fr = w.frames
    ax.plot(fr, w.lip_error_mm(w.captured), c="grey", lw=2, label="capture")
    ax.plot(fr, w.lip_error_mm(w.round1), c="tab:orange", lw=1.5, ls="--",
            label=f"after Propagate, {len(w.first_round)} refined frames")
    e2 = w.lip_error_mm(w.baked)
    ax.plot(fr, e2, c="tab:red", lw=2, label=f"baked after the second Propagate, {len(w.training)} refined frames")
    first = np.array(w.first_round)
    sug = np.array(w.suggested)
    ax.scatter(first, e2[first - T0], c="k", zorder=3, label="first sketched frames")
    ax.scatter(sug, e2[sug - T0], c="white", edgecolors="k", zorder=3, label="suggested frames, sketched")
    ax.set_xlabel("frame")
    ax.set_ylabel("inner-lip RMS error (mm)")
    ax.set_ylim(bottom=0)
    ax.set_title("The sample's inner-lip error per frame: where each round helps, and where it does not yet")
    ax.legend(fontsize=8, ncol=3, loc="upper center", bbox_to_anchor=(0.5, -0.2))
    fig.savefig(img / "first_hour_timeline.png", dpi=90, bbox_inches="tight")
    plt.close(fig)
    print(f"wrote {img / 'first_hour_regions.png'} and {img / 'first_hour_timeline.png'}")


if __name__ == "__main__":
    main()
