"""Compiled rasterizer backends pinned to the pure-torch reference.

The CPU extension runs the math header the CUDA kernels share, so these tests check both; the
CUDA-specific tests run only where torch has CUDA, and every .cu file is compiled with nvcc
when nvcc is on PATH.
"""
import shutil
import subprocess
import warnings
from pathlib import Path

import pytest
import torch

from stdr import render as render_mod
from stdr import extension
from stdr.render import compiled, rasterize, render, resolve_backend
from stdr.verified import VERIFIED
from stdr.render.projection import project_and_shade, project_gaussians

from helpers import brute_force_composite, hard_case_scene, look_at_camera, random_gaussians

BACKENDS = ["cpu"] + (["cuda"] if torch.cuda.is_available() and torch.version.cuda else [])


def _inputs(means, quats, scales, opac, colors, cam):
    p = project_gaussians(means, quats, scales, opac, cam)
    feats = torch.cat([colors, p.depths[:, None]], -1)
    leaves = [x.detach().clone().requires_grad_(True) for x in (p.means2d, p.conics, p.opacities, feats)]
    return leaves, p


def _run(backend, leaves, p, cam, tile, seed=0):
    dev = "cuda" if backend == "cuda" else "cpu"
    xs = [x.detach().to(dev).requires_grad_(True) for x in leaves]
    acc, T = rasterize(*xs, p.depths.detach().to(dev), p.radii.to(dev), cam.width, cam.height,
                       tile_size=tile, backend=backend)
    g = torch.Generator().manual_seed(seed)
    wa = torch.randn(acc.shape, generator=g).to(dev, acc.dtype)  # same weights in every dtype
    wt = torch.randn(T.shape, generator=g).to(dev, T.dtype)
    loss = (acc * wa).sum() + (T * wt).sum()
    if not loss.requires_grad:  # N = 0 in the reference: the image does not depend on inputs
        return acc.detach().cpu(), T.detach().cpu(), [torch.zeros_like(x).cpu() for x in xs]
    grads = torch.autograd.grad(loss, xs, allow_unused=True)
    grads = [torch.zeros_like(x) if gr is None else gr for x, gr in zip(xs, grads)]
    return acc.detach().cpu(), T.detach().cpu(), [gr.cpu() for gr in grads]


def _assert_parity(backend, scene, cam, tiles=(8, 16), img_tol=1e-5, grad_rtol=1e-4):
    """The oracle is the reference evaluated in float64 on the same inputs (the float32
    reference itself loses precision in its expanded exponent: ~1e-3 relative on conic
    gradients of Gaussians far from a tile centre)."""
    leaves, p = _inputs(*scene, cam)
    p64 = type(p)(**{k: (v.double() if v.is_floating_point() else v) for k, v in vars(p).items()})
    ref_acc, ref_T, ref_g = _run("reference", [x.double() for x in leaves], p64, cam, 8)
    dt = leaves[0].dtype
    ref_acc, ref_T, ref_g = ref_acc.to(dt), ref_T.to(dt), [g.to(dt) for g in ref_g]
    for tile in tiles:
        acc, T, gr = _run(backend, leaves, p, cam, tile)
        assert (acc - ref_acc).abs().max() <= img_tol, (tile, (acc - ref_acc).abs().max())
        assert (T - ref_T).abs().max() <= img_tol, (tile, (T - ref_T).abs().max())
        for name, a, b in zip(("means2d", "conics", "opacities", "features"), gr, ref_g):
            if b.numel() == 0:
                continue
            scale = b.abs().max().clamp_min(1e-12)
            err = ((a - b).abs().max() / scale).item()
            assert err <= grad_rtol, (tile, name, err)
    return ref_T


@pytest.mark.parametrize("backend", BACKENDS)
def test_random_scene_matches_reference_float32(backend):
    cam = look_at_camera((2.5, 0.3, 0.8), width=61, height=45)
    # tiles 3 and 5 leave padding lanes in the CPU float32 path's 16-pixel chunks
    tiles = (3, 5, 8, 16) if backend == "cpu" else (8, 16)
    T = _assert_parity(backend, random_gaussians(400, seed=1), cam, tiles=tiles)
    assert T.min() < 1e-3  # early termination exercised


