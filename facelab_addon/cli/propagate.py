"""Propagate the corrected (training) frames to every frame (Dinev et al. 2018 §4), like the
sidebar's Train & Propagate: Auto Regions when FL_mouth/FL_lips are missing, then Propagate.

Training frames are the ones already in the .blend (Refine Lips, Mark Training Frame), plus any
``--corrected FRAME:FILE.obj`` (the face corrected by hand on that frame, same vertex order), which
become corrective keys ``FL_Corrected_<frame>`` marked as training frames.

    python -m facelab_addon propagate SHOT.blend --object Face --frames 1-1200 --out SHOT_fixed.blend
    python -m facelab_addon propagate --mesh face.obj --cache perf.pc2 --corrected 12:fix12.obj \\
        --corrected 80:fix80.obj --out fixed.blend --bake fixed.pc2
"""

from __future__ import annotations

from pathlib import Path

from ._common import EXIT_INPUT, EXIT_OUTPUT, EXIT_USAGE, CliError, contiguous, parse_frames

HELP = "propagate the training frames' lip corrections to every frame (corrective shape keys)"


def add_arguments(p) -> None:
    p.add_argument("--corrected", action="append", default=[], metavar="FRAME:FILE.obj",
                   help="the face corrected on FRAME (an OBJ with the mesh's vertex order); repeatable")
    p.add_argument("--suggestions", type=int, default=3, metavar="N",
                   help="how many frames to suggest correcting next (timeline markers 'FL suggest'); default 3")
    p.add_argument("--no-auto-regions", dest="auto_regions", action="store_false",
                   help="fail instead of running Auto Regions when FL_mouth / FL_lips are missing")
    p.add_argument("--bake", metavar="FILE",
                   help="also bake the corrected performance to FILE (.pc2, .mdd or .abc) over the frames")


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
    import numpy as np

    from ..blender import caches
    from ..blender.shapekeys import add_corrective_key, key_spike
    from ..ui.ops import record_training_frame

    names = []
    for frame, path in specs:
        V = session.import_obj_vertices(path)
        if len(V) != len(obj.data.vertices):
            raise CliError(f"--corrected {frame}:{path}: {len(V)} vertices, '{obj.name}' has "
                           f"{len(obj.data.vertices)}; export the corrected face with the same topology.", EXIT_INPUT)
        if caches.sequence_source(obj) in ("mesh_cache", "mesh_sequence_cache"):
            caches.cache_to_shape_key_ready(obj)
        captured = caches.read_captured_frames(obj, [frame])[0].astype(np.float64)
        d = V - captured
        if caches.sequence_source(obj) in ("mesh_cache", "mesh_sequence_cache"):
            d = caches.correction_to_key_offsets(obj, captured, d)
        kb = add_corrective_key(obj, f"FL_Corrected_{frame:04d}", d)
        key_spike(kb, frame)
        record_training_frame(session.scene, obj, frame, kb.name, "sculpt")
        session.log(f"corrected frame {frame} from {path.name}: key '{kb.name}', max offset "
                    f"{np.linalg.norm(d, axis=1).max():.4g}")
        names.append(kb.name)
    return names


def run(args, session) -> dict:
    import numpy as np

    scene = session.scene
    obj = session.face()
    frames = parse_frames(args.frames, scene)
    f0, f1 = contiguous(frames, "propagate")
    specs = _corrected_specs(args.corrected)
    if args.bake and Path(args.bake).suffix.lower() not in (".pc2", ".mdd", ".abc"):
        raise CliError(f"--bake {args.bake}: give a .pc2, .mdd or .abc file.", EXIT_USAGE)
    if args.out and (obj.modifiers and any(m.type == "MESH_SEQUENCE_CACHE" for m in obj.modifiers)):
        session.save(args.out)  # an Alembic capture is baked to a PC2 beside the .blend: save it first
    added = add_corrected_frames(session, obj, specs)

    regions = "kept"
    if obj.vertex_groups.get("FL_mouth") is None or obj.vertex_groups.get("FL_lips") is None:
        if not args.auto_regions:
            raise CliError(f"'{obj.name}' has no FL_mouth / FL_lips vertex groups; paint them, or drop "
                           "--no-auto-regions to propose them automatically.")
        session.log("Auto Regions (FL_mouth / FL_lips missing)")
        session.call("auto_regions")
        regions = "auto"

    train = sorted({t.frame for t in obj.facelab.training_frames})
    session.log(f"propagating frames {f0}-{f1} ({len(frames):,}) from {len(train)} training frames {train[:12]}")
    import time

    t0 = time.perf_counter()
    session.call("propagate", frame_start=f0, frame_end=f1, suggestions=max(0, args.suggestions))
    dt = time.perf_counter() - t0
    keys = [kb.name for kb in obj.data.shape_keys.key_blocks if kb.name.startswith("FL_Prop_")]
    suggested = sorted(m.frame for m in scene.timeline_markers if m.name.startswith("FL suggest"))
    score = _keyed_curve(obj, '["FL_extrapolation"]', frames)
    session.log(f"Propagated to {len(frames):,} frames in {dt:.1f} s, {len(keys)} corrective shapes"
                + (f"; suggested next: {suggested}" if suggested else ""))
    result = {
        "object": obj.name,
        "frames": [f0, f1],
        "frame_count": len(frames),
        "training_frames": train,
        "corrected_keys_added": added,
        "regions": regions,
        "corrective_keys": keys,
        "suggested_frames": suggested,
        "propagate_seconds": round(dt, 3),
    }
    if score is not None:
        result["extrapolation"] = {"max": round(float(np.max(score)), 4), "mean": round(float(np.mean(score)), 4),
                                   "frames_over_0.5": [int(f) for f, s in zip(frames, score) if s > 0.5][:100]}
    if args.bake:
        fmt = {".pc2": "PC2", ".mdd": "MDD", ".abc": "ABC"}[Path(args.bake).suffix.lower()]
        p = Path(args.bake).resolve()
        if not p.parent.is_dir():
            raise CliError(f"--bake {args.bake}: the folder {p.parent} does not exist.", EXIT_OUTPUT)
        session.log(f"baking {fmt} to {p}")
        scene.frame_start, scene.frame_end = f0, f1
        session.call("bake", filepath=str(p), format=fmt, overwrite=True)
        result["bake"] = str(p)
    result["saved"] = session.save(args.out)
    return result


def _keyed_curve(obj, data_path, frames):
    """Values of an F-curve of ``obj``'s action at ``frames`` (None if not keyed)."""
    import numpy as np

    ad = obj.animation_data
    if ad is None or ad.action is None:
        return None
    from ..blender.shapekeys import _find_fcurve

    fc = _find_fcurve(ad, data_path)
    if fc is None:
        return None
    return np.array([fc.evaluate(f) for f in frames])
