"""Plumbing shared by the subcommands: common options, inputs, the face object, outputs, exit codes.

Nothing here does FaceLab work: the subcommands call the pipelines (``facelab_addon.pipeline``), the
code the sidebar buttons run, or the registered operators (``bpy.ops.facelab.*``, through
``Session.call``), and build the JSON summary from what they return.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import sys
import time
import traceback
from pathlib import Path

from ._errors import (
    EXIT_BPY,
    EXIT_FAILED,
    EXIT_INPUT,
    EXIT_INTERNAL,
    EXIT_OBJECT,
    EXIT_OK,
    EXIT_OUTPUT,
    EXIT_USAGE,
    CliError,
)
from ._frames import MAX_FRAME
from ._stdout import quiet_stdout
from ._paths import (
    check_blend_caches,
    check_distinct_outputs,
    check_outputs,
    check_outputs_not_played,
    expand_paths,
)

MESH_EXTS = (".obj", ".abc")
CACHE_EXTS = (".pc2", ".mdd")


_T0 = time.perf_counter()

#: Where FaceLab's own lines go while a command runs (the terminal's stderr, saved by
#: :func:`blender_output`); None: ``sys.stderr``.
_LOG = {"stream": None}


def log(msg: str) -> None:
    """Progress line on stderr, with the seconds since start (stdout carries only the JSON summary)."""
    print(f"[facelab {time.perf_counter() - _T0:6.1f}s] {msg}", file=_LOG["stream"] or sys.stderr, flush=True)


#: Lines of Blender's own output that are noise for a batch user (shown with ``--verbose`` only).
NOISE = re.compile(r"EGL|GPU|DeprecationWarning|deprecated|Read blend|Saved as|Info: |^\d\d:\d\d\.\d+ ")


@contextlib.contextmanager
def blender_output(verbose: bool):
    """While bpy runs, Blender's own output (C-level stdout and stderr: file loading, operator reports,
    EGL and deprecation warnings) goes to a temporary file instead of the terminal; FaceLab's own
    lines (:func:`log`) still reach the terminal's stderr, once and in one format. Yields the list the
    captured lines are put in on exit. ``verbose``: Blender's output goes to stderr as it comes."""
    captured: list = []
    if verbose:
        with quiet_stdout():
            yield captured
        return
    import tempfile

    try:
        out_fd, err_fd = sys.stdout.fileno(), sys.stderr.fileno()
    except (AttributeError, OSError, ValueError):  # no real file descriptors (some embeddings)
        yield captured
        return
    sys.stdout.flush()
    sys.stderr.flush()
    saved_out, saved_err = os.dup(out_fd), os.dup(err_fd)
    tmp = tempfile.TemporaryFile(mode="w+b")
    stream = os.fdopen(os.dup(saved_err), "w", buffering=1)
    _LOG["stream"] = stream
    try:
        os.dup2(tmp.fileno(), out_fd)
        os.dup2(tmp.fileno(), err_fd)
        yield captured
    finally:
        sys.stdout.flush()
        sys.stderr.flush()
        os.dup2(saved_out, out_fd)
        os.dup2(saved_err, err_fd)
        os.close(saved_out)
        os.close(saved_err)
        _LOG["stream"] = None
        stream.close()
        tmp.seek(0)
        captured.extend(tmp.read().decode("utf-8", "replace").splitlines())
        tmp.close()


def add_common_arguments(p, inputs=("blend", "mesh")) -> None:
    g = p.add_argument_group("input (a .blend, or a mesh with an optional cache)")
    g.add_argument("blend", nargs="?", metavar="SHOT.blend",
                   help="the .blend to work on (inside Blender: omit it to use the open file)")
    if "mesh" in inputs:
        g.add_argument("--mesh", metavar="FILE",
                       help="build a scene from a mesh instead: .obj (coordinates kept as in the file, Z up) "
                            "or .abc (Alembic, imported with its animation)")
        g.add_argument("--cache", metavar="FILE",
                       help="captured performance for --mesh: .pc2 or .mdd, played by a Mesh Cache modifier")
        g.add_argument("--rest", metavar="FILE.obj",
                       help="for an Alembic --mesh: the neutral face (same vertex order) as the rest pose; "
                            "otherwise the file's first frame is the rest pose")
    p.add_argument("--from-open-scene", action="store_true", help=argparse_suppress())
    p.add_argument("--object", metavar="NAME",
                   help="the face mesh (default: FaceLab > Setup > Face of the scene, else the only mesh)")
    p.add_argument("--frames", metavar="RANGE",
                   help="frames to work on: 'A-B', 'N' or a list such as '40,88' or '1-10,20' (propagate, "
                        "reconstruct, solve and retarget take one range 'A-B'); default: the scene's frame range")
    p.add_argument("--out", metavar="FILE.blend",
                   help="save the result here (default: nothing is saved, only the summary is printed)")
    p.add_argument("--json", metavar="FILE", dest="json_path",
                   help="write the JSON summary to FILE instead of stdout")
    p.add_argument("--quiet", action="store_true",
                   help="print nothing but the JSON summary (no progress, none of Blender's own lines)")
    p.add_argument("--verbose", action="store_true",
                   help="also show Blender's own output (file loading, operator reports, warnings) on stderr")


