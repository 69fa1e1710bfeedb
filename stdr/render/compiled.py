"""Compiled rasterizer backends: C++ (CPU, vectorized, multi-threaded) and CUDA, with the
projection and SH shading (`project_sh_compiled`, math in `csrc/project_math.h`).

Both are built just in time on first use with `torch.utils.cpp_extension` into a cache keyed by
the sources, flags, torch version and CPU, or ahead of time with `stdr-build`. The CUDA backend is
built only when torch has CUDA. They share one math header (`csrc/raster_math.h`) and the
semantics of `reference.py`, which the tests pin them to.

The extension sorts the visible Gaussians by depth (a stable radix sort), packs one row per
visible Gaussian, [mx, my, a, b, c, o, f_0..f_{F-1}], bins Gaussian-tile pairs with an exact
ellipse/tile test, composites, and in the backward scatters gradients straight back to the
2D means (densification reads them), conics, opacities and features.
"""
from __future__ import annotations

import hashlib
import os
import platform
import sys
import threading
import time
import warnings
from pathlib import Path
from typing import Optional

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from ..verified import verified_on

CSRC = Path(__file__).resolve().parent / "csrc"
CPU_SOURCES = [CSRC / "cpu" / "raster_cpu.cpp"]
CUDA_SOURCES = [CSRC / "cuda" / "raster_cuda.cpp", CSRC / "cuda" / "raster_kernels.cu"]
HEADERS = [CSRC / "hd.h", CSRC / "raster_math.h", CSRC / "project_math.h", CSRC / "hexplane_math.h", CSRC / "loss_math.h",
           CSRC / "cpu" / "raster_simd.h",
           CSRC / "cpu" / "loss_cpu.h",
           CSRC / "cuda" / "raster_kernels.h"]
PORTABLE_ENV = "STDR_PORTABLE_BUILD"  # =1: no -march=native (e.g. a cache shared by machines)

_lock = threading.Lock()
_modules: dict[str, object] = {}
_errors: dict[str, str] = {}


class BuildError(RuntimeError):
    pass


def cache_root() -> Path:
    """Where compiled extensions live: $STDR_EXT_DIR, else the user cache's extensions folder
    (~/.cache/stdr/extensions; $XDG_CACHE_HOME moves it)."""
    from .. import user_cache
    env = os.environ.get("STDR_EXT_DIR")
    return Path(env) if env else user_cache() / "extensions"


def _cpu_id() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("flags"):
                return line
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _cpu_flags(native: bool) -> list[str]:
    # -fopenmp: ATen's parallel_for is inline OpenMP code, serial without it. The extension then
    # needs libgomp.so.1, which resolves to the copy torch has already loaded (same soname), so
    # torch and the rasterizer share one thread pool.
    flags = ["-O3", "-fopenmp", "-std=c++17"]
    if native:
        flags += ["-march=native", "-mprefer-vector-width=512"]
    return flags + os.environ.get("STDR_EXTRA_CFLAGS", "").split()


def _key(kind: str, sources: list[Path], flags: list[str]) -> str:
    h = hashlib.sha1()
    # torch's JIT loader rebuilds when a build directory was last built from sources at other
    # paths, so each checkout gets its own entry (no rebuild ping-pong between clones)
    h.update(str(CSRC).encode())
    for p in sources + HEADERS:
        if p.exists():
            h.update(p.read_bytes())
    h.update(" ".join(flags).encode())
    h.update(torch.__version__.encode())
    h.update(str(torch.version.cuda).encode())
    h.update(_cpu_id().encode())
    h.update(sys.version.encode())
    return f"stdr_raster_{kind}_{h.hexdigest()[:12]}"


STALE_LOCK_SECONDS = 900  # a build takes ~15-60 s on the CPU, a few minutes with nvcc


