"""FaceLab's command line: the sidebar's steps, in batch, for render farms and pipeline scripts.

    python -m facelab_addon propagate SHOT.blend --object Face --frames 1-1200 --out SHOT_fixed.blend
    python -m facelab_addon refine SHOT.blend --object Face --frames 40,88 --lambda-silh 2 --out SHOT_refined.blend
    python -m facelab_addon reconstruct SHOT.blend --object Face --frames 1-300 --out SHOT_recon.blend
    python -m facelab_addon propagate --mesh face.obj --cache perf.pc2 --corrected 12:fix12.obj --out fixed.blend

Each subcommand is one module of this package (``refine.py``, ``propagate.py``, ``solve.py``, ...)
found at run time: a new one is added by dropping in a module that defines

    HELP: str                                   # one line for --help
    def add_arguments(parser) -> None            # its own options (the common ones are already there)
    def run(args, session: Session) -> dict      # call the pipelines (facelab_addon.pipeline); return the JSON summary

The common options (inputs, ``--object``, ``--frames``, ``--out``, ``--json``, ``--quiet``,
``--verbose``) and the plumbing (opening inputs, finding the object, Blender's own output kept off
the terminal, exit codes) are in ``_common.py``. The settings a command's steps store with the shot
(:data:`facelab_addon.pipeline.shot_settings.SCENE_SETTINGS`) are flags too; without a flag the value
saved in the .blend is used. Progress goes to stderr, the JSON summary to stdout (or ``--json FILE``).

Exit codes (also in docs/cli.md):

====  =====================================================================
0     success
1     FaceLab refused the data (the message says what is wrong and the fix)
2     usage: bad arguments, bad frame range
3     an input file is missing or unreadable
4     the object is missing or not a mesh
5     the output could not be written
6     bpy (Blender as a Python module) is not available
70    internal error (a bug: the traceback is on stderr)
====  =====================================================================

Works with plain Python (``bpy`` wheel) and inside Blender::

    blender -b SHOT.blend --python-expr "import sys, facelab_addon.cli as c; sys.exit(c.main(['propagate', '--object', 'Face']))"
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys

from ._common import add_common_arguments, add_settings_arguments, execute


def subcommands() -> dict:
    """``{name: module}`` of every subcommand module in this package (names not starting with ``_``)."""
    found = {}
    for info in pkgutil.iter_modules(__path__):
        if info.name.startswith("_"):
            continue
        mod = importlib.import_module(f"{__name__}.{info.name}")
        if callable(getattr(mod, "run", None)) and callable(getattr(mod, "add_arguments", None)):
            found[getattr(mod, "NAME", info.name)] = mod
    return dict(sorted(found.items()))


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m facelab_addon",
        description="FaceLab in batch: the same operators as the sidebar tab, on a .blend or on OBJ/Alembic/PC2/MDD "
        "inputs. Progress on stderr, a JSON summary on stdout. Exit codes: 0 ok, 1 FaceLab refused the data, "
        "2 usage, 3 missing/unreadable input, 4 object missing, 5 output not writable, 6 no bpy, 70 internal error.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, mod in subcommands().items():
        p = sub.add_parser(name, help=getattr(mod, "HELP", ""), description=(mod.__doc__ or "").strip(),
                           formatter_class=argparse.RawDescriptionHelpFormatter)
        add_common_arguments(p, inputs=getattr(mod, "INPUTS", ("blend", "mesh")))
        mod.add_arguments(p)
        add_settings_arguments(p, name)
        p.set_defaults(_module=mod)
    return parser


def main(argv=None) -> int:
    """Run one subcommand; returns the exit code (never calls ``sys.exit``).

    ``argv`` defaults to ``sys.argv[1:]``; inside Blender (``blender -b ... --python-expr``) pass the
    list explicitly, because Blender's own arguments are in ``sys.argv``.
    """
    parser = build_parser()
    if argv is None:
        argv = sys.argv[1:]
    try:
        args = parser.parse_args(list(argv))
    except SystemExit as e:  # argparse: --help (0) or a usage error (2)
        return int(e.code or 0)
    return execute(args)
