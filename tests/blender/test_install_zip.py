"""The zip users download works: build this platform's extension zip, install it into a fresh
Blender user folder with ``bpy.ops.extensions.package_install_files``, enable it and run Refine
Lips from the *installed* copy on the sample mouth of the installed ``assets/meshes/lips.obj``, with
SciPy/libigl/cholespy coming from the zip's wheels, then Load Sample on the installed sample shot.

The install runs in a subprocess (a fresh user folder is read when bpy starts; a fresh
``sys.modules``). That process hides the venv's scipy, igl and cholespy, like Blender's own Python
which has numpy but none of them, so the add-on can only work if Blender installed the bundled
wheels (into ``<user>/extensions/.local/lib/pythonX.Y/site-packages``, the site folder Blender adds to
``sys.path``). The repository checkout is not importable there either: every FaceLab module must
come from the extension folder.

There is one zip per platform and Blender Python (``# python:`` lines of requirements/bpy-*.txt), each
with that Python's wheels only; the test builds the one for the Python at hand (scripts/test.sh runs it
on the oldest and the newest supported Blender).
"""

import importlib.util
import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

pytestmark = [pytest.mark.blender, pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[2]


def this_platform():
    import platform

    machine = {"x86_64": "x64", "amd64": "x64", "aarch64": "arm64", "arm64": "arm64"}[platform.machine().lower()]
    system = {"linux": "linux", "windows": "windows", "darwin": "macos"}[platform.system().lower()]
    return f"{system}-{machine}"


@pytest.fixture(scope="session")
def extension_zip(tmp_path_factory):
    """This platform's zip for this Python's Blenders, built by scripts/build_extension.py (wheels cached in
    build/wheels/)."""
    out = tmp_path_factory.mktemp("dist")
    here = "%d.%d" % sys.version_info[:2]
    r = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "build_extension.py"), "--platform", this_platform(),
         "--python", here, "--stage-dir", str(out / "stage"), "--out", str(out)],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, timeout=600,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    summary = json.loads(r.stdout)
    (z,) = summary["zips"]
    assert z["platform"] == this_platform()
    pythons = summary["pythons"]
    assert pythons == [here] and z["pythons"] == [here]
    # one wheel of each package, for this Python only (the other Python's Blenders get their own zip)
    assert sorted(w.split("-")[0] for w in z["wheels"]) == ["cholespy", "libigl", "scipy"]
    build = build_script()
    assert build.check_complete(z["wheels"], build.pinned_versions(), [here]) == []
    other = [py for py in build.supported_pythons() if py != here]
    assert other and all(build.check_complete(z["wheels"], build.pinned_versions(), [py]) for py in other)
    # the name and the manifest say which Blenders it is for; Blender refuses it on the others
    lo, hi, label = build.BLENDERS[here]
    assert Path(z["zip"]).name == f"facelab-{summary['version']}-blender{label}-{this_platform().replace('-', '_')}.zip"
    import tomllib
    import zipfile

    with zipfile.ZipFile(z["zip"]) as f:
        manifest = tomllib.loads(f.read("blender_manifest.toml").decode())
    assert (manifest["blender_version_min"], manifest["blender_version_max"]) == (lo, hi)
    assert "website" not in manifest
    return Path(z["zip"])