def clear_stale_lock(build_dir: Path, max_age: float = STALE_LOCK_SECONDS) -> bool:
    """torch's extension builder holds `build_dir/lock` while it compiles, and every other
    process waits for it to disappear, with no time limit. A build killed midway (Ctrl-C during
    the first run) leaves the file behind, and every later run would hang silently. A lock older
    than `max_age` seconds is removed with a warning; a younger one is announced (another
    process may be building right now). Returns True when a stale lock was removed."""
    lock = build_dir / "lock"
    try:
        age = time.time() - lock.stat().st_mtime
    except FileNotFoundError:
        return False
    if age > max_age:
        warnings.warn(f"removing {lock}: left {age / 60:.0f} min ago by a build that did not finish "
                      "(killed?); building again", RuntimeWarning, stacklevel=2)
        lock.unlink(missing_ok=True)
        return True
    print(f"[stdr] waiting for another process's build of the rasterizer ({lock}, {age:.0f} s old); if no "
          "build is running, delete that file", file=sys.stderr, flush=True)
    return False


def _compile(kind: str, verbose: bool = False):
    import shutil

    from torch.utils import cpp_extension

    # the `ninja` pip package installs next to the interpreter, which may not be on PATH
    bindir = str(Path(sys.executable).parent)
    if shutil.which("ninja") is None and (Path(bindir) / "ninja").exists():
        os.environ["PATH"] = bindir + os.pathsep + os.environ.get("PATH", "")

    native = os.environ.get(PORTABLE_ENV, "0") != "1" and platform.machine() in ("x86_64", "AMD64")
    attempts = [native, False] if native else [False]
    last_err: Optional[BaseException] = None
    for use_native in attempts:
        cflags = _cpu_flags(use_native)
        if kind == "cpu":
            sources, extra = CPU_SOURCES, {}
        else:
            sources = CUDA_SOURCES
            extra = {"extra_cuda_cflags": ["-O3", "--use_fast_math", "-std=c++17"],
                     "with_cuda": True}
        name = _key(kind, sources, cflags + extra.get("extra_cuda_cflags", []))
        build_dir = cache_root() / name
        build_dir.mkdir(parents=True, exist_ok=True)
        clear_stale_lock(build_dir)
        cached = any(build_dir.glob(f"{name}*.so"))
        if not cached:
            print(f"[stdr] compiling the {kind.upper()} rasterizer into {build_dir} "
                  f"(first use only; ~20-60 s)...", file=sys.stderr, flush=True)
        t0 = time.perf_counter()
        try:
            mod = cpp_extension.load(name=name, sources=[str(s) for s in sources],
                                     extra_cflags=cflags, extra_ldflags=["-fopenmp"],
                                     build_directory=str(build_dir),
                                     verbose=verbose, **extra)
        except Exception as e:  # compiler missing, unsupported flag, ...
            last_err = e
            continue
        if not cached:
            print(f"[stdr] {kind.upper()} rasterizer built in {time.perf_counter() - t0:.0f} s",
                  file=sys.stderr, flush=True)
        return mod
    raise BuildError(f"could not build the {kind} rasterizer: {last_err}")


def load_extension(kind: str, verbose: bool = False):
    """The compiled module for `kind` ('cpu' or 'cuda'), building it if needed (cached)."""
    if kind not in ("cpu", "cuda"):
        raise ValueError(f"unknown compiled backend {kind!r}")
    with _lock:
        if kind in _modules:
            return _modules[kind]
        if kind in _errors:
            raise BuildError(_errors[kind])
        if kind == "cuda" and not (torch.cuda.is_available() and torch.version.cuda):
            _errors[kind] = "torch has no CUDA here; the CUDA rasterizer is not built"
            raise BuildError(_errors[kind])
        try:
            _modules[kind] = _compile(kind, verbose=verbose)
        except BuildError as e:
            _errors[kind] = str(e)
            raise
        return _modules[kind]


def available(kind: str) -> bool:
    try:
        load_extension(kind)
        return True
    except BuildError:
        return False


def build_error(kind: str) -> Optional[str]:
    return _errors.get(kind)


