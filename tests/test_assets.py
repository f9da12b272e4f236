"""The shipped assets: the path rule of ``facelab_addon.assets``, the presets hold the paper's values
(and the core defaults), a broken preset is refused with its file name, the sample lip mesh is
exactly ``two_lips()``, and the add-on takes its defaults from the presets."""

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from facelab_addon import assets
from facelab_addon.assets import AssetError, asset_path, load_json, load_preset
from facelab_addon.core.errors import FaceLabError

ROOT = Path(__file__).resolve().parents[1]

SKETCH_SCHEMA = {"iterations": int, "lambda_pos": float, "lambda_reg": float, "lambda_silh": float}
REGION_SCHEMA = {"lip_width": float, "mouth_width": float}


def read_obj(path):
    """(V,3) float64, (F,3) int64 0-based, {group: (k,) face ids} of a triangle OBJ."""
    V, F, groups, group = [], [], {}, None
    for line in Path(path).read_text().splitlines():
        tok = line.split()
        if not tok or tok[0].startswith("#"):
            continue
        if tok[0] == "v":
            V.append([float(t) for t in tok[1:4]])
        elif tok[0] == "g":
            group = tok[1]
            groups[group] = []
        elif tok[0] == "f":
            assert len(tok) == 4, line
            if group is not None:
                groups[group].append(len(F))
            F.append([int(t.split("/")[0]) - 1 for t in tok[1:]])
    return np.array(V), np.array(F, dtype=np.int64), {g: np.array(ids) for g, ids in groups.items()}


# --------------------------------------------------------------------------------------------------
# asset_path
# --------------------------------------------------------------------------------------------------


def test_asset_path_from_the_checkout():
    assert assets.ASSETS_DIR == ROOT / "assets"
    assert asset_path("presets", "regions.json") == ROOT / "assets" / "presets" / "regions.json"
    assert asset_path("meshes") == ROOT / "assets" / "meshes"


def test_asset_path_refuses_missing_and_escaping_paths():
    with pytest.raises(AssetError, match=r"nothing\.json is missing; reinstall") as e:
        asset_path("presets", "nothing.json")
    assert isinstance(e.value, FaceLabError)
    with pytest.raises(AssetError, match="leaves"):
        asset_path("..", "blender_manifest.toml")
    with pytest.raises(AssetError, match="needs the file's path"):
        asset_path()


def test_assets_module_imports_without_bpy():
    code = "import sys, facelab_addon.assets as a; a.load_preset('regions', {'lip_width': float, " \
           "'mouth_width': float}); assert 'bpy' not in sys.modules, 'bpy imported'"
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr


def test_the_extension_ships_assets():
    import tomllib

    excluded = tomllib.loads((ROOT / "blender_manifest.toml").read_text())["build"]["paths_exclude_pattern"]
    assert not [p for p in excluded if "assets" in p]
    build = (ROOT / "scripts" / "build_extension.py").read_text()
    assert '"assets/meshes/lips.obj"' in build and '("facelab_addon", "assets")' in build


# --------------------------------------------------------------------------------------------------
# presets
# --------------------------------------------------------------------------------------------------


def test_sketch_preset_is_the_papers_and_the_solvers_defaults():
    p = load_preset("sketch_refine", SKETCH_SCHEMA)
    assert p == {"iterations": 5, "lambda_pos": 0.1, "lambda_reg": 3.0, "lambda_silh": 1.0}
    assert type(p["iterations"]) is int and all(type(p[k]) is float for k in ("lambda_pos", "lambda_reg", "lambda_silh"))
    from facelab_addon.core.lips.refine_params import RefineParams

    defaults = RefineParams()
    assert {k: getattr(defaults, k) for k in p} == p


def test_region_preset_is_the_core_default():
    from facelab_addon.core.lips import regions

    p = load_preset("regions", REGION_SCHEMA)
    assert p == {"lip_width": regions.DEFAULT_LIP_WIDTH, "mouth_width": regions.DEFAULT_MOUTH_WIDTH}
    assert p == {"lip_width": 0.12, "mouth_width": 0.45}


def test_sketch_material_preset():
    p = load_preset("sketch_material", {"color": tuple, "show_fill": bool})
    assert p == {"color": (1.0, 1.0, 1.0, 1.0), "show_fill": False}


@pytest.fixture
def tmp_assets(tmp_path, monkeypatch):
    (tmp_path / "presets").mkdir()
    monkeypatch.setattr(assets, "ASSETS_DIR", tmp_path.resolve())
    return tmp_path / "presets"


