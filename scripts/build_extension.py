"""Build FaceLab's Blender extension zips, one per platform and Blender Python, with their wheels.

    python scripts/build_extension.py                       # every platform x Blender Python -> dist/
    python scripts/build_extension.py --platform linux-x64  # just one platform (both Pythons)
    python scripts/build_extension.py --python 3.11         # just the zips for Blender 4.5 and 5.0
    python scripts/build_extension.py --update-manifest     # after bumping scipy/libigl/cholespy

Steps:

1. For every supported Python (the ``# python: X.Y`` lines of ``requirements/bpy-*.txt``, one file
   per supported Blender) and every platform: ``pip download --only-binary=:all: --no-deps
   --python-version X.Y --platform TAG`` of the versions pinned there (scipy, libigl, cholespy; every
   requirements file must pin the same ones) into ``build/wheels/<platform>/`` (a cache:
   already-downloaded wheels are reused, so a rebuild needs no network). A ``cp312-abi3`` wheel
   serves every Python from 3.12 on. numpy is NOT bundled: Blender supplies it (see docs/install.md).
2. Check that every (platform, Python) pair has one wheel of each package, and the file names
   against the ``wheels = [...]`` list of blender_manifest.toml (``--update-manifest`` rewrites that
   list instead).
3. For each Python: stage the extension in ``build/extension/``: the root ``__init__.py``, the
   manifest (restricted to the requested platforms, that Python's wheels, and the Blender versions
   running that Python: ``BLENDERS``), ``facelab_addon/``, ``assets/`` (presets, sample mesh) and
   ``wheels/``.
4. Run Blender's extension CLI (shipped in the bpy wheel, no Blender binary needed):
   ``blender_ext.py build --split-platforms``; the CLI keeps only each platform's wheels and appends
   ``[build.generated] platforms/wheels`` to the zip's manifest. The zip is renamed
   ``dist/facelab-<version>-blender<versions>-<platform>.zip`` (e.g. ``blender4.5-5.0``).
5. Check every zip: ``blender_ext.py validate``, the expected files, exactly that platform's wheels
   for that one Python (a complete set), nothing from tests/, benchmarks/, docs/, scripts/, .venv/.

Prints a JSON summary on stdout; progress, and at the end which zip is for which Blender and where it
is, go to stderr. Exit 0 on success, 1 on any failure.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import re
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MANIFEST = ROOT / "blender_manifest.toml"
REQUIREMENTS = ROOT / "requirements"  # bpy-<blender version>.txt, one per supported Blender
PACKAGES = ("scipy", "libigl", "cholespy")  # bundled; numpy comes with Blender

# Blender platform -> pip --platform tags (pip also accepts older manylinux / macOS versions).
# Linux: Blender 4.5 and newer need glibc >= 2.28. macOS arm64: SciPy 1.17's oldest arm64 wheel needs macOS 12.
PIP_PLATFORMS = {
    "linux-x64": ["manylinux_2_28_x86_64"],
    "windows-x64": ["win_amd64"],
    "macos-arm64": ["macosx_12_0_arm64"],
    "macos-x64": ["macosx_11_0_x86_64"],
}

# Blender Python -> the Blender versions running it: (blender_version_min, blender_version_max (the first
# version NOT served, as Blender's manifest wants it), the label in the zip's name and in docs/install.md).
BLENDERS = {
    "3.11": ("4.5.0", "5.1.0", "4.5-5.0"),
    "3.13": ("5.1.0", "5.4.0", "5.1-5.3"),
}

FORBIDDEN_PREFIXES = ("tests/", "benchmarks/", "docs/", "scripts/", "out/", ".venv/", ".git/", "build/", "dist/")
REQUIRED_FILES = ("blender_manifest.toml", "__init__.py", "facelab_addon/__init__.py",
                  "facelab_addon/core/geometry/deform.py", "facelab_addon/ui/panel.py", "facelab_addon/cli/__init__.py",
                  "facelab_addon/assets.py", "assets/presets/sketch_refine.json", "assets/presets/regions.json",
                  "assets/presets/sketch_material.json", "assets/meshes/lips.obj",
                  "assets/sample/face.npz", "assets/sample/plate/plate_0001.jpg", "assets/sample/LICENSE-ICT-FaceKit.txt")


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def extension_cli() -> Path:
    """Blender's extension CLI inside the installed bpy wheel (found without importing bpy)."""
    spec = importlib.util.find_spec("bpy")
    if spec is None or not spec.submodule_search_locations:
        raise SystemExit("The bpy module is not installed in this Python; run from the project's .venv "
                         "(source scripts/env.sh).")
    for base in spec.submodule_search_locations:
        hits = sorted(Path(base).glob("*/scripts/addons_core/bl_pkg/cli/blender_ext.py"))
        if hits:
            return hits[-1]
    raise SystemExit("blender_ext.py not found inside the bpy package; reinstall bpy (source scripts/env.sh).")