def use_compiled(key: str, setting: Optional[bool], kind: str, supported: bool = True,
                 unsupported: str = "") -> bool:
    """A `<key>: null | true | false` switch between a compiled kernel on `kind` ('cpu', 'cuda')
    and its torch twin: false = the twin; null = the kernel where it has been verified (`kind` in
    stdr.verified.VERIFIED[key]), the inputs are `supported` and the extension builds; true = the
    kernel, or an error that names the key and says why not (`unsupported`: what the kernel does
    not take)."""
    if setting is False:
        return False
    if setting is None:
        return supported and kind in verified_on(key) and available(kind)
    if not supported:
        raise ValueError(f"{key}=true: {unsupported}; set {key}=null (or false) to use the torch ops")
    if not available(kind):
        raise RuntimeError(f"{key}=true, but the {kind} extension could not be built: {build_error(kind)}; "
                           f"set {key}=null (or false)")
    return True


class _Rasterize(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, opacities, features, depths, radii, width, height, tile, ext):
        acc, T, last, ids, offsets, packed, order = ext.forward(
            means2d.detach(), conics.detach(), opacities.detach(), features.detach(),
            depths.detach(), radii, width, height, tile)
        ctx.save_for_backward(packed, order, ids, offsets, T, last)
        ctx.meta = (means2d.shape[0], width, height, tile, ext)
        return acc, T

    @staticmethod
    @once_differentiable
    def backward(ctx, g_acc: Optional[Tensor], g_T: Optional[Tensor]):
        packed, order, ids, offsets, T, last = ctx.saved_tensors
        n, width, height, tile, ext = ctx.meta
        if g_acc is None:
            g_acc = torch.zeros(height, width, packed.shape[1] - 6, dtype=packed.dtype,
                                device=packed.device)
        if g_T is None:
            g_T = torch.zeros_like(T)
        g_m, g_c, g_o, g_f = ext.backward(packed, order, n, ids, offsets, T, last,
                                          g_acc.contiguous(), g_T.contiguous(), width, height,
                                          tile)
        return g_m, g_c, g_o, g_f, None, None, None, None, None, None


MAX_CHANNELS = 8  # stdr::MAX_CHANNELS in csrc/raster_math.h (a test keeps the two equal)
TILE_SIZES = {"cpu": tuple(range(1, 33)), "cuda": (8, 16)}  # CUDA: whole warps, shared memory


def check_inputs(means2d: Tensor, conics: Tensor, opacities: Tensor, features: Tensor,
                 depths: Tensor, radii: Tensor, width: int, height: int, tile_size: int,
                 kind: str) -> None:
    """The compiled backends' input contract, checked in Python before any C++ runs.

    The extensions check again, with literal messages only: on one CUDA image (torch
    2.11.0+cu130, g++ 13.3) any torch extension that throws a TORCH_CHECK with formatted
    arguments crashed the process instead of raising (docs/notes/2026-11-24-rasterizer-measurements.md, "GPU check"). The CUDA
    kernels also read every row by index, so a short tensor here would be an out-of-bounds read
    on the GPU rather than an error.
    """
    if kind not in TILE_SIZES:
        raise ValueError(f"unknown compiled backend {kind!r}")
    n = means2d.shape[0] if means2d.dim() >= 1 else -1
    shapes = {"means2d": (means2d, (n, 2)), "conics": (conics, (n, 3)), "opacities": (opacities, (n,)),
              "depths": (depths, (n,)), "radii": (radii, (n,))}
    for name, (t, want) in shapes.items():
        if tuple(t.shape) != want:
            raise ValueError(f"stdr rasterizer: {name} must be {list(want)} for N={n} Gaussians, got "
                             f"{list(t.shape)}")
    if features.dim() != 2 or features.shape[0] != n:
        raise ValueError(f"stdr rasterizer: features must be [N, F] with N={n}, got {list(features.shape)}")
    if not 1 <= features.shape[1] <= MAX_CHANNELS:
        raise ValueError(f"stdr rasterizer: the compiled backends take 1..{MAX_CHANNELS} feature channels "
                         f"(got {features.shape[1]}); use render.backend=reference")
    floats = {"conics": conics, "opacities": opacities, "features": features, "depths": depths}
    for name, t in floats.items():
        if t.dtype != means2d.dtype:
            raise ValueError(f"stdr rasterizer: all float inputs must share one dtype ({name} is {t.dtype}, "
                             f"means2d {means2d.dtype})")
    if means2d.dtype not in ((torch.float32,) if kind == "cuda" else (torch.float32, torch.float64)):
        raise ValueError(f"stdr {kind} rasterizer: float inputs must be "
                         f"{'float32' if kind == 'cuda' else 'float32 or float64'}, got {means2d.dtype}")
    if width <= 0 or height <= 0:
        raise ValueError(f"stdr rasterizer: empty image ({width}x{height})")
    if tile_size not in TILE_SIZES[kind]:
        allowed = "8 or 16" if kind == "cuda" else "in [1, 32]"
        raise ValueError(f"stdr {kind} rasterizer: render.tile_size must be {allowed} (got {tile_size})")
    want_dev = "cuda" if kind == "cuda" else "cpu"
    for name, t in {"means2d": means2d, **floats, "radii": radii}.items():
        if t.device.type != want_dev:
            raise ValueError(f"stdr {kind} rasterizer: {name} is on {t.device}; every input must be on "
                             f"the {want_dev.upper()} (render.backend={kind} renders {want_dev} tensors)")
    if len({t.device for t in (means2d, conics, opacities, features, depths, radii)}) > 1:
        raise ValueError("stdr rasterizer: inputs are on different devices")