@pytest.mark.parametrize("channels", [1, 2, 5, 8])
def test_every_channel_count_matches_reference(channels):
    """The CPU float32 path is compiled per channel count F: its forward keeps F accumulators in
    registers and its backward reduces 6 + F values across lanes at once."""
    cam = look_at_camera((2.5, 0.3, 0.8), width=37, height=29)
    means, quats, scales, opac, _ = random_gaussians(200, seed=6)
    feats = torch.rand(200, channels - 1, generator=torch.Generator().manual_seed(2))  # + depth
    _assert_parity("cpu", (means, quats, scales, opac, feats), cam, tiles=(5, 8))


def test_cpu_float64_matches_brute_force_exactly():
    d = torch.float64
    cam = look_at_camera((2.5, 0.3, 0.8), width=23, height=17, dtype=d)
    leaves, p = _inputs(*random_gaussians(80, seed=2, dtype=d), cam)
    ref_img, ref_T = brute_force_composite(*[x.detach() for x in leaves], p.depths, p.radii,
                                           cam.width, cam.height)
    for tile in (1, 3, 8, 16, 32):
        acc, T, _ = _run("cpu", leaves, p, cam, tile)
        assert torch.allclose(acc, ref_img, atol=1e-12) and torch.allclose(T, ref_T, atol=1e-12), tile
    _assert_parity("cpu", random_gaussians(80, seed=2, dtype=d), cam, tiles=(4, 8),
                   img_tol=1e-12, grad_rtol=1e-9)


def _hard_scene(dtype):
    # the reference's hard cases plus an opacity below 1/255 (invisible everywhere)
    return hard_case_scene(dtype, extra_rows=[([0.0, 0.3, -0.3], [0.05, 0.05, 0.05], 0.003)])


@pytest.mark.parametrize("backend", BACKENDS)
def test_hard_cases_match_reference(backend):
    cam = look_at_camera((3.0, 0.0, 0.0), width=40, height=28)
    _assert_parity(backend, _hard_scene(torch.float32), cam)
    if backend == "cpu":
        cam64 = look_at_camera((3.0, 0.0, 0.0), width=20, height=14, dtype=torch.float64)
        _assert_parity(backend, _hard_scene(torch.float64), cam64, tiles=(4, 8, 16),
                       img_tol=1e-12, grad_rtol=1e-9)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("n", [0, 1])
def test_tiny_counts(backend, n):
    cam = look_at_camera((2.5, 0.3, 0.8), width=9, height=7)
    m, q, s, o, c = random_gaussians(max(n, 1), seed=3, spread=0.05, scale=(-1.5, -1.0))
    _assert_parity(backend, (m[:n], q[:n], s[:n], o[:n], c[:n]), cam)


@pytest.mark.parametrize("backend", BACKENDS)
def test_one_pixel_image(backend):
    cam = look_at_camera((2.5, 0.0, 0.0), width=1, height=1, fov_x=0.5)
    _assert_parity(backend, random_gaussians(10, seed=4, spread=0.05, scale=(-1.5, -1.0)), cam)


@pytest.mark.parametrize("backend", BACKENDS)
def test_render_gradients_match_reference_end_to_end(backend):
    """Through projection and SH: gradients for every 3D parameter and the 2D means."""
    cam = look_at_camera((2.5, 0.3, 0.8), width=48, height=40)
    means, quats, scales, opac, _ = random_gaussians(300, seed=5)
    sh = torch.randn(300, 4, 3, generator=torch.Generator().manual_seed(1)) * 0.3
    out = {}
    for b in ("reference", backend):
        dev = "cuda" if b == "cuda" else "cpu"
        xs = [x.clone().to(dev).requires_grad_(True) for x in (means, quats, scales, opac, sh)]
        r = render(*xs, cam, sh_degree=1,
                   background=torch.tensor([0.2, 0.3, 0.4]), backend=b)
        (r.image.square().sum() + r.depth.sum() + r.alpha.sum()).backward()
        out[b] = (r.image.detach().cpu(), [x.grad.cpu() for x in xs], r.means2d.grad.cpu())
    img_r, g_r, m2_r = out["reference"]
    img_c, g_c, m2_c = out[backend]
    assert (img_c - img_r).abs().max() <= 1e-5
    for a, b in zip(g_c + [m2_c], g_r + [m2_r]):
        assert ((a - b).abs().max() / b.abs().max()).item() <= 1e-4