def argparse_suppress():
    import argparse

    return argparse.SUPPRESS


def exit_code_for(e: BaseException) -> int:
    """The documented exit code of a FaceLab error: 3 for an unreadable input file (cache, OBJ),
    5 for an output that cannot be written, 1 for data FaceLab refuses; 70 for anything else (a bug)."""
    from ..core.errors import CacheFileError, FaceLabError, ObjFileError, OutputError

    if isinstance(e, CliError):
        return e.code
    if isinstance(e, OutputError):
        return EXIT_OUTPUT
    if isinstance(e, (CacheFileError, ObjFileError)):
        return EXIT_INPUT
    if isinstance(e, FaceLabError):
        return EXIT_FAILED
    return EXIT_INTERNAL


def one_line(text) -> str:
    """A message on one line (stderr's error line and the JSON ``error``)."""
    return " ".join(str(text).split())


class Session:
    """The open scene and the face object the subcommand works on, plus helpers."""

    def __init__(self, args):
        self.args = args
        self.quiet = getattr(args, "quiet", False)
        self.t0 = time.perf_counter()
        self.inputs: dict = {}
        self.notes: list = []
        import bpy

        self.bpy = bpy

    # -- messages ---------------------------------------------------------------------------------
    def log(self, msg: str) -> None:
        if not self.quiet:
            log(msg)

    def note(self, msg: str) -> None:
        """Something the user must know about the run: logged now, and in the summary's ``notes`` (on failure too)."""
        self.notes.append(msg)
        self.log(f"note: {msg}")

    def progress(self, label: str, total: int):
        """A callable ``(i, n=total)`` printing ``label i/n (p %)`` on stderr about every 10 %."""
        state = {"last": -1}

        def update(i, n=total):
            if self.quiet or not n:
                return
            pct = int(100 * (i + 1) / n)
            if pct // 10 != state["last"] // 10 or i + 1 == n:
                state["last"] = pct
                log(f"{label}: {i + 1}/{n} ({pct} %)")

        return update

    @property
    def scene(self):
        return self.bpy.context.scene

    # -- inputs -----------------------------------------------------------------------------------
    def open_inputs(self) -> None:
        a = self.args
        mesh, cache = getattr(a, "mesh", None), getattr(a, "cache", None)
        if a.blend and mesh:
            raise CliError("Give either SHOT.blend or --mesh, not both.", EXIT_USAGE)
        if cache and not mesh:
            raise CliError("--cache needs --mesh (the mesh the cache animates).", EXIT_USAGE)
        if a.blend:
            self.open_blend(a.blend)
        elif mesh:
            self.build_scene(mesh, cache)
        elif getattr(self.bpy.app, "module", False) and not self.bpy.data.filepath and not a.from_open_scene:
            # plain Python: the bpy module starts on Blender's default scene, never what was meant
            raise CliError("No input: give SHOT.blend, or --mesh FILE (with --cache FILE); inside Blender "
                           "('blender -b SHOT.blend --python-expr ...') the open file is used.", EXIT_USAGE)
        else:
            self.inputs["blend"] = self.bpy.data.filepath or None  # inside Blender: the open file

    def open_blend(self, path) -> None:
        p = Path(path)
        if p.is_dir():
            blends = sorted(q.name for q in p.glob("*.blend"))[:5]
            raise CliError(f"{path} is a folder, not a .blend file; give the .blend itself"
                           + (f" (the folder holds {', '.join(blends)})." if blends else "."), EXIT_INPUT)
        if not p.is_file():
            raise CliError(f"{path}: no such .blend file; check the path.", EXIT_INPUT)
        check_blend_caches(self.bpy, p)
        self.log(f"opening {p}")
        try:
            with quiet_stdout():
                self.bpy.ops.wm.open_mainfile(filepath=str(p.resolve()), load_ui=False)
        except RuntimeError as e:
            this = self.bpy.app.version_string
            with open(p, "rb") as f:
                head = f.read(7)
            said = str(e).lower()
            if "newer" in said or (head == b"BLENDER" and "not supported" in said):  # a header it cannot parse
                raise CliError(f"{path}: this Blender ({this}) cannot read it ({clean_report(e)}): a newer Blender "
                               "saved it. Run FaceLab in the Blender that saved it (or open it there and save it "
                               "in an older format).", EXIT_INPUT) from None
            raise CliError(f"{path}: Blender {this} cannot read it ({first_line(e)}); check that it is a whole "
                           ".blend file (re-copy it, or open it in Blender and save it again).", EXIT_INPUT) from None
        self.inputs["blend"] = str(p.resolve())
        saved = tuple(self.bpy.data.version)[:2]
        if saved > tuple(self.bpy.app.version)[:2]:
            self.note(f"{p.name} was saved by Blender {saved[0]}.{saved[1]}, newer than this Blender "
                      f"{self.bpy.app.version_string}: what this one does not know is dropped from the saved result; "
                      "run FaceLab in that Blender to keep everything.")

    def build_scene(self, mesh_path, cache_path) -> None:
        import numpy as np

        bpy = self.bpy
        mp = Path(mesh_path)
        if not mp.is_file():
            raise CliError(f"--mesh {mesh_path}: no such file; check the path.", EXIT_INPUT)
        if mp.suffix.lower() not in MESH_EXTS:
            raise CliError(f"--mesh {mesh_path}: unsupported type; give an .obj or an Alembic .abc.", EXIT_INPUT)
        cp = Path(cache_path) if cache_path else None
        if cp is not None:
            if not cp.is_file():
                raise CliError(f"--cache {cache_path}: no such file; check the path.", EXIT_INPUT)
            if cp.suffix.lower() not in CACHE_EXTS:
                raise CliError(f"--cache {cache_path}: unsupported type; give a .pc2 or .mdd point cache.", EXIT_INPUT)
        with quiet_stdout():
            bpy.ops.wm.read_homefile(use_empty=True)
        scene = bpy.context.scene
        self.log(f"building a scene from {mp.name}" + (f" + {cp.name}" if cp else ""))
        if mp.suffix.lower() == ".obj":
            obj = self.import_obj(mp, "Face")
        else:
            from ..blender.caches import alembic_file_problem

            why = alembic_file_problem(mp.resolve())  # Blender's importer aborts the process on a truncated file
            if why is not None:
                raise CliError(f"--mesh {mesh_path}: Blender cannot read this Alembic file: {why}. Re-export or "
                               "re-copy it.", EXIT_INPUT)
            before = set(bpy.data.objects)
            try:
                with quiet_stdout():
                    bpy.ops.wm.alembic_import(filepath=str(mp.resolve()), set_frame_range=True)
            except RuntimeError as e:
                raise CliError(f"--mesh {mesh_path}: the Alembic importer failed ({first_line(e)}).", EXIT_INPUT) \
                    from None
            meshes = [o for o in bpy.data.objects if o not in before and o.type == "MESH"]
            if not meshes:
                raise CliError(f"--mesh {mesh_path}: the Alembic file has no mesh.", EXIT_INPUT)
            obj = max(meshes, key=lambda o: len(o.data.vertices))
        if cp is not None:
            self.add_cache(obj, cp)
        rest = getattr(self.args, "rest", None)
        if rest:
            V = self.import_obj_vertices(rest)
            if len(V) != len(obj.data.vertices):
                raise CliError(f"--rest {rest}: {len(V)} vertices, the mesh has {len(obj.data.vertices)}; give the "
                               "neutral of the same topology.", EXIT_INPUT)
            obj.data.vertices.foreach_set("co", V.astype(np.float32).ravel())
            obj.data.update()
            self.inputs["rest"] = str(Path(rest).resolve())
        bpy.context.view_layer.objects.active = obj
        obj.select_set(True)
        self.inputs.update(mesh=str(mp.resolve()), cache=str(cp.resolve()) if cp else None)

    def import_obj(self, path: Path, name: str):
        """A mesh object from an OBJ, vertex order and coordinates exactly as in the file."""
        from ..blender.scene import new_mesh_object
        from ..core.capture.obj import read_obj
        from ..core.errors import FaceLabError

        try:
            V, _, cv, _, off, _, _ = read_obj(path)
        except OSError as e:
            raise CliError(f"{path}: cannot read it ({e.strerror or e}); check the path and its permissions.",
                           EXIT_INPUT) from None
        except ValueError as e:  # ObjFileError: names the line and the fix
            raise CliError(str(e), EXIT_INPUT) from None
        if not len(V) or len(off) < 2:
            raise CliError(f"{path}: the OBJ has no vertices or no faces; give the face mesh exported as a "
                           "Wavefront OBJ.", EXIT_INPUT)
        try:
            return new_mesh_object(name, V, poly_verts=cv, poly_offsets=off)
        except FaceLabError as e:
            raise CliError(f"{path}: {e}", EXIT_INPUT) from None

    def import_obj_vertices(self, path: Path):
        """(V,3) float64 vertex positions of an OBJ, in file order."""
        from ..core.capture.obj import read_obj_vertices

        try:
            V = read_obj_vertices(Path(path))
        except OSError as e:
            raise CliError(f"{path}: cannot read it ({e.strerror or e}); check the path and its permissions.",
                           EXIT_INPUT) from None
        except ValueError as e:  # ObjFileError: names the line and the fix
            raise CliError(str(e), EXIT_INPUT) from None
        if not len(V):
            raise CliError(f"{path}: the OBJ has no vertices.", EXIT_INPUT)
        return V

    def add_cache(self, obj, path: Path) -> None:
        from ..core.capture import pointcache
        from ..core.errors import FaceLabError

        try:
            info = pointcache.cache_info(str(path))
            pointcache.check_vertex_count(info, len(obj.data.vertices), name=f"'{obj.name}'")
        except FaceLabError as e:
            raise CliError(f"--cache {path}: {e}", EXIT_INPUT) from None
        if info.start_frame is not None and round(info.start_frame) < 0:
            raise CliError(f"--cache {path}: its first sample is on frame {info.start_frame:g}, before frame 0, where "
                           "Blender's scene range starts; re-export the cache starting on frame 0 or later.",
                           EXIT_INPUT)
        last = round(info.start_frame or 1) + round((info.num_samples - 1) * (info.sample_rate or 1.0))
        if last > MAX_FRAME:
            raise CliError(f"--cache {path}: its samples run to frame {last:,}, past Blender's last frame "
                           f"{MAX_FRAME:,}; check the header's start frame and sample rate, or re-export it.",
                           EXIT_INPUT)
        md = obj.modifiers.new("Capture", "MESH_CACHE")
        md.cache_format = info.format
        md.filepath = str(path.resolve())
        md.play_mode, md.time_mode = "SCENE", "FRAME"
        start = int(round(info.start_frame)) if info.start_frame is not None else 1
        md.frame_start = float(start)
        step = info.sample_rate or 1.0
        scene = self.scene
        scene.frame_start, scene.frame_end = start, start + int(round((info.num_samples - 1) * step))
        self.log(f"cache {path.name}: {info.num_samples} samples of {info.num_points} points, frames "
                 f"{scene.frame_start}-{scene.frame_end}")

    # -- the face ---------------------------------------------------------------------------------
    def face(self):
        """The face object (``--object``, else Setup > Face, else the only mesh), made active and selected."""
        bpy, scene, name = self.bpy, self.scene, self.args.object
        meshes = [o.name for o in scene.objects if o.type == "MESH"]
        if name:
            obj = bpy.data.objects.get(name)
            if obj is None:
                raise CliError(f"--object {name!r}: no such object; meshes in the scene: {meshes[:20]}.", EXIT_OBJECT)
            if obj.type != "MESH":
                raise CliError(f"--object {name!r} is a {obj.type.lower()}, not a mesh; give the face mesh "
                               f"({meshes[:20]}).", EXIT_OBJECT)
        elif scene.facelab.face is not None:
            obj = scene.facelab.face
        elif len(meshes) == 1:
            obj = scene.objects[meshes[0]]
        else:
            raise CliError(f"Which mesh is the face? Give --object NAME (meshes: {meshes[:20]}).", EXIT_OBJECT)
        if scene.objects.get(obj.name) is None:
            raise CliError(f"'{obj.name}' is not in the scene '{scene.name}'; link it or give another --object.",
                           EXIT_OBJECT)
        scene.facelab.face = obj
        from ..blender.correction_files import correction_cache_problems

        for problem in correction_cache_problems(obj):  # a bake refuses; every other command says it
            self.note(problem)
        vl = bpy.context.view_layer
        if vl.objects.get(obj.name) is not None:
            vl.objects.active = obj
            obj.select_set(True)
        return obj

    # -- running operators ------------------------------------------------------------------------
    def call(self, op, **kw):
        """Run ``bpy.ops.facelab.<op>`` (stdout kept clean); its error report becomes a CliError."""
        fn = getattr(self.bpy.ops.facelab, op)
        try:
            with quiet_stdout():
                return fn(**kw)
        except RuntimeError as e:
            raise CliError(*operator_failure(e)) from None

    # -- outputs ----------------------------------------------------------------------------------
    def check_out(self, only=None) -> None:
        """Refuse a bad ``--out``, ``--json`` or ``--bake`` before any work (``_paths.check_outputs``)."""
        check_outputs(self.args, self.bpy.data.filepath, only)

    def save(self, out) -> str | None:
        if not out:
            return None
        self.check_out("--out")
        p = Path(out).resolve()
        self.log(f"saving {p}")
        try:
            with quiet_stdout():
                self.bpy.ops.wm.save_as_mainfile(filepath=str(p), copy=False, check_existing=False)
        except RuntimeError as e:
            raise CliError(f"--out {out}: cannot write it ({first_line(e)}).", EXIT_OUTPUT) from None
        return str(p)