def rasterize_compiled(means2d: Tensor, conics: Tensor, opacities: Tensor, features: Tensor,
                       depths: Tensor, radii: Tensor, width: int, height: int,
                       tile_size: int = 16, kind: str = "cpu") -> tuple[Tensor, Tensor]:
    """Same contract as `rasterize_reference`.

    means2d [N, 2], conics [N, 3], opacities [N], features [N, F], depths [N], radii [N].
    Returns (feature image [H, W, F] without background, transmittance [H, W]).
    """
    check_inputs(means2d, conics, opacities, features, depths, radii, int(width), int(height),
                 int(tile_size), kind)
    ext = load_extension(kind)
    return _Rasterize.apply(means2d, conics, opacities, features, depths,
                            radii.to(torch.int32).contiguous(), int(width), int(height),
                            int(tile_size), ext)


def contribution_compiled(means2d: Tensor, conics: Tensor, opacities: Tensor, depths: Tensor, radii: Tensor,
                          width: int, height: int, tile_size: int = 16, kind: str = "cpu") -> Tensor:
    """The score pass [N]: each Gaussian's blending weight alpha * T summed over the image, from
    the extension's forward compositing (same contract and values as `contribution_reference`;
    no autograd). CPU: deterministic, the same on any thread count; CUDA: atomic adds, so the last bits of a
    sum may vary from run to run."""
    n = means2d.shape[0] if means2d.dim() >= 1 else -1
    ones = means2d.new_ones(max(n, 0), 1)
    check_inputs(means2d, conics, opacities, ones, depths, radii, int(width), int(height), int(tile_size), kind)
    ext = load_extension(kind)
    with torch.no_grad():
        return ext.score(means2d.detach(), conics.detach(), opacities.detach(), depths.detach(),
                         radii.to(torch.int32).contiguous(), int(width), int(height), int(tile_size))


def bin_pairs_split(packed: Tensor, emit: Tensor, vradii: Tensor, width: int, height: int, tile_size: int = 16,
                    kind: str = "cpu") -> tuple[Tensor, Tensor]:
    """The CUDA backend's two-pass Gaussian-tile binning (count each packed row's tiles, scan,
    write the keys, sort) with the count pass reading `packed` and the write pass `emit`, on the
    CUDA kernels (kind='cuda') or the same shared function on the CPU (kind='cpu'). Rendering always
    passes one array twice; tests pass two to make the passes disagree, as two differently
    rounded compilations of one float test can. Returns (pair_ids [P] int32, tile_offsets
    [n_tiles + 1] int64): tile t's list is pair_ids[tile_offsets[t]:tile_offsets[t + 1]]; ids past
    tile_offsets[-1] fill slots the write pass did not reach and are in no list.

    packed, emit [V, 6 + F] (rows as the forward packs them, depth order), vradii [V] int32."""
    return tuple(load_extension(kind).bin_pairs_split(packed, emit, vradii.to(torch.int32), int(width), int(height),
                                                      int(tile_size)))