@pytest.mark.skipif("cuda" not in BACKENDS, reason="no CUDA device on this machine (torch.cuda.is_available() is False)")
@pytest.mark.parametrize("n,res", [(20_000, 256), (200_000, 800)])
def test_cuda_matches_the_cpu_backend_at_training_scale(n, res):
    """The small parity tests above cover the edge cases; this one runs the CUDA kernels at the
    sizes training uses (hundreds of tiles, long per-tile lists, many blocks writing the same
    Gaussian's gradient with atomics) against the CPU backend, which runs the same math header
    in a fixed order. Fresh random scenes (the benchmark's generator); errors are relative to the
    norm of the CPU result, so an unwritten pixel or a lost atomic add shows."""
    from stdr.tools.bench_rasterizer import make_scene

    (means, quats, scales, opac, _), cam = make_scene(n, res, coverage=5.0, seed=n)
    g = torch.Generator().manual_seed(res)
    colors = torch.rand(n, 3, generator=g)
    leaves, p = _inputs(means, quats, scales, opac, colors, cam)
    cpu_acc, cpu_T, cpu_g = _run("cpu", leaves, p, cam, 16)
    acc, T, grads = _run("cuda", leaves, p, cam, 16)
    assert torch.isfinite(acc).all() and torch.isfinite(T).all()
    rel = lambda a, b: ((a - b).norm() / b.norm().clamp_min(1e-30)).item()  # noqa: E731
    assert rel(acc, cpu_acc) <= 1e-5 and rel(T, cpu_T) <= 1e-5, (rel(acc, cpu_acc), rel(T, cpu_T))
    assert (cpu_T < 0.5).float().mean() > 0.2  # the scene covers the image: real compositing
    for name, a, b in zip(("means2d", "conics", "opacities", "features"), grads, cpu_g):
        assert torch.isfinite(a).all(), name
        assert rel(a, b) <= 1e-4, (name, rel(a, b))


@pytest.mark.parametrize("backend", BACKENDS + ["reference"])
def test_benchmark_row_runs_each_backend_on_its_device(backend):
    """`stdr-tool bench-rasterizer` times every backend on the device it renders on (a CUDA row
    once failed before timing anything because the scene was resolved for the CPU)."""
    from stdr.tools.bench_rasterizer import label, measure_row

    row = measure_row(backend, n=300, res=32, coverage=2.0, repeats=1, tile=0)
    assert row["device"] == ("cuda" if backend == "cuda" else "cpu") and row["backend"] == backend
    assert row["fwd_ms"] > 0 and row["fwd_bwd_ms"] > 0 and row["pair_evals"] > 0
    assert label(row) == backend
    if torch.cuda.is_available() and backend == "reference":
        row = measure_row(backend, n=300, res=32, coverage=2.0, repeats=1, tile=0, reference_device="cuda")
        assert row["device"] == "cuda" and label(row) == "reference (cuda)"


def test_cpu_backward_is_deterministic():
    cam = look_at_camera((2.5, 0.3, 0.8), width=50, height=50)
    leaves, p = _inputs(*random_gaussians(500, seed=6), cam)
    a = _run("cpu", leaves, p, cam, 8)[2]
    b = _run("cpu", leaves, p, cam, 8)[2]
    assert all(torch.equal(x, y) for x, y in zip(a, b))


def test_auto_prefers_compiled_and_falls_back_with_one_warning(monkeypatch):
    assert resolve_backend("auto", "cpu") == "cpu"
    assert resolve_backend("reference") == "reference"
    with pytest.raises(ValueError, match="render.backend"):
        resolve_backend("opengl")
    # simulate a machine without a compiler: a fresh module cache and a failing build
    monkeypatch.setattr(extension, "_modules", {})
    monkeypatch.setattr(extension, "_errors", {})
    monkeypatch.setattr(render_mod, "_warned", set())

    def no_compiler(kind, verbose=False):
        raise extension.BuildError(f"could not build the {kind} extension: no C++ compiler")
    monkeypatch.setattr(extension, "_compile", no_compiler)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert resolve_backend("auto", "cpu") == "reference"
        assert resolve_backend("auto", "cpu") == "reference"
    msgs = [str(w.message) for w in caught if issubclass(w.category, RuntimeWarning)]
    assert len(msgs) == 1 and "no C++ compiler" in msgs[0] and "reference" in msgs[0]
    with pytest.raises(extension.BuildError, match="no C\\+\\+ compiler"):
        resolve_backend("cpu")  # asked for by name: an error, never a silent fallback


