"""Propagate the corrected (training) frames to every frame (Dinev et al. 2018 §4), like the
sidebar's Train & Propagate: Auto Regions when FL_mouth/FL_lips are missing, then Propagate.

The Auto Regions band widths and the number of suggestions are the shot's settings (FaceLab >
Setup / Train & Propagate > Propagate Settings), or the flags below (saved with ``--out``).

Training frames are the ones already in the .blend (Refine Lips, Mark Training Frame), plus any
``--corrected FRAME:FILE.obj`` (the face corrected by hand on that frame, same vertex order), which
become corrective keys ``FL_Corrected_<frame>`` marked as training frames.

    python -m facelab_addon propagate SHOT.blend --object Face --frames 1-1200 --out SHOT_fixed.blend
    python -m facelab_addon propagate --mesh face.obj --cache perf.pc2 --corrected 12:fix12.obj \\
        --corrected 80:fix80.obj --out fixed.blend --bake fixed.pc2
"""

from __future__ import annotations

from pathlib import Path

from ..names import LIPS_GROUP, MOUTH_GROUP
from ._errors import EXIT_INPUT, EXIT_USAGE, CliError
from ._frames import contiguous, parse_frames

HELP = "propagate the training frames' lip corrections to every frame (corrective shape keys)"


def add_arguments(p) -> None:
    p.add_argument("--corrected", action="append", default=[], metavar="FRAME:FILE.obj",
                   help="the face corrected on FRAME (an OBJ with the mesh's vertex order); repeatable")
    p.add_argument("--no-auto-regions", dest="auto_regions", action="store_false",
                   help=f"fail instead of running Auto Regions when {MOUTH_GROUP} / {LIPS_GROUP} are missing")
    p.add_argument("--bake", metavar="FILE",
                   help="also bake the corrected performance to FILE (.pc2, .mdd or .abc) over the frames")
    p.add_argument("--overwrite", action="store_true",
                   help="let --bake replace an existing file (without it an existing file is refused, as in the panel)")


def _corrected_specs(specs):
    out = []
    for s in specs:
        frame, sep, path = s.partition(":")
        if not sep or not frame.strip().lstrip("-").isdigit():
            raise CliError(f"--corrected {s!r}: expected FRAME:FILE.obj, e.g. 12:face_fixed_0012.obj.", EXIT_USAGE)
        if not Path(path).is_file():
            raise CliError(f"--corrected {s!r}: no such file {path}; check the path.", EXIT_INPUT)
        out.append((int(frame), Path(path)))
    return out


def add_corrected_frames(session, obj, specs) -> list[str]:
    """Corrective keys from corrected OBJs, recorded as training frames; returns the key names."""
    from ..pipeline.training import add_corrected_frame

    names = []
    for frame, path in specs:
        V = session.import_obj_vertices(path)
        if len(V) != len(obj.data.vertices):
            raise CliError(f"--corrected {frame}:{path}: {len(V)} vertices, '{obj.name}' has "
                           f"{len(obj.data.vertices)}; export the corrected face with the same topology.", EXIT_INPUT)
        c = add_corrected_frame(session.scene, obj, frame, V)
        session.log(f"corrected frame {frame} from {path.name}: key '{c.shape_key}', max offset {c.max_offset:.4g}")
        names.append(c.shape_key)
    return names


def stage_logger(session, what):
    """A ``progress(stage, done, total)`` callback logging each stage and about every 10 % of it."""
    shown = [None, -1]

    def update(stage, done, total):
        factor = min(1.0, done / total) if total else 0.0
        tenth = int(10 * factor)
        if stage != shown[0] or tenth > shown[1]:
            shown[:] = stage, tenth
            session.log(f"{what}: {stage} ({int(100 * factor)} %)")

    return update


def run(args, session) -> dict:
    import time

    import numpy as np

    from ..pipeline import wording
    from ..pipeline.bake import BakeSettings, bake
    from ..pipeline.propagate import PropagateSettings, propagate
    from ..pipeline.regions import RegionSettings, auto_regions
    from ..pipeline.shot_settings import scene_settings

    scene = session.scene
    obj = session.face()
    frames = parse_frames(args.frames, scene)
    f0, f1 = contiguous(frames, "propagate")
    specs = _corrected_specs(args.corrected)
    if args.out and (obj.modifiers and any(m.type == "MESH_SEQUENCE_CACHE" for m in obj.modifiers)):
        session.save(args.out)  # an Alembic capture is baked to a PC2 beside the .blend: save it first
    added = add_corrected_frames(session, obj, specs)

    regions = "kept"
    if obj.vertex_groups.get(MOUTH_GROUP) is None or obj.vertex_groups.get(LIPS_GROUP) is None:
        if not args.auto_regions:
            raise CliError(f"'{obj.name}' has no {MOUTH_GROUP} / {LIPS_GROUP} vertex groups; paint them, or drop "
                           "--no-auto-regions to propose them automatically.")
        session.log(f"Auto Regions ({MOUTH_GROUP} / {LIPS_GROUP} missing)")
        auto_regions(obj, scene_settings(scene, RegionSettings))
        regions = "auto"

    train = sorted({t.frame for t in obj.facelab.training_frames})
    session.log(f"propagating frames {f0}-{f1} ({len(frames):,}) from {len(train)} training frames {train[:12]}")
    if not len(obj.facelab.training_frames):
        raise CliError("Correct at least one frame first (Refine Lips, or sculpt and Mark Training Frame)")
    t0 = time.perf_counter()
    r = propagate(scene, obj, np.arange(f0, f1 + 1), scene_settings(scene, PropagateSettings),
                  progress=stage_logger(session, "propagate"))
    dt = time.perf_counter() - t0
    suggested = sorted(r.suggested)
    score = r.extrapolation.astype(np.float32)  # the values keyed on the object
    session.log(wording.join([
        wording.propagate_headline(len(frames), dt, r.rank, len(r.training), r.whole_weight,
                                   wording.forced_whole_reason(r.model)),
        f"correct next (suggested): frames {', '.join(map(str, suggested))}" if suggested else ""]))
    result = {
        "object": obj.name,
        "frames": [f0, f1],
        "frame_count": len(frames),
        "training_frames": train,
        "corrected_keys_added": added,
        "regions": regions,
        "corrective_keys": r.keys,
        "suggested_frames": suggested,
        "model": r.model,
        "propagate_seconds": round(dt, 3),
        "extrapolation": {"max": round(float(np.max(score)), 4), "mean": round(float(np.mean(score)), 4),
                          "frames_over_0.5": [int(f) for f, s in zip(frames, score) if s > 0.5][:100]},
    }
    if args.bake:
        fmt = {".pc2": "PC2", ".mdd": "MDD", ".abc": "ABC"}[Path(args.bake).suffix.lower()]
        p = Path(args.bake).resolve()
        session.log(f"baking {fmt} to {p}")
        scene.frame_start, scene.frame_end = f0, f1  # the saved scene's range is the baked range
        frame_done = session.progress(f"bake {fmt}", len(frames))
        bake(obj, np.arange(f0, f1 + 1), p, BakeSettings(format=fmt, overwrite=args.overwrite),
             progress=lambda stage, done, total: frame_done(done - 1, total))
        result["bake"] = str(p)
    result["saved"] = session.save(args.out)
    return result