# ---------------------------------------------------------------- projection and SH shading

def camera_values(camera) -> list[float]:
    """The first 23 of the 26 camera numbers `csrc/project_math.h` (make_proj_cam) reads: R
    (row-major), t, the centre, fx, fy, cx, cy and the Jacobian clamp limits
    (`projection.frustum_limits`); the caller appends near, far and eps2d.

    One host copy per camera: the values are kept on the camera object, keyed by its pose
    tensors and their versions (an in-place change of R or t recomputes them), so a training
    step on a dataset camera, which is on the device, does not wait for the device here."""
    from .projection import frustum_limits
    key = (id(camera.R), camera.R._version, id(camera.t), camera.t._version,
           float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy), camera.width, camera.height)
    hit = getattr(camera, "__dict__", {}).get("_host_values")
    if hit is not None and hit[0] == key:
        return list(hit[1])
    pose = torch.cat([camera.R.detach().reshape(-1), camera.t.detach().reshape(-1), camera.center.detach()])
    values = pose.double().cpu().tolist() + [float(camera.fx), float(camera.fy), float(camera.cx),
                                             float(camera.cy), *frustum_limits(camera)]
    if hasattr(camera, "__dict__"):
        camera.__dict__["_host_values"] = (key, tuple(values), camera.R, camera.t)  # (R, t kept: ids stay unique)
    return values


class _ProjectSH(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, opacities, sh, cam, width, height, antialiased, degree, ext):
        ins = [x.detach().contiguous() for x in (means, quats, scales, opacities, sh)]
        means2d, depths, conics, opac, radii, colors = ext.project_forward(*ins, cam, width, height, antialiased,
                                                                           degree)
        ctx.save_for_backward(*ins)
        ctx.meta = (cam, width, height, antialiased, degree, ext)
        ctx.mark_non_differentiable(radii)
        return means2d, depths, conics, opac, radii, colors

    @staticmethod
    @once_differentiable
    def backward(ctx, g_m2d, g_depth, g_conic, g_opac, g_radii, g_color):
        ins = ctx.saved_tensors
        cam, width, height, antialiased, degree, ext = ctx.meta
        m = ins[0]
        n = m.shape[0]
        grads = []
        for g, shape in ((g_m2d, (n, 2)), (g_depth, (n,)), (g_conic, (n, 3)), (g_opac, (n,)), (g_color, (n, 3))):
            grads.append(m.new_zeros(shape) if g is None else g.to(m.dtype).contiguous())
        gm, gq, gs, go, gh = ext.project_backward(*ins, *grads, cam, width, height, antialiased, degree)
        return gm, gq, gs, go, gh, None, None, None, None, None, None


