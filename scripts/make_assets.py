"""Write the generated files of ``assets/`` (today: the sample lip mesh).

    python scripts/make_assets.py           # (re)write assets/meshes/lips.obj
    python scripts/make_assets.py --check   # exit 1 if the committed file differs from what it would write

``assets/meshes/lips.obj`` is the tiny analytic mouth of ``tests/core/lipmesh.py`` with its
default arguments (``two_lips()``: two facing half tubes along x, radius 0.5, 0.4 apart, camera on
+z, y up): 2,378 vertices and 4,480 triangles, coordinates written with ``repr`` so they read back
bit for bit. The faces of the upper lip are in OBJ group ``upper_lip``, the lower lip's in
``lower_lip`` (Blender's OBJ importer turns them into vertex groups with *Vertex Groups* ticked).
The presets in ``assets/presets/`` are written by hand, not by this script.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LIPS_OBJ = ROOT / "assets" / "meshes" / "lips.obj"


def lips_obj_text() -> str:
    """The OBJ text of ``two_lips()`` (vertices in order, 1-based triangles, one group per lip)."""
    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))
    from tests.core.lipmesh import two_lips

    V, F, upper = two_lips()
    lines = [
        "# FaceLab sample mouth: two facing half tubes (tests/core/lipmesh.py two_lips(), defaults).",
        "# Units: scene units; y up, the lips face +z; inner lips at y = +0.2 (upper) and -0.2 (lower).",
        "# Written by scripts/make_assets.py; do not edit by hand.",
        "o FaceLabLips",
    ]
    lines += [f"v {x!r} {y!r} {z!r}" for x, y, z in V.tolist()]
    face_upper = upper[F].all(axis=1)
    if not (face_upper | ~upper[F].any(axis=1)).all():
        raise SystemExit("two_lips(): a triangle joins the two lips; the groups would overlap.")
    for group, sel in (("upper_lip", face_upper), ("lower_lip", ~face_upper)):
        lines.append(f"g {group}")
        lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in F[sel].tolist()]
    if not (face_upper[: face_upper.sum()].all()):
        raise SystemExit("two_lips(): the upper lip's triangles do not come first; the group order would "
                         "reorder the faces.")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--check", action="store_true", help="compare instead of writing; exit 1 if out of date")
    args = ap.parse_args(argv)
    text = lips_obj_text()
    if args.check:
        ok = LIPS_OBJ.exists() and LIPS_OBJ.read_text() == text
        print(f"{LIPS_OBJ.relative_to(ROOT)}: {'up to date' if ok else 'OUT OF DATE; run python scripts/make_assets.py'}")
        return 0 if ok else 1
    LIPS_OBJ.parent.mkdir(parents=True, exist_ok=True)
    LIPS_OBJ.write_text(text)
    print(f"wrote {LIPS_OBJ.relative_to(ROOT)} ({LIPS_OBJ.stat().st_size / 1e3:.0f} kB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