@pytest.mark.parametrize("kind", ["cpu", "cuda"])
def test_bad_inputs_are_rejected_in_python_with_the_values(kind):
    """Every input the compiled backends cannot take is a ValueError raised before any C++ runs
    (also for kind='cuda' on a machine without a GPU), naming the tensor and what it got."""
    z = torch.zeros
    ok = dict(means2d=z(2, 2), conics=z(2, 3), opacities=z(2), features=z(2, 3), depths=z(2),
              radii=torch.ones(2), width=8, height=8, tile_size=16)
    bad = [({"features": z(2, 9)}, r"1\.\.8 feature channels \(got 9\); use render.backend=reference"),
           ({"features": z(2, 0)}, "got 0"),
           ({"conics": z(3, 3)}, r"conics must be \[2, 3\] for N=2 Gaussians, got \[3, 3\]"),
           ({"opacities": z(2, 1)}, r"opacities must be \[2\]"),
           ({"radii": torch.ones(3)}, "radii must be"),
           ({"depths": z(2, dtype=torch.float64)}, "share one dtype .*depths"),
           ({"features": z(3, 3)}, r"features must be \[N, F\] with N=2"),
           ({"width": 0}, "empty image"),
           ({"tile_size": 64}, "render.tile_size must be")]
    for change, msg in bad:
        with pytest.raises(ValueError, match=msg):
            compiled.rasterize_compiled(**{**ok, **change}, kind=kind)
    if kind == "cuda":  # CPU tensors given to the CUDA backend, and tiles it has no kernel for
        for change, msg in [({}, "means2d is on cpu; every input must be on the CUDA"),
                            ({"tile_size": 32}, "must be 8 or 16 .got 32."),
                            ]:
            with pytest.raises(ValueError, match=msg):
                compiled.check_inputs(**{**ok, **change}, kind="cuda")
        f64 = {k: v.double() if v.is_floating_point() else v for k, v in ok.items() if torch.is_tensor(v)}
        with pytest.raises(ValueError, match="float inputs must be float32, got torch.float64"):
            compiled.check_inputs(**{**ok, **f64}, kind="cuda")
    else:
        compiled.check_inputs(**ok, kind="cpu")  # the valid set passes


def test_extension_checks_raise_with_literal_messages():
    """The C++ checks behind the Python ones still raise (called directly), and every TORCH_CHECK
    in csrc passes one string literal: formatted messages crashed one CUDA toolchain instead of
    raising (compiled.check_inputs)."""
    import re

    z = torch.zeros
    ext = compiled.load_extension("cpu")
    with pytest.raises(RuntimeError, match="more feature channels than stdr::MAX_CHANNELS"):
        ext.forward(z(2, 2), z(2, 3), z(2), z(2, 9), z(2), torch.ones(2, dtype=torch.int32), 8, 8, 16)
    with pytest.raises(RuntimeError, match="conics must be"):
        ext.forward(z(2, 2), z(3, 3), z(2), z(2, 3), z(2), torch.ones(2, dtype=torch.int32), 8, 8, 16)
    with pytest.raises(RuntimeError, match="render.tile_size must be in"):
        ext.forward(z(2, 2), z(2, 3), z(2), z(2, 3), z(2), torch.ones(2, dtype=torch.int32), 8, 8, 64)
    sources = [p for p in extension.CSRC.rglob("*") if p.suffix in (".cpp", ".cu", ".h")]
    calls = 0
    for src in sources:
        text = src.read_text()
        for m in re.finditer(r"TORCH_CHECK\(", text):
            depth, i = 1, m.end()
            while depth:  # the macro's argument list, parentheses balanced
                depth += {"(": 1, ")": -1}.get(text[i], 0)
                i += 1
            args = text[m.end():i - 1]
            # the message: everything after the condition's top-level comma is one literal
            level, cut = 0, None
            for j, ch in enumerate(args):
                level += {"(": 1, ")": -1}.get(ch, 0)
                if ch == "," and level == 0:
                    cut = j
                    break
            assert cut is not None, f"{src.name}: TORCH_CHECK without a message: {args[:80]}"
            msg = args[cut + 1:].strip()
            assert re.fullmatch(r'("([^"\\]|\\.)*"\s*)+', msg), f"{src.name}: formatted TORCH_CHECK message {msg!r}"
            calls += 1
    assert calls >= 15
    header = (extension.CSRC / "raster_math.h").read_text()
    assert f"constexpr int MAX_CHANNELS = {compiled.MAX_CHANNELS};" in header


NVCC = shutil.which("nvcc")


