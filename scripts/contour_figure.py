"""Figure for docs/contours.md: candidate loops, occluding contours and correspondences on ICT-FaceKit.

Like Bhat et al. 2013, Fig. 2: for one helmet camera, the candidate mouth loops (grey), the silhouette edges
among them (red), the chosen occluding half-loops (yellow), a tracked curve (blue) and the correspondence of
every contour point (green ticks), for a slightly open mouth with and without mouthRollUpper (the upper lip's occluding
contour moves outward by several rings).

Also the eyelids of the left eye (docs/images/contours_eyelids.png).

Run:  PYTHONPATH=. .venv/bin/python scripts/contour_figure.py [out.png]
"""

import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from facelab_addon.core.capture.camera import Camera  # noqa: E402
from facelab_addon.core.capture.ict import load_ict  # noqa: E402
from facelab_addon.core.solve.contour_loops import MOUTH_CURVES  # noqa: E402
from facelab_addon.core.solve.matching import MatchParams, match_contours  # noqa: E402
from facelab_addon.core.solve.occlusion import _facing_sign, half_silhouette_counts  # noqa: E402
from facelab_addon.testing.contour_truth import (  # noqa: E402
    ict_contour_loops,
    synthetic_tracked_curves,
)


def main(out="docs/images/contours_selection.png"):
    m = load_ict()
    loops = ict_contour_loops(m)
    tgt = m.neutral[6632:6706].mean(0) + [0, 2.0, 0]
    cam = Camera.look_at(tgt + [-5.0, -6.0, 30.0], tgt, [0, 1, 0], 100, 36, 3840, 2160)  # zoomed on the mouth
    fig, axes = plt.subplots(1, 2, figsize=(15, 5.5))
    poses = {"jawOpen 0.25": {"jawOpen": 0.25},
             "jawOpen 0.25 + mouthRollUpper 0.9": {"jawOpen": 0.25, "mouthRollUpper": 0.9}}
    for ax, (expr, w) in zip(axes, poses.items()):
        V = m.pose(w)
        # the "tracked" curves: the truth's occluding contours, displaced by 8 px so the matching shows
        curves = synthetic_tracked_curves(V, m.faces, [cam], loops, names=list(MOUTH_CURVES))
        for c in curves:
            c.pixels = c.pixels + [0.0, -8.0 if c.name == "mouth_upper" else 8.0]
        corr = match_contours(V, m.faces, [cam], curves, loops)
        P = cam.project(V)
        counts = half_silhouette_counts(V, cam, loops)
        for k, lp in enumerate(loops.mouth):
            q = P[np.r_[lp, lp[:1]]]
            ax.plot(q[:, 0], q[:, 1], color="0.75", lw=0.6, zorder=1)
        # silhouette edges on the candidates
        (tri, inv), ok, hid = loops._pack[:3]
        s = _facing_sign(V, tri, cam)[inv]
        sil = ok & (s[:, 0] != s[:, 1])
        for name in MOUTH_CURVES:
            lo, hi = loops._pack[4][name]
            for k, h in enumerate(loops.halves[name]):
                mask = sil[hid == lo + k]
                for (a, b), on in zip(zip(h.chain[:-1], h.chain[1:]), mask):
                    if on:
                        ax.plot(P[[a, b], 0], P[[a, b], 1], color="red", lw=1.0, zorder=4)
        for c, cv in zip(corr, curves):
            X = cam.project(c.evaluate(V))
            ax.plot(X[:, 0], X[:, 1], color="gold", lw=4, zorder=2)
            ax.plot(cv.pixels[:, 0], cv.pixels[:, 1], color="royalblue", lw=1.2, zorder=3)
            for a, b in zip(X, c.pixels):
                ax.plot([a[0], b[0]], [a[1], b[1]], color="green", lw=0.8, zorder=5)
            lo, hi = loops._pack[4][c.name]
            h = loops.halves[c.name][c.loop]
            S = X[h.splits]
            ax.plot(S[:, 0], S[:, 1], "ko", ms=4, zorder=6)
            ax.text(X[len(X) // 2, 0], X[len(X) // 2, 1] + (-60 if c.name == "mouth_upper" else 80),
                    f"{c.name}: ring {c.loop} ({counts[lo + c.loop]} silhouette edges)", ha="center", fontsize=8)
        box = P[np.concatenate(loops.mouth)]
        ax.set_xlim(box[:, 0].min() - 15, box[:, 0].max() + 15)
        ax.set_ylim(box[:, 1].max() + 40, box[:, 1].min() - 40)
        ax.set_aspect("equal")
        ax.set_title(f"{expr}: 14 candidate loops (grey), silhouette edges (red),\n"
                     "occluding half-loops (yellow), tracked curves (blue), correspondences (green)", fontsize=9)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    print(out)


def eyelids(out="docs/images/contours_eyelids.png"):
    """The left eye from the right helmet camera: eyelid loops, occluding halves, 3D targets on the eyeball."""
    from facelab_addon.testing.capture_sim import helmet_cameras

    m = load_ict()
    loops = ict_contour_loops(m)
    cam = helmet_cameras()[1]
    fig, axes = plt.subplots(1, 2, figsize=(14, 5))
    poses = {"neutral": {}, "eyeBlink 0.5 + eyeLookDown_L 0.4": {"eyeBlink_L": 0.5, "eyeLookDown_L": 0.4}}
    for ax, (title, w) in zip(axes, poses.items()):
        X = m.pose(w)
        curves = synthetic_tracked_curves(X, m.faces, [cam], loops, names=["eyelid_left_upper", "eyelid_left_lower"])
        for c in curves:  # moved 3 px away from the lid so the pairing shows
            c.pixels = c.pixels + [0.0, -3.0 if c.name.endswith("upper") else 3.0]
        corr = match_contours(X, m.faces, [cam], curves, loops, MatchParams(eyelids="both"))
        P = cam.project(X)
        for lp in loops.eyes["left"]:
            q = P[np.r_[lp, lp[:1]]]
            ax.plot(q[:, 0], q[:, 1], color="0.7", lw=0.6)
        for c in corr:
            Xp = cam.project(c.evaluate(X))
            if c.camera >= 0:
                ax.plot(Xp[:, 0], Xp[:, 1], color="gold", lw=3)
                for a, b in zip(Xp, c.pixels):
                    ax.plot([a[0], b[0]], [a[1], b[1]], color="green", lw=0.7)
            else:
                T = cam.project(c.targets)
                ax.plot(T[:, 0], T[:, 1], ".", color="magenta", ms=3)
        for c in curves:
            ax.plot(c.pixels[:, 0], c.pixels[:, 1], color="royalblue", lw=1)
        cor = cam.project(X[loops.eye_corners["left"].ravel()])
        ax.plot(cor[:, 0], cor[:, 1], "k.", ms=5)
        box = P[np.concatenate(loops.eyes["left"])]
        ax.set_xlim(box[:, 0].min() - 10, box[:, 0].max() + 10)
        ax.set_ylim(box[:, 1].max() + 10, box[:, 1].min() - 10)
        ax.set_aspect("equal")
        rings = [c.loop for c in corr if c.camera >= 0]
        ax.set_title(f"{title}: occluding halves on rings {rings}", fontsize=10)
    fig.suptitle("Left eye, right helmet camera: 4 eyelid loops (grey), occluding halves (yellow), tracked curves "
                 "(blue), correspondences (green),\n3D targets on the eyeball reprojected (magenta), corners (black)",
                 fontsize=10)
    fig.tight_layout()
    fig.savefig(out, dpi=100)
    print(out)


if __name__ == "__main__":
    main(*sys.argv[1:])
    eyelids()
