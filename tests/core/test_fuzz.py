"""Property-based fuzz test of the core entry points (issue 13).

Random small meshes and inputs (NaN, inf, degenerate triangles, duplicate
vertices, empty arrays, random bytes for cache files) go into refinement,
the lip regressor, regions, compression, the cache readers, the camera,
binding and the solvers. The property: every call either returns finite
results or raises one of FaceLab's own errors (a ``FaceLabError``, whose
message names the problem and the fix); any other exception is a bug.
Deterministic (``derandomize=True``) and bounded (about a minute in all).
"""

import struct

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from facelab_addon.core.capture.camera import Camera
from facelab_addon.core.capture.markers import SurfacePoints, bind_surface_points, nearest_surface_points
from facelab_addon.core.capture.obj import read_obj
from facelab_addon.core.capture.pointcache import read_cache
from facelab_addon.core.capture.pointcache_writer import write_pc2
from facelab_addon.core.errors import FaceLabError
from facelab_addon.core.geometry.compress import compress, reconstruct
from facelab_addon.core.geometry.deform import LaplacianDeformer, PointConstraints
from facelab_addon.core.geometry.laplacian import uniform_laplacian
from facelab_addon.core.lgi.binding import bind_points
from facelab_addon.core.lips.lip_loop import inner_lip_loop
from facelab_addon.core.lips.regressor import LipRegressor
from facelab_addon.core.lips.regions import auto_regions, faces_in_region
from facelab_addon.core.lips.refine_params import RefineParams
from facelab_addon.core.lips.sketch import refine_lips
from facelab_addon.core.lips.suggest import suggest_frames
from facelab_addon.core.solve.blendshape_solve import BlendshapeSolver, SolveParams
from facelab_addon.testing.meshes import grid_mesh

from .lipmesh import front_camera, line_px, two_lips

