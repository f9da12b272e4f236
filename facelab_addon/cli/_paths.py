"""Paths of the CLI: ``~``, outputs checked against each other, the inputs and the file system before any
work, and the files a .blend plays checked before Blender opens it."""

from __future__ import annotations

import os
from pathlib import Path

from ._errors import EXIT_INPUT, EXIT_OUTPUT, EXIT_USAGE, CliError
from ._stdout import quiet_stdout


def same_file(a: Path, b: Path) -> bool:
    """Whether two absolute paths name one file (the same path, or links to one file)."""
    if a == b:
        return True
    try:
        return a.exists() and b.exists() and os.path.samefile(a, b)
    except OSError:
        return False


#: Path options expanded (``~``) and checked against each other: (flag, attribute).
OUTPUT_FLAGS = (("--out", "out"), ("--json", "json_path"), ("--bake", "bake"))
INPUT_FLAGS = (("SHOT.blend", "blend"), ("--mesh", "mesh"), ("--cache", "cache"), ("--rest", "rest"))


def expand_paths(args) -> None:
    """``~`` and ``~user`` in every path option, as a shell would (``--out=~/x.blend`` and paths given from
    Python reach FaceLab unexpanded)."""
    for _, attr in OUTPUT_FLAGS + INPUT_FLAGS:
        v = getattr(args, attr, None)
        if isinstance(v, str) and v.startswith("~"):
            setattr(args, attr, os.path.expanduser(v))
    specs = getattr(args, "corrected", None)
    if specs:
        out = []
        for s in specs:
            frame, sep, path = s.partition(":")
            out.append(f"{frame}:{os.path.expanduser(path)}" if sep and path.startswith("~") else s)
        args.corrected = out


def check_distinct_outputs(args) -> None:
    """Refuse, before anything is read or written, two outputs that are one file (``--json X.blend --out
    X.blend``: the summary would overwrite the saved .blend) and an output that is an input file (FaceLab
    never writes over its input)."""
    outs = [(f, Path(v).resolve()) for f, a in OUTPUT_FLAGS if (v := getattr(args, a, None))]
    ins = [(f, Path(v).resolve()) for f, a in INPUT_FLAGS if (v := getattr(args, a, None))]
    for s in getattr(args, "corrected", None) or []:
        frame, sep, path = s.partition(":")
        if sep and path:
            ins.append((f"--corrected {s}", Path(path).resolve()))
    for i, (fa, pa) in enumerate(outs):
        for fb, pb in outs[i + 1:]:
            if same_file(pa, pb):
                raise CliError(f"{fa} and {fb} are the same file ({pa}): one output would overwrite the other. "
                               "Give each its own file.", EXIT_USAGE, json_to_stdout=True)
        for fb, pb in ins:
            if same_file(pa, pb):
                raise CliError(f"{fa} {pa} is the input {fb}: FaceLab never writes over its input. Give another "
                               f"file, such as {pa.stem}_fixed{pa.suffix}.", EXIT_USAGE, json_to_stdout=True)


def played_files(bpy) -> list:
    """``[(what, absolute path)]`` of every file the open scene reads: Mesh Cache modifiers (FaceLab's
    correction caches included), Alembic Cache Files, linked libraries, images and movie clips."""
    out = []
    for ob in bpy.data.objects:
        for md in ob.modifiers:
            if md.type == "MESH_CACHE" and md.filepath:
                out.append((f"the Mesh Cache '{md.name}' of '{ob.name}'", md.filepath, ob.library))
    for kind, coll in (("the Cache File", bpy.data.cache_files), ("the library", bpy.data.libraries),
                       ("the image", bpy.data.images), ("the Movie Clip", bpy.data.movieclips)):
        for d in coll:
            fp = getattr(d, "filepath", "")
            if fp:
                out.append((f"{kind} '{d.name}'", fp, getattr(d, "library", None)))
    return [(what, Path(bpy.path.abspath(fp, library=lib)).resolve()) for what, fp, lib in out]