@pytest.mark.skipif(NVCC is None, reason="nvcc not on PATH")
@pytest.mark.parametrize("arch", ["sm_80", "sm_90"])
def test_cuda_kernels_compile_with_nvcc(tmp_path, arch):
    """Every .cu compiles on its own (no torch headers in kernel translation units)."""
    sources = sorted((extension.CSRC / "cuda").glob("*.cu"))
    assert sources
    for src in sources:
        text = src.read_text()
        assert "torch/" not in text and "ATen/" not in text, src
        proc = subprocess.run([NVCC, "-c", f"-arch={arch}", "-std=c++17", "-O3", str(src),
                               "-o", str(tmp_path / (src.stem + ".o"))],
                              capture_output=True, text=True, timeout=300)
        assert proc.returncode == 0, proc.stderr[-3000:]
        assert "warning" not in proc.stderr.lower(), proc.stderr[-3000:]


@pytest.mark.slow
def test_training_with_either_backend_reaches_the_same_psnr(tmp_path):
    """300 iterations on the embedded scene with a fixed set of Gaussians reach the same test
    PSNR with the reference and the compiled CPU backend (within 0.1 dB).

    Densification is off on purpose: its thresholds turn 1e-7 gradient differences into
    different clone/split/prune decisions (and a shifted random stream), after which two runs
    differ by seed-to-seed noise (measured +-0.5 dB at 400 iterations, either sign; see
    docs/rasterizer.md), whichever backends they use.
    """
    import json

    from stdr.train.run import run_training as run
    from stdr.testing import tiny_config as _tiny

    res = {}
    for b in ("reference", "cpu"):
        cfg = _tiny(tmp_path, ["optim.iterations=300", "baseline.warmup=100", "densify.refine_stop=0",
                               "densify.reset_every=0", "train.eval_at_warmup_end=false",
                               f"render.backend={b}"])
        res[b] = run(cfg, tmp_path / b)
        conv = json.loads((tmp_path / b / "metrics.json").read_text())["test"]["conventions"]
        assert conv["render_backend"] == b
    assert res["cpu"]["num_gaussians"] == res["reference"]["num_gaussians"]
    assert abs(res["cpu"]["psnr"] - res["reference"]["psnr"]) <= 0.1, (res["cpu"]["psnr"], res["reference"]["psnr"])


@pytest.mark.slow
@pytest.mark.skipif(NVCC is None or shutil.which("g++") is None, reason="nvcc or g++ not on PATH")
def test_cuda_binding_compiles_against_torch_headers(tmp_path):
    """The CUDA binding is built only where torch has CUDA; check its C++ here anyway.

    CPU wheels of torch lack one generated header of the CUDA build (c10/cuda/impl/
    cuda_cmake_macros.h); an empty stand-in is enough for a syntax check.
    """
    import sysconfig
    from pathlib import Path

    from torch.utils.cpp_extension import CUDA_HOME, include_paths

    cuda_inc = Path(CUDA_HOME or "/usr/local/cuda") / "include"
    if not (cuda_inc / "cuda_runtime_api.h").is_file():
        pytest.skip(f"no CUDA runtime headers under {cuda_inc}")
    stub = tmp_path / "stub" / "c10" / "cuda" / "impl"
    stub.mkdir(parents=True)
    (stub / "cuda_cmake_macros.h").write_text("#pragma once\n")
    incs = [f"-I{p}" for p in include_paths()] + [f"-I{sysconfig.get_paths()['include']}",
                                                   f"-I{tmp_path / 'stub'}", f"-I{cuda_inc}"]
    src = extension.CSRC / "cuda" / "ops_cuda.cpp"
    proc = subprocess.run(["g++", "-fsyntax-only", "-std=c++17", "-DTORCH_EXTENSION_NAME=x",
                           *incs, str(src)], capture_output=True, text=True, timeout=300)
    errors = [ln for ln in proc.stderr.splitlines() if "error" in ln]
    assert proc.returncode == 0 and not errors, "\n".join(errors[:20]) or proc.stderr[-3000:]


def test_cpu_rejects_bad_tile_size():
    cam = look_at_camera((2.5, 0.3, 0.8), width=8, height=8)
    leaves, p = _inputs(*random_gaussians(5, seed=7), cam)
    with pytest.raises(ValueError, match="render.tile_size must be in .1, 32. .got 64."):
        _run("cpu", leaves, p, cam, 64)