FUZZ = settings(max_examples=150, deadline=None, derandomize=True, database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
SEEDS = st.integers(0, 2**32 - 1)
FLAWS = st.sampled_from(["none", "none", "nan", "inf", "degenerate", "duplicate", "empty_faces", "empty_vertices",
                         "bad_index", "float_faces", "flat"])


def outcome(fn, *args, **kwargs):
    """``fn(...)``'s result, or None when it refuses with a FaceLabError; any other exception fails the test."""
    try:
        return fn(*args, **kwargs)
    except FaceLabError as e:
        assert str(e).strip(), "a FaceLabError must carry a message"
        return None


def finite(*arrays):
    for a in arrays:
        a = np.asarray(a)
        if a.dtype.kind in "fc":
            assert np.isfinite(a).all(), "a result is not finite"


def flawed(V, F, flaw, rng):
    """Apply one kind of bad input to a mesh (copies)."""
    V, F = V.copy(), F.copy()
    if flaw == "nan":
        V[rng.integers(len(V)), rng.integers(3)] = np.nan
    elif flaw == "inf":
        V[rng.integers(len(V)), rng.integers(3)] = np.inf
    elif flaw == "degenerate" and len(F):
        f = F[rng.integers(len(F))]
        V[f[1]] = V[f[0]]
    elif flaw == "duplicate" and len(F):
        V = np.vstack([V, V[F[0, 0]]])
        F[0, 0] = len(V) - 1
    elif flaw == "empty_faces":
        F = F[:0]
    elif flaw == "empty_vertices":
        V, F = V[:0], F[:0]
    elif flaw == "bad_index" and len(F):
        F[rng.integers(len(F)), rng.integers(3)] = len(V) + rng.integers(0, 3) * -len(V) * 3
    elif flaw == "float_faces":
        F = F.astype(float) + 0.5
    elif flaw == "flat":
        V[:, 2] = 0.0
    return V, F


def random_grid(rng):
    n, m = rng.integers(2, 7, 2)
    V, F = grid_mesh(np.arange(n, dtype=float), np.arange(m, dtype=float), None)
    return V + rng.normal(0, rng.choice([0.0, 0.05, 0.5]), V.shape), F


def random_lips(rng):
    V, F, _ = two_lips(gap=float(rng.choice([0.0, 0.05, 0.4, 3.0])), radius=float(rng.uniform(0.2, 1.0)))
    return V + rng.normal(0, rng.choice([0.0, 0.01, 0.2]), V.shape), F


# ---------------------------------------------------------------- regions


@FUZZ
@given(seed=SEEDS, flaw=FLAWS, lips=st.booleans(), loop=st.sampled_from([None, "random", "short"]))
@pytest.mark.slow
def test_fuzz_regions(seed, flaw, lips, loop):
    rng = np.random.default_rng(seed)
    V, F = (random_lips if lips else random_grid)(rng)
    V, F = flawed(V, F, flaw, rng)
    lp = None if loop is None else rng.integers(-2, max(len(V), 1) + 2, 2 if loop == "short" else 6)
    res = outcome(auto_regions, V, F, lp, return_distance=True)
    if res is not None:
        mouth, lip, d, found = res
        assert mouth.shape == lip.shape == (len(V),) and mouth.any() and lip.any()
        assert not np.isnan(d).any()
    res = outcome(inner_lip_loop, V, F, lp)
    if res is not None:
        assert res.ndim == 1 and len(res) >= 3 and res.min() >= 0 and res.max() < len(V)


# ---------------------------------------------------------------- regressor


def _regressor_grid():
    V, F = grid_mesh(np.arange(12, dtype=float), np.arange(10, dtype=float), lambda x, y: 0.3 * np.sin(0.5 * x))
    y = V[:, 1]
    return V, F, faces_in_region(F, (y <= 3) | (y >= 6)), faces_in_region(F, (y >= 3) & (y <= 6))


REG = _regressor_grid()


def _frame(V, rng, kind):
    out = V.copy()
    if kind == "rest":
        return out
    amp = {"tiny": 1e-9, "small": 1e-3, "normal": 0.3, "huge": 1e6}.get(kind, 0.3)
    c = rng.normal(0, amp, (3, 3))
    x, y = V[:, 0] / 12, V[:, 1] / 10
    out += np.stack([np.sin(3 * x + y), np.cos(2 * y), x * y], 1) @ c
    if kind == "nan":
        out[rng.integers(len(V)), 0] = np.nan
    return out


FRAME_KINDS = st.sampled_from(["rest", "tiny", "small", "normal", "normal", "huge", "nan"])


@FUZZ
@given(seed=SEEDS, train=st.lists(FRAME_KINDS, min_size=0, max_size=3), test=st.lists(FRAME_KINDS, min_size=1,
       max_size=3), center=st.sampled_from(["rest", None]), patches=st.sampled_from([1, 3]),
       atol=st.sampled_from([0.0, 1e-4]), out=st.sampled_from([None, "self", "f32", "int", "bad_shape"]))
def test_fuzz_regressor(seed, train, test, center, patches, atol, out):
    rng = np.random.default_rng(seed)
    V, F, mouth, lips = REG
    reg = LipRegressor(V, F, mouth, lips, center=center, patches=patches, atol=atol)
    T = np.stack([_frame(V, rng, k) for k in train]) if train else np.zeros((0,) + V.shape)
    if outcome(reg.fit, T) is None:
        return
    X = np.stack([_frame(V, rng, k) for k in test])
    o = {None: None, "self": X, "f32": X.astype(np.float32), "int": np.zeros(X.shape, int),
         "bad_shape": np.zeros((len(X) + 1,) + V.shape)}[out]
    keep = None if o is None else o.copy()
    res = outcome(reg.predict, X, out=o)
    if res is None:
        if o is not None:
            np.testing.assert_array_equal(o, keep)  # a refused prediction writes nothing
    else:
        finite(res)
        move = np.linalg.norm(res - X, axis=2).max()
        assert move <= reg.mouth_size * (1 + 1e-6) + 1e-3
    e = outcome(reg.extrapolation, X)
    if e is not None:
        finite(e)
        assert (e >= 0).all()
    if outcome(reg.add, X) is not None:
        idx = outcome(suggest_frames, X, 2, regressor=reg)
        if idx is not None:
            assert all(0 <= i < len(X) for i in idx)


# ---------------------------------------------------------------- compression


@FUZZ
@given(seed=SEEDS, T=st.integers(0, 5), nv=st.integers(0, 6), kind=st.sampled_from(["zeros", "normal", "nan", "inf",
       "huge", "rank1"]), tol=st.sampled_from([None, 0.0, 1e-6, -1.0, np.nan, 1.0]),
       mpu=st.sampled_from([1.0, 0.01, 0.0, -1.0]), max_rank=st.sampled_from([None, 0, 1, 3]))
def test_fuzz_compress(seed, T, nv, kind, tol, mpu, max_rank):
    rng = np.random.default_rng(seed)
    C = np.zeros((T, nv, 3))
    if kind != "zeros":
        C = rng.normal(0, 1e6 if kind == "huge" else 1.0, C.shape)
        if kind == "rank1" and T:
            C = C[:1] * rng.normal(size=(T, 1, 1))
        if kind in ("nan", "inf") and C.size:
            C.flat[rng.integers(C.size)] = np.nan if kind == "nan" else np.inf
    if seed % 2:
        C = C.astype(np.float32)
    res = outcome(compress, C, tol, metres_per_unit=mpu, max_rank=max_rank)
    if res is None:
        return
    basis, weights = res[0], res[1]
    finite(basis, weights)
    R = outcome(reconstruct, basis, weights)
    if R is not None:
        finite(R)


# ---------------------------------------------------------------- cache readers


@FUZZ
@given(data=st.binary(min_size=0, max_size=200), ext=st.sampled_from([".pc2", ".mdd", ".bin"]),
       header=st.booleans(), frames=st.sampled_from([None, [0], [-1], [10**9], [0, 0]]))
def test_fuzz_cache_readers_on_random_bytes(tmp_path_factory, data, ext, header, frames):
    d = tmp_path_factory.mktemp("fuzz")
    p = d / f"c{ext}"
    if header:  # a valid PC2 whose body is overwritten by the random bytes
        write_pc2(p, np.zeros((2, 3, 3), np.float32))
        raw = bytearray(p.read_bytes())
        raw[32 - min(len(data), 32) + 32 :] = data[:len(raw)]
        p.write_bytes(bytes(raw))
    else:
        p.write_bytes(data)
    res = outcome(read_cache, p, frames)
    if res is not None:
        arr = res[0] if isinstance(res, tuple) else res
        finite(arr)


@FUZZ
@given(seed=SEEDS, fmt=st.sampled_from(["PC2", "MDD"]), V=st.sampled_from([0, 1, 3, -1, 2**31 - 1]),
       T=st.sampled_from([0, 1, 2, -5, 2**31 - 1]), body=st.sampled_from(["exact", "short", "long", "nan"]),
       rate=st.sampled_from([1.0, 0.0, np.nan, -1.0]), frames=st.sampled_from([None, [0], [1, 0], [-1], [5],
       [0.5]]), ask=st.sampled_from([None, "PC2", "MDD", "OBJ"]))
def test_fuzz_cache_readers_on_structured_headers(tmp_path_factory, seed, fmt, V, T, body, rate, frames, ask):
    rng = np.random.default_rng(seed)
    nv, nt = max(min(V, 4), 0), max(min(T, 3), 0)
    data = rng.normal(size=(nt, nv, 3)).astype(np.float32)
    if body == "nan" and data.size:
        data.flat[rng.integers(data.size)] = np.nan
    if fmt == "PC2":
        head = b"POINTCACHE2\0" + struct.pack("<iiffi", 1, V, 1.0, rate, T)
        payload = data.astype("<f4").tobytes()
    else:
        head = struct.pack(">ii", T, V) + np.arange(nt, dtype=">f4").tobytes()
        payload = data.astype(">f4").tobytes()
    payload = {"short": payload[: len(payload) // 2], "long": payload + b"\0" * 7}.get(body, payload)
    p = tmp_path_factory.mktemp("fuzz") / f"c.{fmt.lower()}"
    p.write_bytes(head + payload)
    res = outcome(read_cache, p, frames, fmt=ask)
    if res is not None:
        finite(res)
        assert res.ndim == 3 and res.shape[2] == 3


@FUZZ
@given(text=st.text(alphabet=st.sampled_from(list("vf 0123456789.-/#enai\n")), max_size=120),
       raw=st.binary(max_size=60), use_raw=st.booleans())
def test_fuzz_obj_reader(tmp_path_factory, text, raw, use_raw):
    p = tmp_path_factory.mktemp("fuzz") / "m.obj"
    p.write_bytes(raw if use_raw else text.encode())
    m = outcome(read_obj, p)
    if m is not None:
        V = np.asarray(m.vertices)
        finite(V)
        for F in (getattr(m, "faces", None), getattr(m, "triangles", None)):
            if F is not None and np.asarray(F).size:
                assert np.asarray(F).min() >= 0 and np.asarray(F).max() < len(V)


# ---------------------------------------------------------------- camera


NUMS = st.sampled_from([0.0, 1.0, -1.0, 1e-12, 1e12, np.nan, np.inf, 1920.0])


@FUZZ
@given(seed=SEEDS, f=NUMS, w=NUMS, h=NUMS, tz=NUMS, pts=st.sampled_from(["normal", "behind", "nan", "empty",
       "on_center"]), R=st.sampled_from(["eye", "random", "singular"]))
def test_fuzz_camera(seed, f, w, h, tz, pts, R):
    rng = np.random.default_rng(seed)
    K = np.array([[f, 0, 960], [0, f, 540], [0, 0, 1.0]])
    Rm = {"eye": np.eye(3), "random": rng.normal(size=(3, 3)), "singular": np.zeros((3, 3))}[R]
    cam = outcome(Camera, K, Rm, [0, 0, tz], w, h)
    if cam is None:
        return
    X = {"normal": rng.normal(0, 1, (4, 3)) + [0, 0, 5], "behind": rng.normal(0, 1, (4, 3)) - [0, 0, 50],
         "nan": np.full((2, 3), np.nan), "empty": np.zeros((0, 3)), "on_center": np.tile(cam.center, (2, 1))}[pts]
    px = outcome(cam.project, X)
    if px is not None:
        assert px.shape == (len(X), 2)
        seen = np.isfinite(X).all(axis=1) & (cam.depth(X) > 1e-9 * (1 + np.abs(X).max(initial=0)))
        finite(px[seen])  # documented: points at or behind the camera plane (or NaN) give non-finite pixels
    r = outcome(cam.rays, rng.normal(500, 400, (3, 2)))
    if r is not None:
        finite(*r)
    P = {"eye": rng.normal(size=(3, 4)), "random": np.full((3, 4), np.nan), "singular": np.zeros((3, 4))}[R]
    c2 = outcome(Camera.from_projection, P, 640, 480)
    if c2 is not None:
        finite(c2.K, c2.R, c2.t)
    c3 = outcome(Camera.look_at, [0, 0, tz], [0, 0, 0], [0, 1, 0] if R != "singular" else [0, 0, 1], f, 36, w, h)
    if c3 is not None:
        finite(c3.K, c3.R, c3.t)


# ---------------------------------------------------------------- binding


@FUZZ
@given(seed=SEEDS, flaw=FLAWS, npts=st.integers(0, 5), pflaw=st.sampled_from(["none", "nan", "far"]),
       maxd=st.sampled_from([None, 0.0, 1e-9, 10.0, -1.0]))
def test_fuzz_binding(seed, flaw, npts, pflaw, maxd):
    rng = np.random.default_rng(seed)
    V, F = flawed(*random_grid(rng), flaw, rng)
    P = rng.uniform(0, 3, (npts, 3)) * [1, 1, 0.01]
    if pflaw == "nan" and npts:
        P[0, 1] = np.nan
    elif pflaw == "far":
        P += 1e3
    res = outcome(bind_points, V, F, P, max_distance=maxd)
    if res is not None:
        fi, bary, dist = res
        finite(bary, dist)
        assert fi.min(initial=0) >= 0 and fi.max(initial=0) < len(F)
    sv = rng.integers(-1, max(len(V), 1), (npts, 3))
    bad_shape = pflaw == "far"
    sp2 = outcome(SurfacePoints, sv, rng.random((npts, 2 if bad_shape else 3)))
    if sp2 is not None:
        assert len(sp2) == npts
    sp_ = outcome(nearest_surface_points, V, F, P)
    if sp_ is not None:
        finite(sp_.bary)
    cam = Camera.look_at([1, 1, 10], [1, 1, 0], [0, 1, 0], 50, 36, 640, 480)
    px = rng.normal(320, 200, (npts, 2))
    if pflaw == "nan" and npts:
        px[0, 0] = np.nan
    res = outcome(bind_surface_points, V, F, cam, px)
    if res is not None:
        pts, hit = res
        finite(pts.bary)
        assert len(pts) == len(hit) == npts


# ---------------------------------------------------------------- solvers


@FUZZ
@given(seed=SEEDS, flaw=FLAWS, lam=st.sampled_from([1.0, 0.0, -1.0, np.nan]), pos=st.sampled_from([0.0, 1.0, np.inf]),
       pinned=st.sampled_from(["none", "some", "all", "out_of_range"]), anchor=st.sampled_from(["ok", "nan",
       "wrong_shape"]), cons=st.booleans())
def test_fuzz_laplacian_deformer(seed, flaw, lam, pos, pinned, anchor, cons):
    rng = np.random.default_rng(seed)
    V, F = flawed(*random_grid(rng), flaw, rng)
    L = outcome(lambda: uniform_laplacian(F, len(V)))
    if L is None:
        return
    pin = {"none": None, "some": np.array([0]), "all": np.arange(len(V)), "out_of_range": np.array([len(V) + 5])}[pinned]
    dfm = outcome(LaplacianDeformer, L, lambda_reg=lam, pos_weights=pos, pinned=pin)
    if dfm is None:
        return
    A = {"ok": V, "nan": np.full_like(V, np.nan), "wrong_shape": V[:-1]}[anchor]
    c = None
    if cons and len(V) >= 3:
        c = outcome(PointConstraints, np.array([[0, 1, 2]]), np.array([[1 / 3, 1 / 3, 1 / 3]]),
                    rng.normal(size=(1, 3)), np.eye(3)[None], np.ones(1))
    X = outcome(dfm.solve, A, constraints=c)
    if X is not None:
        finite(X)


@FUZZ
@given(seed=SEEDS, flaw=FLAWS, nshapes=st.integers(0, 3), px=st.sampled_from(["ok", "nan", "all_nan", "huge"]),
       bounds=st.sampled_from([(-1.0, 1.0), (0.0, 1.0), (1.0, -1.0), (np.nan, 1.0)]))
def test_fuzz_blendshape_solver_on_a_tiny_rig(seed, flaw, nshapes, px, bounds):
    rng = np.random.default_rng(seed)
    V, F = random_grid(rng)
    V = V + [0, 0, 0]
    D = rng.normal(0, 0.2, (nshapes,) + V.shape)
    V, F = flawed(V, F, flaw, rng)
    if D.shape[1:] != V.shape:
        D = rng.normal(0, 0.2, (nshapes,) + V.shape)
    cam = Camera.look_at([1, 1, 10], [1, 1, 0], [0, 1, 0], 50, 36, 640, 480)
    mk = outcome(nearest_surface_points, V, F, V[:4] if len(V) else np.zeros((0, 3)))
    if mk is None:
        return
    solver = outcome(BlendshapeSolver, V, D, F, [cam], mk, None, params=SolveParams(bounds=bounds))
    if solver is None:
        return
    obs = cam.project(V[:4])[None] if px != "huge" else np.full((1, len(mk), 2), 1e15)
    if px == "nan":
        obs = obs.copy()
        obs[0, 0] = np.nan
    elif px == "all_nan":
        obs = np.full_like(obs, np.nan)
    res = outcome(solver.solve_frame, obs)
    if res is not None:
        finite(res.weights)


# ---------------------------------------------------------------- refine


LIPS = two_lips(gap=0.4)
CAM = front_camera()


@settings(FUZZ, max_examples=30)
@given(seed=SEEDS, upper=st.sampled_from(["ok", "empty", "nan", "one_point", "offscreen", "duplicate"]),
       lower=st.sampled_from(["ok", "empty", "nan", "crossing"]), flaw=st.sampled_from(["none", "nan", "degenerate",
       "duplicate", "bad_index"]), iterations=st.sampled_from([0, 1, 2, -1]))
def test_fuzz_refine_lips(seed, upper, lower, flaw, iterations):
    rng = np.random.default_rng(seed)
    V, F, _ = LIPS
    V, F = flawed(V, F, flaw, rng)
    U = line_px(CAM, 0.05, n=10)
    Lw = line_px(CAM, -0.05, n=10)
    U = {"ok": U, "empty": np.zeros((0, 2)), "nan": np.where(rng.random(U.shape) < 0.2, np.nan, U),
         "one_point": U[:1], "offscreen": U + 1e5, "duplicate": np.repeat(U[:1], 5, axis=0)}[upper]
    Lw = {"ok": Lw, "empty": np.zeros((0, 2)), "nan": np.full_like(Lw, np.nan), "crossing": line_px(CAM, 0.3, n=10)}[lower]
    res = outcome(lambda: refine_lips(V, F, CAM, U, Lw, RefineParams(iterations=iterations)))
    if res is not None:
        finite(res)
        assert res.shape == V.shape


@pytest.mark.parametrize("seed", [0])
def test_fuzz_module_uses_only_facelab_errors(seed):
    """The helper fails the test on a foreign exception (so the fuzz tests above can fail)."""
    with pytest.raises(IndexError):
        outcome(lambda: np.zeros(1)[3])
    assert outcome(lambda: (_ for _ in ()).throw(FaceLabError("x; fix"))) is None


# ---------------------------------------------------------------- the process itself (libigl)
_CHILD = """
import sys
from facelab_addon.core.errors import FaceLabError
from facelab_addon.core.geometry.geodesic import geodesic_distance
from facelab_addon.core.lips.regions import auto_regions
from facelab_addon.testing.meshes import malformed_grid
for seed in range(int(sys.argv[1]), int(sys.argv[2])):
    V, F, kinds = malformed_grid(seed)
    print(seed, kinds, flush=True)
    for call in (lambda: auto_regions(V, F, None), lambda: geodesic_distance(V, F, [0, len(V) // 2], 3.0)):
        try:
            call()
        except FaceLabError:
            pass
print("done", flush=True)
"""


def test_malformed_meshes_never_kill_the_process():
    """Auto Regions and geodesic distances on perturbed grids with flipped, repeated, non-manifold or sliver
    triangles, holes and merged corners, run in a child process: a crash inside libigl (it segfaulted on seed 35
    and looped for ever on seed 61) fails this test, naming the mesh, instead of killing the test run. Every
    call must return or raise a FaceLabError."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    root = str(Path(__file__).resolve().parents[2])
    env = dict(os.environ, PYTHONPATH=root + os.pathsep + os.environ.get("PYTHONPATH", ""))
    try:
        run = subprocess.run([sys.executable, "-c", _CHILD, "0", "200"], capture_output=True, text=True, env=env,
                             timeout=240)
    except subprocess.TimeoutExpired as e:
        last = (e.stdout or b"").decode(errors="replace").strip().splitlines()[-1:]
        pytest.fail(f"a call hung on the malformed mesh {last}")
    lines = run.stdout.strip().splitlines()
    assert run.returncode == 0 and lines[-1:] == ["done"], \
        f"the process died (code {run.returncode}) on the malformed mesh {lines[-1:]}: {run.stderr[-2000:]}"