def project_sh_compiled(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, sh: Tensor, camera,
                        sh_degree: int, near: float = 0.01, far: float = 1e10, eps2d: float = 0.3,
                        antialiased: bool = False, kind: str = "cpu"):
    """`project_gaussians` and `eval_sh` (view direction from the camera centre) in one compiled
    pass, forward and backward: (Projection, colours [N, 3]). The same contract and values as
    the torch twin (stdr/render/projection.py, sh.py; the parity tests in tests/test_compiled.py).

    means [N, 3], quats [N, 4], scales [N, 3] (activated), opacities [N] (activated),
    sh [N, K, 3] with (sh_degree + 1)^2 <= K <= 16."""
    from .projection import Projection
    n = means.shape[0]
    if not 0 <= sh_degree <= 3:
        raise ValueError(f"SH degree must be in [0, 3], got {sh_degree}")
    if sh.dim() != 3 or sh.shape[0] != n or sh.shape[2] != 3 or not (sh_degree + 1) ** 2 <= sh.shape[1] <= 16:
        raise ValueError(f"stdr projection: sh must be [N, K, 3] with N={n} and {(sh_degree + 1) ** 2} <= K <= 16 "
                         f"for SH degree {sh_degree}, got {list(sh.shape)}")
    want = (torch.float32,) if kind == "cuda" else (torch.float32, torch.float64)
    tensors = {"means": means, "quats": quats, "scales": scales, "opacities": opacities, "sh": sh}
    for name, t in tensors.items():
        if t.dtype != means.dtype or t.dtype not in want:
            raise ValueError(f"stdr {kind} projection: {name} is {t.dtype}; every input must be one of {want}")
        if t.device != means.device or t.device.type != ("cuda" if kind == "cuda" else "cpu"):
            raise ValueError(f"stdr {kind} projection: {name} is on {t.device}; every input must be on the "
                             f"{'GPU' if kind == 'cuda' else 'CPU'}")
    ext = load_extension(kind)
    cam = camera_values(camera) + [float(near), float(far), float(eps2d)]
    means2d, depths, conics, opac, radii, colors = _ProjectSH.apply(
        means, quats, scales, opacities, sh, cam, int(camera.width), int(camera.height), bool(antialiased),
        int(sh_degree), ext)
    return Projection(means2d=means2d, depths=depths, conics=conics, opacities=opac, radii=radii), colors


# the dtypes each HexPlane kernel takes (the CUDA one is float32 only)
HEXPLANE_DTYPES = {"cpu": (torch.float32, torch.float64), "cuda": (torch.float32,)}


class _HexPlane(torch.autograd.Function):
    @staticmethod
    def forward(ctx, coords, ext, *planes):
        feats, others = ext.hexplane_forward(coords, list(planes))
        ctx.save_for_backward(coords, others, *planes)
        ctx.ext = ext
        return feats

    @staticmethod
    @once_differentiable
    def backward(ctx, g):
        coords, others, *planes = ctx.saved_tensors
        grads = ctx.ext.hexplane_backward(coords, list(planes), others, g.to(coords.dtype).contiguous())
        return (None, None, *grads)


def hexplane_compiled(coords: Tensor, planes: list[Tensor], kind: str = "cpu") -> Tensor:
    """A HexPlane field's features in one compiled pass, forward and backward (the planes'
    gradients; the coordinates get none): [N, M*C] = for each scale m (6 planes each, in the
    order of `stdr.deform.hexplane.PAIRS`), the product over its planes of the bilinear samples
    at the coordinate pairs, zero outside the planes (grid_sample, align_corners=True). The
    torch twin is `stdr.deform.hexplane.HexPlaneField.features_torch`; tests/test_compiled.py
    pins the two together. The CPU backward is deterministic; the CUDA one adds atomically.

    coords [N, 4] in [-1, 1] (x, y, z, t), planes 6*M tensors [C, H, W] (one C)."""
    want = HEXPLANE_DTYPES["cuda" if kind == "cuda" else "cpu"]
    if coords.dim() != 2 or coords.shape[1] != 4:
        raise ValueError(f"stdr hexplane: coords must be [N, 4], got {list(coords.shape)}")
    if not planes or len(planes) % 6 or len(planes) > 48:
        raise ValueError(f"stdr hexplane: planes must be 6 per scale (at most 8 scales), got {len(planes)}")
    dev = "cuda" if kind == "cuda" else "cpu"
    for i, t in enumerate([coords, *planes]):
        name = "coords" if i == 0 else f"plane {i - 1}"
        if t.dtype != coords.dtype or t.dtype not in want:
            raise ValueError(f"stdr {kind} hexplane: {name} is {t.dtype}; every input must be one of {want}")
        if t.device.type != dev or t.device != coords.device:
            raise ValueError(f"stdr {kind} hexplane: {name} is on {t.device}; every input must be on {coords.device} "
                             f"({dev})")
        if i and (t.dim() != 3 or t.shape[0] != planes[0].shape[0]):
            raise ValueError(f"stdr hexplane: {name} must be [C, H, W] with C={planes[0].shape[0]}, got {list(t.shape)}")
    ext = load_extension(kind)
    return _HexPlane.apply(coords.detach().contiguous(), ext, *[p.contiguous() for p in planes])