def test_a_lock_left_by_a_killed_build_is_cleared_not_waited_on_forever(tmp_path, capsys):
    """torch's builder waits with no time limit while build_dir/lock exists; a build killed
    midway leaves it behind. Old locks are removed with a warning, young ones announced and kept."""
    import os
    import time as _time

    from stdr.extension import clear_stale_lock
    lock = tmp_path / "lock"
    assert not clear_stale_lock(tmp_path)  # no lock: nothing to do
    lock.touch()
    assert not clear_stale_lock(tmp_path, max_age=600) and lock.exists()  # maybe a build running now
    assert "waiting for another process's build" in capsys.readouterr().err
    old = _time.time() - 3600
    os.utime(lock, (old, old))
    with pytest.warns(RuntimeWarning, match="did not finish"):
        assert clear_stale_lock(tmp_path, max_age=600)
    assert not lock.exists()


def test_a_built_module_loads_without_the_build_tool_and_an_unfinished_one_goes_to_it(tmp_path):
    """A process that finds another ninja first on PATH (the system's, not the venv's: their logs
    differ, so that ninja would rebuild it) still loads the cached module: the build tool is not
    run while a finished module is there. A module whose build did not finish (it has no stamp of
    the file a load imported) goes to the build tool instead of being imported."""
    import os
    import sys

    built = Path(extension.load_extension("cpu").__file__).parent
    cache = tmp_path / "ext"
    shutil.copytree(built, cache / built.name)
    (cache / built.name / "lock").unlink(missing_ok=True)
    bindir = tmp_path / "bin"
    bindir.mkdir()
    calls = tmp_path / "ninja_calls"
    (bindir / "ninja").write_text(f'#!/bin/sh\n[ "$1" = --version ] && echo 1.11.1 && exit 0\necho "$@" >> {calls}\nexit 1\n')
    (bindir / "ninja").chmod(0o755)
    env = {**os.environ, "STDR_EXT_DIR": str(cache), "PATH": f"{bindir}{os.pathsep}{os.environ['PATH']}"}
    code = ("import warnings; warnings.simplefilter('always'); from stdr import extension as e\n"
            "try:\n    m = e.load_extension('cpu'); print('loaded', m.__file__)\n"
            "except e.BuildError as x:\n    print('build error', x)\n")
    run = lambda: subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)  # noqa: E731
    first = run()
    assert f"loaded {cache / built.name / built.name}.so" in first.stdout, first.stdout + first.stderr
    assert not calls.exists()  # the build tool was never asked
    so = cache / built.name / f"{built.name}.so"
    so.write_bytes(so.read_bytes()[:4096])  # a link killed midway: importing it would kill the process
    second = run()
    assert second.returncode == 0 and "build error" in second.stdout, second.stdout + second.stderr
    assert calls.is_file()  # not imported: the (here failing) build tool was asked


# ---------------------------------------------------------------- projection and SH (csrc/project_math.h)

def _project_outputs_and_grads(fn, inputs, device, seed=3):
    """Outputs (means2d, depths, conics, opacities, colours), radii and the gradients of a
    random linear function of every output for (means, quats, scales, opacities, sh)."""
    xs = [x.detach().to(device).requires_grad_(True) for x in inputs]
    p, colors = fn(*xs)
    outs = [p.means2d, p.depths, p.conics, p.opacities, colors]
    g = torch.Generator().manual_seed(seed)
    loss = sum((o * torch.randn(o.shape, generator=g, dtype=torch.float64).to(o)).sum() for o in outs)
    grads = torch.autograd.grad(loss, xs)
    return [o.detach().cpu() for o in outs], p.radii.cpu(), [gr.cpu() for gr in grads]


def _projection_scene(dtype):
    """Random Gaussians (some outside the view, so the Jacobian clamp is active), unnormalized
    quaternions, SH of degree 3 with some colours below zero (clamped), plus the hard cases:
    behind the camera, off-screen, very thin, very large."""
    means, quats, scales, opac, _ = random_gaussians(1500, seed=11, dtype=dtype, spread=1.6)
    hm, hq, hs, ho, _ = hard_case_scene(dtype)
    hq = hq + 0.3 * torch.randn(hq.shape, generator=torch.Generator().manual_seed(2), dtype=dtype)
    means, quats = torch.cat([means, hm]), torch.cat([quats * 3.0, hq])
    scales, opac = torch.cat([scales, hs]), torch.cat([opac, ho])
    sh = torch.randn(means.shape[0], 16, 3, generator=torch.Generator().manual_seed(12), dtype=dtype) * 0.5
    return [means, quats, scales, opac, sh], look_at_camera((3.0, 0.0, 0.0), width=61, height=45, dtype=dtype)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("antialiased", [False, True])