@pytest.mark.parametrize("text, message", [
    (None, r"sketch_refine\.json is missing"),
    ('{"iterations": 5, "lambda_pos": 0.1,', r"sketch_refine\.json is not valid JSON \(line 1"),
    ('[5, 0.1, 3, 1]', r"sketch_refine\.json must hold a JSON object"),
    ('{"iterations": 5, "lambda_pos": 0.1, "lambda_reg": 3}', r"missing \['lambda_silh'\]"),
    ('{"iterations": 5, "lambda_pos": 0.1, "lambda_reg": 3, "lambda_silh": 1, "lambda_x": 2}',
     r"unknown \['lambda_x'\]"),
    ('{"iterations": 5.5, "lambda_pos": 0.1, "lambda_reg": 3, "lambda_silh": 1}', "'iterations' must be an integer"),
    ('{"iterations": 5, "lambda_pos": "0.1", "lambda_reg": 3, "lambda_silh": 1}', "'lambda_pos' must be a finite"),
    ('{"iterations": 5, "lambda_pos": NaN, "lambda_reg": 3, "lambda_silh": 1}', "'lambda_pos' must be a finite"),
    ('{"iterations": 5, "lambda_pos": 0.1, "lambda_reg": true, "lambda_silh": 1}', "'lambda_reg' must be a finite"),
])
def test_broken_preset_is_refused_naming_the_file(tmp_assets, text, message):
    if text is not None:
        (tmp_assets / "sketch_refine.json").write_text(text)
    with pytest.raises(AssetError, match=message) as e:
        load_preset("sketch_refine", SKETCH_SCHEMA)
    assert str(tmp_assets / "sketch_refine.json") in str(e.value)
    assert "fix the file" in str(e.value) or "reinstall" in str(e.value)


def test_preset_comments_are_ignored_and_ints_become_floats(tmp_assets):
    (tmp_assets / "p.json").write_text(json.dumps({"_comment": "x", "a": 3, "b": [1, 0.5], "c": True, "d": "s"}))
    p = load_preset("p", {"a": float, "b": tuple, "c": bool, "d": str})
    assert p == {"a": 3.0, "b": (1.0, 0.5), "c": True, "d": "s"} and type(p["a"]) is float
    assert load_json("presets", "p.json")["_comment"] == "x"


# --------------------------------------------------------------------------------------------------
# the sample lip mesh
# --------------------------------------------------------------------------------------------------


def test_lips_obj_is_exactly_two_lips():
    from tests.core.lipmesh import two_lips

    V0, F0, upper = two_lips()
    V, F, groups = read_obj(asset_path("meshes", "lips.obj"))
    assert V.dtype == np.float64 and np.array_equal(V, V0)  # bit for bit
    assert np.array_equal(F, F0)
    assert sorted(groups) == ["lower_lip", "upper_lip"]
    in_upper = np.zeros(len(F), bool)
    in_upper[groups["upper_lip"]] = True
    assert len(groups["upper_lip"]) + len(groups["lower_lip"]) == len(F)
    assert np.array_equal(upper[F].all(axis=1), in_upper) and np.array_equal(~upper[F].any(axis=1), ~in_upper)
    # the documented geometry: inner lips at y = +-0.2, facing +z
    front = np.abs(V[:, 0]) < 1.5
    assert math.isclose(V[upper & front, 1].min(), 0.2, abs_tol=1e-12)
    assert math.isclose(V[~upper & front, 1].max(), -0.2, abs_tol=1e-12)
    assert V[:, 2].max() == pytest.approx(0.5)