def first_line(e) -> str:
    return str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__


def operator_failure(e: RuntimeError) -> tuple[str, int]:
    """``(message, exit code)`` of a failed ``bpy.ops`` call.

    An operator's error report is FaceLab refusing the data (1). A Python
    exception that escaped the operator arrives as its traceback: a FaceLab
    error keeps its documented code (``exit_code_for``: 3 input, 5 output,
    1 data), anything else is a bug (70), whose traceback goes to stderr.
    """
    from ..core import errors

    text = str(e)
    if "Traceback (most recent call last)" not in text:
        return clean_report(e), EXIT_FAILED
    lines = [ln.strip() for ln in text.strip().splitlines() if ln.strip()]
    last = next((ln for ln in reversed(lines) if re.match(r"^[\w.]+(Error|Exception|Interrupt|Exit)\b", ln)),
                lines[-1])
    name, _, msg = last.partition(":")
    cls = getattr(errors, name.rsplit(".", 1)[-1], None)
    if isinstance(cls, type) and issubclass(cls, errors.FaceLabError):
        return one_line(msg), exit_code_for(cls(msg))
    print(text, file=sys.stderr, flush=True)
    return f"internal error in an operator: {one_line(last)} (a bug: the traceback is above)", EXIT_INTERNAL


def clean_report(e) -> str:
    """An operator's RuntimeError text without Blender's 'Error: ' prefixes and poll boilerplate."""
    lines = [ln.strip() for ln in str(e).strip().splitlines() if ln.strip()]
    lines = [re.sub(r"^(Error|Warning|Info):\s*", "", ln) for ln in lines]
    return " ".join(lines)