def requirement_files() -> list[Path]:
    files = sorted(REQUIREMENTS.glob("bpy-*.txt"))
    if not files:
        raise SystemExit(f"no requirements/bpy-*.txt in {ROOT}; one per supported Blender is expected.")
    return files


def supported_pythons() -> list[str]:
    """The Python versions ("3.11", ...) of the supported Blenders (``# python: X.Y`` in requirements/bpy-*.txt)."""
    out = set()
    for f in requirement_files():
        m = re.search(r"(?m)^#\s*python:\s*(\d+\.\d+)\s*$", f.read_text())
        if not m:
            raise SystemExit(f"{f.relative_to(ROOT)} has no '# python: X.Y' line; add the Python of that Blender.")
        out.add(m.group(1))
    return sorted(out, key=lambda v: tuple(map(int, v.split("."))))


def pinned_versions() -> dict[str, str]:
    """The versions of PACKAGES pinned in requirements/bpy-*.txt (the ones the tests run against).

    Every file must pin the same version of each package: the zip carries one.
    """
    pins: dict[str, str] = {}
    for f in requirement_files():
        mine = {}
        for line in f.read_text().splitlines():
            m = re.match(r"^\s*([A-Za-z0-9_.-]+)\s*==\s*([^\s;#]+)", line)
            if m and m.group(1).lower() in PACKAGES:
                mine[m.group(1).lower()] = m.group(2)
        missing = [p for p in PACKAGES if p not in mine]
        if missing:
            raise SystemExit(f"{f.relative_to(ROOT)} pins no version of {missing}; pin them (name==version).")
        for p, v in mine.items():
            if pins.setdefault(p, v) != v:
                raise SystemExit(f"{f.relative_to(ROOT)} pins {p}=={v} but another requirements file pins "
                                 f"{p}=={pins[p]}; the zip carries one version, pin the same everywhere.")
    return pins


def wheel_serves(filename: str, python: str) -> bool:
    """Whether a wheel file installs on CPython ``python`` ("3.13"), by its python and ABI tags."""
    py_tags, abi_tags = (t.split(".") for t in filename[:-len(".whl")].split("-")[-3:-1])
    major, minor = map(int, python.split("."))
    if f"cp{major}{minor}" in abi_tags:
        return f"cp{major}{minor}" in py_tags
    if "abi3" in abi_tags:
        return any(t.startswith(f"cp{major}") and int(t[3:] or 0) <= minor for t in py_tags)
    return "none" in abi_tags and any(t in (f"py{major}", f"cp{major}{minor}") for t in py_tags)


def manifest_text() -> str:
    return MANIFEST.read_text()


def manifest_wheels(text: str) -> list[str]:
    import tomllib

    return list(tomllib.loads(text).get("wheels", []))


def manifest_version(text: str) -> str:
    import tomllib

    return tomllib.loads(text)["version"]