def test_projection_and_sh_match_the_torch_twin(backend, dtype, antialiased):
    """Every output and every input gradient of the compiled projection + SH equals the torch
    twin's, for SH degrees 0-3, with the hard cases included. In float64: to 1e-10 relative to the
    largest value, radii equal. In float32 both are measured against the truth (the twin in
    float64 on the same inputs): the compiled error must stay within 1e-5 (outputs) / 1e-4
    (gradients) of the largest value, or within 4x the float32 twin's own error where float32
    cannot do better (the quaternion gradient of the hard cases: the twin itself is ~8e-5 off;
    CUDA's fast-math kernels measured 1.4e-4 from the twin on an H100). A ceil() may land on the
    other integer for a value within rounding of one (radii: at most 1 px, on at most 0.5 % of
    rows)."""
    if backend == "cuda" and dtype == torch.float64:
        pytest.skip("the CUDA backend takes float32 only")
    device = "cuda" if backend == "cuda" else "cpu"
    inputs, cam = _projection_scene(dtype)
    # the scene exercises what it claims: rows behind the camera, off-screen, and clamped
    p = project_gaussians(*inputs[:4], cam)
    xc = inputs[0] @ cam.R.T + cam.t
    assert bool((xc[:, 2] < 0.01).any()) and bool((p.radii == 0).any()) and bool((p.radii > 0).any())
    assert bool((xc[:, 0] / xc[:, 2]).abs().max() > 1.3 * 0.5 * cam.width / cam.fx)
    f_tol, g_tol = (1e-10, 1e-10) if dtype == torch.float64 else (1e-5, 1e-4)
    names = ("means2d", "depths", "conics", "opacities", "colours")
    gnames = ("means", "quats", "scales", "opacities", "sh")
    err = lambda a, b: ((a.double() - b.double()).abs().max() / b.double().abs().max().clamp_min(1e-12)).item()  # noqa: E731
    truth_cam = _projection_scene(torch.float64)[1]  # the same camera values in float64
    for degree in range(4):
        ref_o, ref_r, ref_g = _project_outputs_and_grads(
            lambda *a, degree=degree: project_and_shade(*a, cam, degree, antialiased=antialiased), inputs, "cpu")
        out_o, out_r, out_g = _project_outputs_and_grads(
            lambda *a, degree=degree: compiled.project_sh_compiled(*a, cam, degree, antialiased=antialiased, kind=backend),
            inputs, device)
        if dtype == torch.float64:
            bars = [(f_tol, o) for o in ref_o] + [(g_tol, g) for g in ref_g]
            truth = ref_o + ref_g
        else:
            t_o, _, t_g = _project_outputs_and_grads(
                lambda *a, degree=degree: project_and_shade(*a, truth_cam, degree, antialiased=antialiased),
                [x.double() for x in inputs], "cpu")
            truth = t_o + t_g
            bars = [(max(tol, 4 * err(r, t)), r) for tol, r, t in
                    zip([f_tol] * 5 + [g_tol] * 5, ref_o + ref_g, truth)]
        for name, a, b, (bar, _) in zip(names + gnames, out_o + out_g, truth, bars):
            e = err(a, b)
            assert e <= bar, (degree, name, e, bar)
        diff = out_r != ref_r
        if dtype == torch.float64:
            assert not bool(diff.any()), degree
        else:
            assert (out_r - ref_r).abs().max() <= 1 and diff.float().mean() <= 0.005, degree