def ensure_registered(bpy) -> str:
    """Register FaceLab's operators unless Blender already has them (an enabled extension)."""
    if hasattr(bpy.types, "FACELAB_OT_propagate"):
        return "already registered (enabled add-on)"
    from .. import register

    register()
    return f"registered from {Path(__file__).resolve().parents[1]}"


def execute(args) -> int:
    """Run the parsed subcommand: returns the exit code; prints/writes the JSON summary.

    While it runs, Blender's own output (file loading, operator reports, EGL and deprecation
    warnings) is kept off the terminal (:func:`blender_output`; ``--verbose`` shows it on stderr), so
    stdout carries only the JSON and stderr only FaceLab's lines, each once (``--quiet``: none).
    A failure ends in one ``error: ...`` line on stderr and its documented exit code
    (``exit_code_for``); a bug adds its traceback.
    """
    t0 = time.perf_counter()
    summary = {"command": args.command, "ok": False}
    code = EXIT_INTERNAL
    registered_here = False
    quiet = getattr(args, "quiet", False)
    expand_paths(args)
    try:
        check_distinct_outputs(args)
        clash = None
    except CliError as e:  # the JSON then goes to stdout: --json may be the input or the --out .blend
        clash = e
    notes: list = []  # the session's notes, kept on failure too
    with blender_output(getattr(args, "verbose", False)) as blender_lines:
        try:
            if clash is not None:
                raise clash
            try:
                import bpy
            except ImportError as e:
                raise CliError(f"Cannot import bpy ({e}); run with the project's Python (a venv from "
                               "scripts/env.sh, with bpy) or inside Blender.", EXIT_BPY) from None
            try:
                reg = ensure_registered(bpy)
                registered_here = not reg.startswith("already")
            except ImportError as e:  # Blender's Python without the extension's wheels
                raise CliError(f"FaceLab cannot load: {e}. Install the FaceLab extension zip in this Blender (it "
                               "brings SciPy, libigl and cholespy), or use the project's Python (.venv).",
                               EXIT_BPY) from None
            session = Session(args)
            session.notes = notes
            session.log(f"{args.command}: FaceLab {reg}")
            session.check_out()
            session.open_inputs()
            check_outputs_not_played(args, bpy)
            settings = apply_settings(args, session.scene)
            result = args._module.run(args, session)
            summary.update(result)
            if settings:
                summary["settings"] = settings
            summary.update(ok=True, inputs=session.inputs)
            code = EXIT_OK
        except Exception as e:  # noqa: BLE001  (a bug: report it, never a silent success)
            code = exit_code_for(e)
            if getattr(e, "json_to_stdout", False):
                clash = e
            if code == EXIT_INTERNAL:
                summary.update(error=one_line(f"internal error: {type(e).__name__}: {e}"))
                traceback.print_exc(file=_LOG["stream"] or sys.stderr)
                log("internal error: please report it with the traceback above")
            else:
                summary.update(error=one_line(e))
                if not quiet:
                    log(f"error: {one_line(e)}")
        except KeyboardInterrupt:
            code = EXIT_INTERNAL
            summary.update(error="interrupted (Ctrl+C); nothing was saved")
            log("error: interrupted; nothing was saved")
        if notes:
            summary["notes"] = notes + list(summary.get("notes") or [])
        _release_solvers()
        if registered_here:  # a process exiting with FaceLab registered hangs in bpy 4.5's exit
            from .. import unregister

            unregister()
    if code in (EXIT_INPUT, EXIT_INTERNAL) and not quiet:  # what Blender said may be the reason
        for line in [ln for ln in blender_lines if ln.strip() and not NOISE.search(ln)][-10:]:
            log(f"blender: {line.strip()}")
    summary.update(exit_code=code, seconds=round(time.perf_counter() - t0, 3))
    text = json.dumps(summary, indent=2, default=_json_default)
    if getattr(args, "json_path", None) and clash is None:
        try:
            Path(args.json_path).write_text(text + "\n")
        except OSError as e:
            log(f"error: --json {args.json_path}: cannot write it ({e.strerror or e})")
            return code or EXIT_OUTPUT
    else:
        print(text, flush=True)
    return code


def add_settings_arguments(p, command: str) -> None:
    """The flags of the settings stored with the shot that ``command`` uses (``pipeline.shot_settings``);
    none when FaceLab's Blender side cannot be imported (no bpy: the run then exits with code 6)."""
    try:
        from ..pipeline import shot_settings
    except ImportError:
        return
    shot_settings.add_flags(p, command)


def apply_settings(args, scene) -> dict:
    """Write the settings flags given into the scene (saved with ``--out``); ``{group: {field: value}}``
    of the settings the command uses."""
    from ..pipeline import shot_settings

    try:
        return shot_settings.apply_flags(args, scene, args.command)
    except ValueError as e:
        raise CliError(str(e), EXIT_USAGE) from None


def _release_solvers() -> None:
    """Collect unreachable objects now, so native solver factors (Cholesky) held in reference cycles are
    freed before the interpreter exits (nanobind prints a 'leaked instance' warning otherwise)."""
    import gc

    gc.collect()


def _json_default(o):
    try:
        import numpy as np

        if isinstance(o, np.generic):
            return o.item()
        if isinstance(o, np.ndarray):
            return o.tolist()
    except ImportError:
        pass
    return str(o)