def with_wheels(text: str, wheels: list[str]) -> str:
    """The manifest text with its ``wheels = [...]`` block replaced."""
    block = "wheels = [\n" + "".join(f'  "{w}",\n' for w in wheels) + "]\n"
    new, n = re.subn(r"(?ms)^wheels = \[\n.*?^\]\n", block, text)
    if n != 1:
        raise SystemExit("blender_manifest.toml: could not find exactly one 'wheels = [' ... ']' block.")
    return new


def with_platforms(text: str, platforms: list[str]) -> str:
    line = "platforms = [" + ", ".join(f'"{p}"' for p in platforms) + "]"
    new, n = re.subn(r"(?m)^platforms = \[.*\]$", line, text)
    if n != 1:
        raise SystemExit("blender_manifest.toml: could not find the 'platforms = [...]' line.")
    return new


def with_blender_range(text: str, python: str) -> str:
    """The manifest text declaring the Blender versions that run ``python`` (``BLENDERS``)."""
    lo, hi, _ = BLENDERS[python]
    new, n = re.subn(r'(?m)^blender_version_min = ".*"$', f'blender_version_min = "{lo}"\nblender_version_max = "{hi}"',
                     text)
    if n != 1 or "\nblender_version_max" in text:
        raise SystemExit("blender_manifest.toml: expected one 'blender_version_min' line and no 'blender_version_max'.")
    return new


def zip_name(version: str, python: str, platform: str) -> str:
    """``facelab-0.1.0-blender4.5-5.0-linux_x64.zip``: the Blender versions and platform it installs on."""
    return f"facelab-{version}-blender{BLENDERS[python][2]}-{platform.replace('-', '_')}.zip"


def wheels_for(files, pins: dict[str, str], python: str) -> dict[str, Path]:
    """Package -> the wheel among ``files`` serving ``python`` (its own ABI preferred over abi3)."""
    files = list(files)
    out = {}
    for pkg in PACKAGES:
        hits = [f for f in files if f.name.startswith(f"{pkg}-{pins[pkg]}-") and wheel_serves(f.name, python)]
        hits.sort(key=lambda f: ("abi3" in f.name, f.name))
        if hits:
            out[pkg] = hits[0]
    return out


def download(platform: str, pythons: list[str], pins: dict[str, str], cache: Path, offline: bool) -> list[Path]:
    """The platform's wheels for PACKAGES and every Python of ``pythons``, in ``cache/platform``
    (downloaded unless already there); fails unless every Python has one wheel of each package."""
    dest = cache / platform
    dest.mkdir(parents=True, exist_ok=True)
    chosen: dict[str, dict[str, Path]] = {}
    for py in pythons:
        found = wheels_for(dest.glob("*.whl"), pins, py)
        if len(found) < len(PACKAGES) and not offline:
            cmd = [sys.executable, "-m", "pip", "download", "--only-binary=:all:", "--no-deps", "--python-version", py,
                   "--implementation", "cp", "--abi", "cp" + py.replace(".", ""), "--dest", str(dest),
                   "--disable-pip-version-check"]
            for tag in PIP_PLATFORMS[platform]:
                cmd += ["--platform", tag]
            cmd += [f"{pkg}=={pins[pkg]}" for pkg in PACKAGES if pkg not in found]
            log(f"[{platform}] Python {py}: pip download {' '.join(cmd[-(len(PACKAGES) - len(found)):])} "
                f"({', '.join(PIP_PLATFORMS[platform])})")
            r = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
            if r.returncode != 0:
                raise SystemExit(f"[{platform}] Python {py}: pip download failed:\n{r.stdout[-3000:]}")
            found = wheels_for(dest.glob("*.whl"), pins, py)
        chosen[py] = found
    incomplete = {py: [p for p in PACKAGES if p not in found] for py, found in chosen.items() if len(found) < len(PACKAGES)}
    if incomplete:
        hint = " and --offline given; run once with network" if offline else ""
        raise SystemExit(f"[{platform}] no wheel in {dest} for " +
                         "; ".join(f"Python {py}: {', '.join(pk)}" for py, pk in incomplete.items()) + hint)
    files = sorted({f for found in chosen.values() for f in found.values()})
    log(f"[{platform}] {', '.join(f.name for f in files)}")
    return files