def test_make_assets_check_passes():
    r = subprocess.run([sys.executable, str(ROOT / "scripts" / "make_assets.py"), "--check"], cwd=ROOT,
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr


# --------------------------------------------------------------------------------------------------
# the add-on uses them (Blender)
# --------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def addon():
    pytest.importorskip("bpy")
    import facelab_addon

    facelab_addon.register()
    yield
    facelab_addon.unregister()


@pytest.mark.blender
def test_preferences_and_sketch_material_come_from_the_presets(addon):
    import bpy

    from facelab_addon.blender import compat, strokes
    from facelab_addon.pipeline.regions import REGION_DEFAULTS
    from facelab_addon.ui import prefs

    assert prefs.DEFAULTS == load_preset("sketch_refine", SKETCH_SCHEMA)
    assert REGION_DEFAULTS == load_preset("regions", REGION_SCHEMA)
    # the preferences hold the defaults of new scenes, through the scene settings generated from the presets
    rna = bpy.types.PropertyGroup.bl_rna_get_subclass_py("FACELAB_PG_facelab_refine").bl_rna.properties
    assert {k: pytest.approx(rna[k].default) for k in SKETCH_SCHEMA} == prefs.DEFAULTS

    bpy.ops.wm.read_factory_settings(use_empty=True)
    mat = strokes._sketch_material()
    assert tuple(mat.grease_pencil.color) == (1.0, 1.0, 1.0, 1.0) and not compat.gp_material_fill_shown(mat.grease_pencil)


@pytest.mark.blender
@pytest.mark.slow
def test_auto_regions_operator_uses_the_region_preset(addon, ict):
    import bpy

    from facelab_addon.blender.mesh import vertex_group_mask
    from facelab_addon.blender.scene import new_mesh_object
    from facelab_addon.core.lips.regions import auto_regions
    from facelab_addon.pipeline.regions import REGION_DEFAULTS

    def run(**kw):
        bpy.ops.wm.read_factory_settings(use_empty=True)
        for k, v in kw.items():  # the shot's Auto Regions settings (Setup > Settings)
            setattr(bpy.context.scene.facelab_regions, k, v)
        obj = new_mesh_object("Face", ict.neutral, ict.faces)
        bpy.context.view_layer.objects.active = obj
        obj.select_set(True)
        bpy.context.scene.facelab.face = obj
        assert bpy.ops.facelab.auto_regions() == {"FINISHED"}
        return vertex_group_mask(obj, "FL_mouth"), vertex_group_mask(obj, "FL_lips")

    V = np.array(ict.neutral, dtype=np.float32).astype(np.float64)  # what Blender stores
    mouth, lips = run()
    core_mouth, core_lips = auto_regions(V, ict.faces)  # the core defaults
    assert np.array_equal(mouth, core_mouth) and np.array_equal(lips, core_lips)

    assert REGION_DEFAULTS["lip_width"] < 0.2
    _, lips2 = run(lip_width=0.2)  # a wider lip band saved with the shot
    assert lips2.sum() > lips.sum() and not (lips & ~lips2).any()


# --------------------------------------------------------------------------------------------------
# the sample shot (assets/sample, Load Sample)
# --------------------------------------------------------------------------------------------------

SAMPLE = ROOT / "assets" / "sample"
MB = 1e6  # sizes in MB are 10^6 bytes (docs/conventions.md)


def _sample_arrays():
    with np.load(SAMPLE / "face.npz", allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def test_the_sample_is_small_enough_to_ship_and_carries_the_ict_licence():
    files = [p for p in SAMPLE.rglob("*") if p.is_file()]
    total = sum(p.stat().st_size for p in files)
    assert total < 5 * MB, f"assets/sample is {total / MB:.2f} MB; keep the shipped sample under 5 MB"
    assert (SAMPLE / "face.npz").stat().st_size < 1 * MB
    plates = sorted((SAMPLE / "plate").glob("plate_*.jpg"))
    assert all(p.stat().st_size < 150_000 for p in plates)
    assert {p.suffix for p in files} <= {".npz", ".jpg", ".txt", ".md"}, "only the sample's own files"
    lic = (SAMPLE / "LICENSE-ICT-FaceKit.txt").read_text()
    assert lic.startswith("MIT License") and "USC Institute for Creative Technologies" in lic
    assert "Permission is hereby granted" in lic
    readme = (SAMPLE / "README.md").read_text()
    assert "ICT-FaceKit" in readme and "LICENSE-ICT-FaceKit.txt" in readme and "make_sample.py" in readme


def test_the_sample_arrays_and_plate_agree():
    from PIL import Image

    a = _sample_arrays()
    V, T, K = len(a["vertices"]), len(a["weights"]), len(a["expression_names"])
    assert 3000 <= V <= 6000  # a reduced face: a few thousand vertices
    assert 40 <= T <= 60 and a["expression_deltas"].shape == (K, V, 3) and a["capture_error"].shape == (V, 3)
    plates = sorted((SAMPLE / "plate").glob("plate_*.jpg"))
    assert [p.name for p in plates] == [f"plate_{t + 1:04d}.jpg" for t in range(T)]  # one frame per frame
    with Image.open(plates[0]) as im:
        assert im.size == tuple(a["image_size"])
    # the capture's lips fail to close by millimetres (a gap worth fixing), nowhere else
    err_mm = 1e3 * np.linalg.norm(a["capture_error"], axis=1) * a["capture_error_weights"].max()
    assert 2.0 < 2 * err_mm.max() < 3.0  # each lip moves half of the 2.5 mm gap
    moved = err_mm > 0.05
    loop = a["inner_lip_loop"]
    d = np.linalg.norm(a["vertices"][moved][:, None] - a["vertices"][loop][None], axis=2).min(axis=1)
    assert d.max() < 0.015  # within 15 mm of the inner-lip loop


def test_the_sample_is_the_ict_face_reduced(ict):
    """Every sample vertex is an ICT-FaceKit vertex at its upstream position (metres), with its upstream
    expression offsets: the reduction keeps upstream vertices, it does not resample them."""
    a = _sample_arrays()
    src = a["source_vertices"]
    assert len(np.unique(src)) == len(src) and ict.part_vertex_mask("M_Face")[src].all()
    np.testing.assert_allclose(a["vertices"], ict.neutral[src] * 0.01, atol=1e-7)
    for k, name in enumerate(a["expression_names"]):
        np.testing.assert_allclose(a["expression_deltas"][k], (ict.expressions[str(name)] - ict.neutral)[src] * 0.01,
                                   atol=1e-7)