def build_script():
    spec = importlib.util.spec_from_file_location("build_extension", ROOT / "scripts" / "build_extension.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_wheel_tags_select_the_python():
    serves = build_script().wheel_serves
    linux = "manylinux_2_27_x86_64.manylinux_2_28_x86_64.whl"
    cp311, cp313 = f"scipy-1.17.1-cp311-cp311-{linux}", f"scipy-1.17.1-cp313-cp313-{linux}"
    assert serves(cp311, "3.11") and not serves(cp311, "3.13")
    assert serves(cp313, "3.13") and not serves(cp313, "3.11")
    abi3 = f"libigl-2.6.3-cp312-abi3-{linux}"
    assert serves(abi3, "3.12") and serves(abi3, "3.13") and not serves(abi3, "3.11")
    assert serves("pkg-1.0-py3-none-any.whl", "3.13")
    pins = {"scipy": "1.17.1", "libigl": "2.6.3", "cholespy": "2.2.0"}
    assert build_script().check_complete([cp311, cp313, abi3], pins, ["3.11", "3.13"]) == [
        "no libigl wheel for Python 3.11", "no cholespy wheel for Python 3.11", "no cholespy wheel for Python 3.13"]


INSTALL_SCRIPT = textwrap.dedent(r'''
    import importlib.abc, importlib.machinery, importlib.util, json, os, sys, sysconfig
    # Blender's own Python has numpy but no scipy/libigl/cholespy: hide the venv's copies, so they can
    # only be found where Blender installs an extension's wheels.
    VENV = os.path.realpath(sysconfig.get_paths()["purelib"])
    HIDDEN = {"scipy", "igl", "cholespy"}

    class HideVenv(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            if name.split(".")[0] not in HIDDEN or "." in name:
                return None
            paths = [p for p in sys.path if os.path.realpath(p or ".") != VENV]
            spec = importlib.machinery.PathFinder.find_spec(name, paths)
            if spec is None:
                raise ModuleNotFoundError(f"No module named {name!r} (hidden: not in Blender's Python)", name=name)
            return spec

    sys.meta_path.insert(0, HideVenv())
    out = {"checkout_importable": importlib.util.find_spec("facelab_addon") is not None}
    try:
        import scipy  # noqa: F401
        out["scipy_before_install"] = scipy.__file__
    except ImportError:
        out["scipy_before_install"] = None

    import bpy
    import numpy as np

    out["files"] = {}
    out["install"] = sorted(bpy.ops.extensions.package_install_files(
        filepath=sys.argv[1], repo="user_default", enable_on_install=True))
    out["addons"] = [a.module for a in bpy.context.preferences.addons if "facelab" in a.module]
    ext_dir = bpy.utils.user_resource("EXTENSIONS")
    out["ext_dir"] = ext_dir

    import importlib
    pkg = importlib.import_module("bl_ext.user_default.facelab")
    fl = importlib.import_module("bl_ext.user_default.facelab.facelab_addon")
    Camera = importlib.import_module(fl.__name__ + ".core.capture.camera").Camera
    assets = importlib.import_module(fl.__name__ + ".assets")
    strokes = importlib.import_module(fl.__name__ + ".blender.strokes")
    bcam = importlib.import_module(fl.__name__ + ".blender.camera")

    bpy.ops.wm.read_homefile(use_empty=True)  # keeps the preferences (the enabled add-on)
    scene = bpy.context.scene
    scene.frame_set(1)

    # The sample mouth shipped in the extension's assets (two half tubes, inner lips 0.4 apart), imported
    # as a user would, keeping the file's axes (y up, lips facing +z); the sketch says they meet at y = +-0.1.
    lips_obj = assets.asset_path("meshes", "lips.obj")
    out["files"]["lips_obj"] = str(lips_obj)
    out["import_lips"] = sorted(bpy.ops.wm.obj_import(filepath=str(lips_obj), forward_axis="Y", up_axis="Z",
                                                      import_vertex_groups=True))
    (obj,) = bpy.context.scene.objects
    obj.name = "Face"
    # float64 coordinates as written in the file (Blender keeps float32)
    V = np.array([ln.split()[1:4] for ln in lips_obj.read_text().splitlines() if ln.startswith("v ")], float)
    out["imported_max_error"] = float(np.abs(np.array([v.co[:] for v in obj.data.vertices]) - V).max())
    g = obj.vertex_groups["upper_lip"].index
    upper = np.array([any(e.group == g for e in v.groups) for v in obj.data.vertices])
    obj.vertex_groups.new(name="FL_fixed").add(np.flatnonzero(np.abs(V[:, 0]) > 1.9).tolist(), 1.0, "REPLACE")
    cam_obj = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    scene.collection.objects.link(cam_obj)
    bcam.apply_camera_to_blender(Camera.look_at([0, 0, 20], [0, 0, 0], [0, 1, 0], 50, 36, 1920, 1080), cam_obj, scene)
    scene.camera = cam_obj
    bpy.context.view_layer.objects.active = obj
    obj.select_set(True)

    out["new_lip_sketch"] = sorted(bpy.ops.facelab.new_lip_sketch())
    cam = bcam.camera_from_blender(scene)
    line = lambda y: cam.project(np.stack([np.linspace(-1.5, 1.5, 30), np.full(30, y), np.zeros(30)], 1))
    strokes.write_stroke_pixels(scene.facelab.sketch, "Upper lip", 1, [line(0.1)], cam)
    strokes.write_stroke_pixels(scene.facelab.sketch, "Lower lip", 1, [line(-0.1)], cam)
    out["refine_lips"] = sorted(bpy.ops.facelab.refine_lips())

    dg = bpy.context.evaluated_depsgraph_get()
    X = np.array([v.co[:] for v in obj.evaluated_get(dg).data.vertices])
    front = np.abs(V[:, 0]) < 1.5
    out["upper_inner_y"] = [float(V[upper & front, 1].min()), float(X[upper & front, 1].min())]
    out["lower_inner_y"] = [float(V[~upper & front, 1].max()), float(X[~upper & front, 1].max())]
    out["keys"] = [kb.name for kb in obj.data.shape_keys.key_blocks]
    out["training"] = [t.frame for t in obj.facelab.training_frames]

    # the sample shot shipped in the installed assets: Load Sample builds it in a new scene
    out["load_sample"] = sorted(bpy.ops.facelab.load_sample())
    sample = bpy.context.scene
    face = sample.facelab.face
    out["sample"] = {"scene": sample.name, "vertices": len(face.data.vertices),
                     "keys": len(face.data.shape_keys.key_blocks), "frames": [sample.frame_start, sample.frame_end],
                     "plate": bpy.path.abspath(sample.camera.data.background_images[0].clip.filepath),
                     "plate_frames": sample.camera.data.background_images[0].clip.frame_duration}

    import cholespy, igl, scipy
    op_module = bpy.types.FACELAB_OT_refine_lips.__module__
    out["files"].update({
        "extension": pkg.__file__,
        "addon": fl.__file__,
        "operator": sys.modules[op_module].__file__,
        "core": sys.modules[fl.__name__ + ".core.lips.sketch"].__file__,
        "scipy": scipy.__file__, "igl": igl.__file__, "cholespy": cholespy.__file__,
        "numpy": np.__file__,
    })
    out["checkout_modules"] = sorted(m for m in sys.modules if m.split(".")[0] == "facelab_addon")
    out["sys_path"] = list(sys.path)
    print("RESULT " + json.dumps(out))
''')


def test_installed_zip_runs_refine_lips(extension_zip, tmp_path):
    user = tmp_path / "blender-user"
    user.mkdir()
    script = tmp_path / "install_and_run.py"
    script.write_text(INSTALL_SCRIPT)
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "FACELAB_CACHE_DIR")}
    env["BLENDER_USER_RESOURCES"] = str(user)
    r = subprocess.run([sys.executable, str(script), str(extension_zip)], cwd=tmp_path, env=env,
                       stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, timeout=300)
    lines = [ln for ln in r.stdout.splitlines() if ln.startswith("RESULT ")]
    assert r.returncode == 0 and lines, r.stdout[-3000:] + r.stderr[-3000:]
    out = json.loads(lines[-1][len("RESULT "):])

    # a Python like Blender's: no checkout, no scipy until the extension brings it
    assert not out["checkout_importable"] and out["scipy_before_install"] is None
    assert out["install"] == ["FINISHED"]
    assert out["addons"] == ["bl_ext.user_default.facelab"]

    ext = Path(out["ext_dir"]).resolve()
    installed = ext / "user_default" / "facelab"
    assert (installed / "blender_manifest.toml").exists()
    for what in ("extension", "addon", "operator", "core", "lips_obj"):
        assert Path(out["files"][what]).resolve().is_relative_to(installed), (what, out["files"][what])
    # the wheels went to the site folder Blender put on sys.path under <extensions>/.local
    (wheels_site,) = [Path(p).resolve() for p in out["sys_path"] if Path(p).resolve().is_relative_to(ext / ".local")]
    assert wheels_site.name == "site-packages"
    for what in ("scipy", "igl", "cholespy"):
        assert Path(out["files"][what]).resolve().is_relative_to(wheels_site), (what, out["files"][what])
    assert not Path(out["files"]["numpy"]).resolve().is_relative_to(ext)  # numpy is Blender's
    assert out["checkout_modules"] == []

    # the sample mouth came from the installed assets, vertex for vertex
    assert out["import_lips"] == ["FINISHED"] and out["imported_max_error"] < 1e-6
    assert Path(out["files"]["lips_obj"]).resolve() == installed / "assets" / "meshes" / "lips.obj"

    # Refine Lips ran from the installed add-on and moved the inner lips onto the sketch (y = +-0.1)
    assert out["new_lip_sketch"] == ["FINISHED"] and out["refine_lips"] == ["FINISHED"]
    assert "FL_Refine_0001" in out["keys"] and out["training"] == [1]
    (u0, u1), (l0, l1) = out["upper_inner_y"], out["lower_inner_y"]
    assert u0 == pytest.approx(0.2, abs=1e-6) and l0 == pytest.approx(-0.2, abs=1e-6)
    assert abs(u1 - 0.1) < 0.03 and abs(l1 + 0.1) < 0.03, (u1, l1)

    # Load Sample ran from the installed add-on, on the installed sample
    assert out["load_sample"] == ["FINISHED"]
    smp = out["sample"]
    assert smp["scene"].startswith("FaceLab Sample") and smp["vertices"] == 4737 and smp["frames"] == [1, 48]
    assert smp["keys"] == 10 and smp["plate_frames"] == 48  # Basis, 8 expressions, the capture's lip error
    assert Path(smp["plate"]).resolve() == installed / "assets" / "sample" / "plate" / "plate_0001.jpg"