# ----------------------------------------------------------------------------- the training loss
class _ImageLoss(torch.autograd.Function):
    @staticmethod
    def forward(ctx, img, gt, lam, window, sigma, ext):
        loss, stats, partials = ext.image_loss_forward(img, gt, lam, window, sigma)
        ctx.save_for_backward(img, gt, partials)
        ctx.args = (lam, window, sigma, ext)
        ctx.mark_non_differentiable(stats)
        return loss, stats

    @staticmethod
    @once_differentiable
    def backward(ctx, g_loss, g_stats):
        img, gt, partials = ctx.saved_tensors
        lam, window, sigma, ext = ctx.args
        return ext.image_loss_backward(g_loss, img, gt, partials, lam, window, sigma), None, None, None, None, None


# the dtypes each loss kernel takes (the CUDA one is float32 only)
LOSS_DTYPES = {"cpu": (torch.float32, torch.float64), "cuda": (torch.float32,)}


def image_loss_compiled(img: Tensor, gt: Tensor, lam: float, window: int = 11,
                        sigma: float = 1.5) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The photometric training loss in one compiled pass: (loss, l1, dssim, psnr), 0-d tensors,
    where loss = (1 - lam) * l1 + lam * dssim and only loss has a gradient (img's). The torch
    twin is `stdr.metrics.image_loss`; tests/test_fused_loss.py pins the two together. The CPU
    kernel is one call each way; the CUDA one three launches forward and two backward, with no
    host sync (the loss gradient is read on the device). Both are deterministic.

    img, gt [H, W, C] on one device (CPU: float32 or float64; CUDA: float32); gt is a target (no
    gradient)."""
    if img.dim() != 3 or img.shape != gt.shape:
        raise ValueError(f"stdr image_loss: img and gt must be [H, W, C] of one shape, got {list(img.shape)} and "
                         f"{list(gt.shape)}")
    kind = img.device.type
    want = LOSS_DTYPES.get(kind, ())
    for name, t in (("img", img), ("gt", gt)):
        if t.device != img.device or t.dtype not in want or t.dtype != img.dtype:
            raise ValueError(f"stdr image_loss: {name} is {t.dtype} on {t.device}; both must be on one device, of one "
                             "dtype: float32 or float64 on the CPU, float32 on CUDA")
    if gt.requires_grad:
        raise ValueError("stdr image_loss: gt needs a gradient; the compiled loss differentiates img only")
    if not 1 <= window <= 31 or window % 2 == 0:
        raise ValueError(f"stdr image_loss: window={window} must be odd, 1..31")
    ext = load_extension(kind)
    loss, stats = _ImageLoss.apply(img.contiguous(), gt.contiguous(), float(lam), int(window), float(sigma), ext)
    return loss, stats[0], stats[1], stats[2]


def nonfinite_flags_compiled(tensors: list[Tensor]) -> Tensor:
    """One bool per CPU tensor: whether it has a NaN or an infinity (the torch form is
    `stdr.train.guard.nonfinite_flags`)."""
    return load_extension("cpu").nonfinite_flags([t.detach() for t in tensors])


def guard_update_compiled(tensors: list[Tensor], flag: Tensor, bad_step: Tensor, bad_index: Tensor, step: int) -> None:
    """The sync-free guard's per-step update in one call, in place (the torch form is in
    `stdr.train.guard.Guard.flag_step`): when a tensor is non-finite, flag = 1 and, if no step was
    recorded yet (bad_step < 0), bad_step = step and bad_index = the first such tensor's index.
    On the flag's device: the CPU (any floating dtype) or CUDA (float32 tensors; a fill and two
    launches, no host sync)."""
    load_extension(flag.device.type).guard_update([t.detach() for t in tensors], flag, bad_step, bad_index, int(step))