def check_complete(names: list[str], pins: dict[str, str], pythons: list[str]) -> list[str]:
    """Problems: the (Python, package) pairs the wheel file names ``names`` leave without a wheel."""
    files = [Path(n) for n in names]
    return [f"no {pkg} wheel for Python {py}" for py in pythons
            for pkg in PACKAGES if pkg not in wheels_for(files, pins, py)]


def stage(stage_dir: Path, text: str, wheels: dict[str, list[Path]]) -> None:
    """Copy the extension sources and wheels into ``stage_dir`` (recreated)."""
    if stage_dir.exists():
        shutil.rmtree(stage_dir)
    stage_dir.mkdir(parents=True)
    (stage_dir / "blender_manifest.toml").write_text(text)
    shutil.copy2(ROOT / "__init__.py", stage_dir / "__init__.py")
    for extra in ("README.md", "LICENSE"):
        if (ROOT / extra).exists():
            shutil.copy2(ROOT / extra, stage_dir / extra)
    for package in ("facelab_addon", "assets"):
        shutil.copytree(ROOT / package, stage_dir / package, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    wdir = stage_dir / "wheels"
    wdir.mkdir()
    for files in wheels.values():
        for f in files:
            try:
                os.link(f, wdir / f.name)
            except OSError:
                shutil.copy2(f, wdir / f.name)


def run_cli(cli: Path, *args: str) -> str:
    r = subprocess.run([sys.executable, str(cli), *args], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    if r.returncode != 0:
        raise SystemExit(f"blender_ext.py {' '.join(args)} failed:\n{r.stdout}")
    return r.stdout


def check_zip(cli: Path, path: Path, platform: str, expected_wheels: list[str], pins: dict[str, str],
              pythons: list[str]) -> dict:
    """Validate one built zip and list what it holds."""
    run_cli(cli, "validate", str(path))
    with zipfile.ZipFile(path) as z:
        names = z.namelist()
        manifest = z.read("blender_manifest.toml").decode()
    problems = [f"missing {f}" for f in REQUIRED_FILES if f not in names]
    problems += [f"should not ship {n}" for n in names if n.startswith(FORBIDDEN_PREFIXES) or "__pycache__" in n]
    got = sorted(n for n in names if n.endswith(".whl"))
    want = sorted(f"wheels/{w}" for w in expected_wheels)
    if got != want:
        problems.append(f"wheels {got} != expected {want}")
    problems += check_complete(got, pins, pythons)
    if f'platforms = ["{platform}"]' not in manifest:
        problems.append("the zip's manifest does not declare its platform")
    if problems:
        raise SystemExit(f"{path.name}: " + "; ".join(problems))
    return {"zip": str(path), "platform": platform, "bytes": path.stat().st_size, "files": len(names),
            "pythons": pythons, "wheels": [Path(w).name for w in got]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--platform", action="append", choices=sorted(PIP_PLATFORMS),
                    help="build only this platform (repeatable; default: every platform of the manifest)")
    ap.add_argument("--python", action="append", metavar="X.Y",
                    help="build only the zips for the Blenders running this Python (repeatable; default: every "
                         "supported Python: 3.11 for Blender 4.5 and 5.0, 3.13 for 5.1 to 5.3)")
    ap.add_argument("--wheels-dir", type=Path, default=ROOT / "build" / "wheels", help="wheel cache (build/wheels)")
    ap.add_argument("--stage-dir", type=Path, default=ROOT / "build" / "extension", help="staging dir")
    ap.add_argument("--out", type=Path, default=ROOT / "dist", help="where the zips go (dist/)")
    ap.add_argument("--offline", action="store_true", help="use only wheels already in the cache")
    ap.add_argument("--update-manifest", action="store_true",
                    help="rewrite the manifest's wheels list from the downloaded wheels (all platforms)")
    args = ap.parse_args(argv)

    cli = extension_cli()
    text = manifest_text()
    run_cli(cli, "validate", str(ROOT))
    import tomllib

    declared = tomllib.loads(text)["platforms"]
    platforms = args.platform or declared
    if args.update_manifest:
        platforms = declared
    unknown = [p for p in platforms if p not in declared]
    if unknown:
        raise SystemExit(f"{unknown} not in the manifest's platforms {declared}")

    pins = pinned_versions()
    pythons = supported_pythons()
    unserved = [py for py in pythons if py not in BLENDERS]
    if unserved:
        raise SystemExit(f"Python {unserved} (requirements/bpy-*.txt) has no entry in BLENDERS of "
                         "scripts/build_extension.py; add the Blender versions that run it.")
    unknown_py = [py for py in args.python or [] if py not in pythons]
    if unknown_py:
        raise SystemExit(f"--python {unknown_py}: not a supported Blender Python {pythons}")
    build_pythons = pythons if args.update_manifest else (args.python or pythons)
    wheels = {p: download(p, build_pythons, pins, args.wheels_dir, args.offline) for p in platforms}
    listed = sorted(f"./wheels/{f.name}" for files in wheels.values() for f in files)

    if args.update_manifest:
        new = with_wheels(text, listed)
        if new != text:
            MANIFEST.write_text(new)
            log(f"blender_manifest.toml: wheels list rewritten ({len(listed)} wheels)")
        text = new
        run_cli(cli, "validate", str(ROOT))
    else:
        in_manifest = manifest_wheels(text)
        missing = sorted(set(listed) - set(in_manifest))
        if missing:
            raise SystemExit(f"blender_manifest.toml does not list {missing}; run with --update-manifest "
                             "(the pinned versions in requirements/bpy-*.txt or the supported Pythons changed?).")

    version = manifest_version(text)
    results = []
    for py in build_pythons:
        own = {p: sorted(wheels_for(files, pins, py).values()) for p, files in wheels.items()}
        staged = with_blender_range(with_platforms(with_wheels(text, sorted(
            f"./wheels/{f.name}" for files in own.values() for f in files)), platforms), py)
        stage(args.stage_dir, staged, own)
        out = args.out / f".build-python{py}"
        if out.exists():
            shutil.rmtree(out)
        out.mkdir(parents=True)
        log(f"building {', '.join(platforms)} for Python {py} (Blender {BLENDERS[py][2]}) -> {args.out}")
        run_cli(cli, "build", "--split-platforms", "--source-dir", str(args.stage_dir), "--output-dir", str(out))
        for p in platforms:
            built = out / f"facelab-{version}-{p.replace('-', '_')}.zip"
            if not built.exists():
                raise SystemExit(f"the CLI did not produce {built}")
            z = args.out / zip_name(version, py, p)
            built.replace(z)
            results.append(check_zip(cli, z, p, [f.name for f in own[p]], pins, [py]))
            results[-1]["blender"] = BLENDERS[py][2]
            log(f"ok {z.name}: {results[-1]['bytes'] / 1e6:.1f} MB, {results[-1]['files']} files, "
                f"wheels {', '.join(results[-1]['wheels'])}")
        shutil.rmtree(out)
    log("\nThe zips (install one with Edit > Preferences > Get Extensions > Install from Disk):")
    for r in results:
        log(f"  Blender {r['blender']:8s} {r['platform']:12s} {r['zip']}")
    print(json.dumps({"version": version, "pythons": build_pythons, "zips": results}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