def check_outputs_not_played(args, bpy) -> None:
    """Refuse an output that is a file the opened scene reads (its capture, a cache, a library, footage):
    writing it would destroy what the result is made from."""
    played = played_files(bpy)
    for flag, attr in OUTPUT_FLAGS:
        v = getattr(args, attr, None)
        if not v:
            continue
        p = Path(v).resolve()
        hit = next((what for what, f in played if same_file(p, f)), None)
        if hit is not None:
            raise CliError(f"{flag} {v}: the scene reads this file ({hit}), so writing it would overwrite what "
                           f"the result is made from; choose another file, such as {p.stem}_fixed{p.suffix}.",
                           EXIT_USAGE, json_to_stdout=True)


def check_outputs(args, opened: str = "", only=None) -> None:
    """Refuse a bad ``--out``, ``--json`` or ``--bake`` before any work is done: the wrong type, a
    folder that does not exist or cannot be written, a name the file system cannot hold, an existing
    ``--bake`` file without ``--overwrite`` (the panel's rule), the open .blend ``opened`` itself.
    ``only``: check that flag alone (``"--out"`` when saving)."""
    from ..core.capture.pointcache_writer import check_writable
    from ..core.errors import OutputError

    checks = [("--out", getattr(args, "out", None), (".blend",)), ("--json", getattr(args, "json_path", None), None),
              ("--bake", getattr(args, "bake", None), (".pc2", ".mdd", ".abc"))]
    for flag, out, exts in checks:
        if not out or (only and flag != only):
            continue
        p = Path(out).resolve()
        if exts and p.suffix.lower() not in exts:
            raise CliError(f"{flag} {out}: give a {' or '.join(exts)} file.", EXIT_USAGE)
        try:
            check_writable(p)
        except OutputError as e:
            raise CliError(f"{flag} {out}: {e}", EXIT_OUTPUT) from None
        if not p.parent.is_dir():
            raise CliError(f"{flag} {out}: the folder {p.parent} does not exist; create it first.", EXIT_OUTPUT)
        if opened and not args.blend and not getattr(args, "mesh", None) and same_file(p, Path(opened)):
            raise CliError(f"{flag} {out} is the .blend Blender opened, FaceLab's input: it never writes over "
                           f"its input. Give another file, such as {p.stem}_fixed{p.suffix}.", EXIT_USAGE,
                           json_to_stdout=True)
        if flag == "--bake" and p.exists() and not getattr(args, "overwrite", False):
            raise CliError(f"--bake {out}: the file exists; give --overwrite to replace it (the panel's Overwrite), "
                           "or choose another file.", EXIT_OUTPUT)


def check_blend_caches(bpy, p: Path) -> None:
    """Refuse a .blend that plays a broken Alembic file before Blender opens it: Blender's Alembic reader
    aborts the whole process on a truncated file. The file's Cache Files are linked (not evaluated) to read
    their paths; a missing file is left to the checks after opening (Blender plays it as the static mesh)."""
    from ..blender.caches import alembic_file_problem

    try:
        with quiet_stdout(), bpy.data.libraries.load(str(p.resolve()), link=True) as (src, dst):
            dst.cache_files = list(src.cache_files)
    except (OSError, RuntimeError, ValueError):
        return  # unreadable: open_mainfile says why
    for cf in dst.cache_files:
        if cf is None:
            continue
        paths = [cf.filepath] + [lay.filepath for lay in getattr(cf, "layers", ())]
        for fp in paths:
            full = bpy.path.abspath(fp, library=cf.library)
            if not fp or not os.path.exists(full):
                continue
            why = alembic_file_problem(full)
            if why is not None:
                raise CliError(f"{p.name} plays the Alembic file '{full}' (Cache File '{cf.name}'), but {why}, and "
                               "Blender would abort reading it. Re-export or re-copy the Alembic file, then run "
                               "again.", EXIT_INPUT)