@pytest.mark.skipif("cuda" not in BACKENDS, reason="no CUDA device on this machine (torch.cuda.is_available() is False)")
@pytest.mark.parametrize("n", [200_000, 1_000_000])
@pytest.mark.parametrize("antialiased", [False, True])
def test_cuda_projection_matches_the_cpu_extension_at_scale(n, antialiased):
    """The CUDA projection + SH kernels (one thread per Gaussian, many blocks) against the CPU
    extension, which runs the same header (project_math.h), at training and beyond-training
    counts with SH degree 3 at 800 px: every output and every input gradient within 1e-5 / 1e-4
    of the CPU's norm, radii differing by at most 1 px on at most 0.5 % of rows (fast-math ceil),
    everything finite. The torch-twin test above covers the edge cases at 1.5k rows."""
    from stdr.tools.bench_rasterizer import make_scene

    (means, quats, scales, opac, _), cam = make_scene(n, 800, coverage=5.0, seed=n)
    sh = torch.randn(n, 16, 3, generator=torch.Generator().manual_seed(1)) * 0.3
    inputs = [means, quats, scales, opac, sh]
    fn = lambda kind: (lambda *a: compiled.project_sh_compiled(*a, cam, 3, antialiased=antialiased, kind=kind))  # noqa: E731
    cpu_o, cpu_r, cpu_g = _project_outputs_and_grads(fn("cpu"), inputs, "cpu")
    gpu_o, gpu_r, gpu_g = _project_outputs_and_grads(fn("cuda"), inputs, "cuda")
    assert (cpu_r > 0).float().mean() > 0.5  # most rows are visible: the kernels did real work
    rel = lambda a, b: ((a - b).norm() / b.norm().clamp_min(1e-30)).item()  # noqa: E731
    same = (gpu_r == cpu_r) & (cpu_r > 0)  # rows whose visibility both backends agree on
    for name, a, b in zip(("means2d", "depths", "conics", "opacities", "colours"), gpu_o, cpu_o):
        assert torch.isfinite(a).all(), name
        assert rel(a[same], b[same]) <= 1e-5, (name, rel(a[same], b[same]))
    for name, a, b in zip(("means", "quats", "scales", "opacities", "sh"), gpu_g, cpu_g):
        assert torch.isfinite(a).all(), name
        assert rel(a[same], b[same]) <= 1e-4, (name, rel(a[same], b[same]))
    diff = gpu_r != cpu_r
    assert (gpu_r - cpu_r).abs().max() <= 1 and diff.float().mean() <= 0.005, diff.float().mean()


def test_projection_backward_is_deterministic_and_render_uses_it():
    """Two backward passes give identical gradients; render() on a compiled backend runs the
    compiled projection (its grad_fn) unless render.compiled_projection is false."""
    inputs, cam = _projection_scene(torch.float32)
    a = _project_outputs_and_grads(lambda *x: compiled.project_sh_compiled(*x, cam, 3), inputs, "cpu")[2]
    b = _project_outputs_and_grads(lambda *x: compiled.project_sh_compiled(*x, cam, 3), inputs, "cpu")[2]
    assert all(torch.equal(x, y) for x, y in zip(a, b))
    xs = [x.clone().requires_grad_(True) for x in inputs]
    on = render(*xs, cam, sh_degree=3, backend="cpu")
    off = render(*xs, cam, sh_degree=3, backend="cpu", compiled_projection=False)
    assert type(on.projection.conics.grad_fn).__name__.startswith("_ProjectSH")
    assert not type(off.projection.conics.grad_fn).__name__.startswith("_ProjectSH")
    assert (on.image - off.image).abs().max() <= 1e-5


def test_compiled_projection_is_a_default_only_where_verified(monkeypatch):
    """render.compiled_projection=null (auto): the compiled projection on the backends listed as
    verified on real hardware (the CPU; CUDA after its H100 check), the torch twin on any other;
    true or false overrides either; the reference backend never uses it."""
    from stdr.render import use_compiled_projection
    assert use_compiled_projection("cpu") and use_compiled_projection("cuda")
    monkeypatch.setitem(VERIFIED, "render.compiled_projection", ("cpu",))  # a backend not yet verified: off by default
    assert use_compiled_projection("cpu") and not use_compiled_projection("cuda")
    assert use_compiled_projection("cuda", True) and not use_compiled_projection("cpu", False)
    assert not use_compiled_projection("reference", True)
    from stdr.testing import make_cfg
    assert make_cfg([]).render.compiled_projection is None


def test_projection_rejects_bad_inputs_with_the_key():
    inputs, cam = _projection_scene(torch.float32)
    means, quats, scales, opac, sh = inputs
    with pytest.raises(ValueError, match=r"sh must be \[N, K, 3\] .* 16 <= K <= 16 for SH degree 3, got \[.*, 4, 3\]"):
        compiled.project_sh_compiled(means, quats, scales, opac, sh[:, :4], cam, 3)
    with pytest.raises(ValueError, match="SH degree must be in"):
        compiled.project_sh_compiled(means, quats, scales, opac, sh, cam, 4)
    with pytest.raises(ValueError, match="scales is torch.float64"):
        compiled.project_sh_compiled(means, quats, scales.double(), opac, sh, cam, 3)
    with pytest.raises(ValueError, match="means is on cpu; every input must be on the GPU"):
        compiled.project_sh_compiled(means, quats, scales, opac, sh, cam, 3, kind="cuda")
