"""The rasterizer family's compiled form (C++ on the CPU, CUDA) and its bindings: the tile
rasterizer with its hand-written backward, the contribution score, the CUDA binning's two passes
(tests), and the projection with SH shading (`project_sh_compiled`, math in
`stdr/csrc/project_math.h`). The torch twins are `reference.py`, `projection.py` and `sh.py`, which
the tests pin these to. The extension itself (sources, build, loading, the verified-device
switch) is `stdr.extension`; its other families are bound beside their own twins (HexPlane:
stdr.baselines.fourdgs, the training loss: stdr.metrics, the guard's check: stdr.train.guard).

The extension sorts the visible Gaussians by depth (a stable radix sort), packs one row per
visible Gaussian, [mx, my, a, b, c, o, f_0..f_{F-1}], bins Gaussian-tile pairs with an exact
ellipse/tile test, composites, and in the backward scatters gradients straight back to the
2D means (densification reads them), conics, opacities and features.
"""
from __future__ import annotations

from typing import Optional

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from ..extension import (BuildError, available, build_error, cache_root, clear_stale_lock,  # noqa: F401
                         load_extension, use_compiled)
from .projection import frustum_limits, Projection


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
    arguments crashed the process instead of raising (research/notes/2026-11-24-rasterizer-measurements.md, "GPU check"). The CUDA
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


def forward_bounded(means2d: Tensor, conics: Tensor, opacities: Tensor, features: Tensor, depths: Tensor,
                    radii: Tensor, width: int, height: int, capacity: int, tile_size: int = 16,
                    kind: str = "cpu") -> dict[str, Tensor]:
    """The capture-safe form of the extension's forward (no autograd): no host sync on CUDA, so that a
    CUDA graph can hold it. Every row is packed (the visible ones first, in the forward's depth order;
    the others after them, radius 0, no tile), and the Gaussian-tile pairs go into a buffer of
    `capacity` keys instead of one sized by reading their count on the host. kind='cpu' runs the
    same steps on the CPU (for the tests: the CPU forward itself has no sync to remove).

    Inputs as `rasterize_compiled`; capacity >= 0. Returns {image [H, W, F], T [H, W], last [H, W]
    int32, pair_ids [capacity] int32, tile_offsets [n_tiles + 1], packed [N, 6 + F], order [N],
    total [] int64 (the pairs the image needed, on the device)}. With total <= capacity the image,
    the tile lists and the backward's inputs are the forward's (pair_ids[:tile_offsets[-1]]); above
    it the deepest rows' pairs are missing and the image is incomplete: read total where the device
    is read anyway, and render again with a larger capacity."""
    check_inputs(means2d, conics, opacities, features, depths, radii, int(width), int(height), int(tile_size), kind)
    if int(capacity) < 0:
        raise ValueError(f"stdr rasterizer: forward_bounded needs capacity >= 0, got {capacity}")
    with torch.no_grad():
        out = load_extension(kind).forward_bounded(
            means2d.detach(), conics.detach(), opacities.detach(), features.detach(), depths.detach(),
            radii.to(torch.int32).contiguous(), int(width), int(height), int(tile_size), int(capacity))
    return dict(zip(("image", "T", "last", "pair_ids", "tile_offsets", "packed", "order", "total"), out))


# ---------------------------------------------------------------- projection and SH shading

def camera_values(camera) -> list[float]:
    """The first 23 of the 26 camera numbers `csrc/project_math.h` (make_proj_cam) reads: R
    (row-major), t, the centre, fx, fy, cx, cy and the Jacobian clamp limits
    (`projection.frustum_limits`); the caller appends near, far and eps2d.

    One host copy per camera: the values are kept on the camera object, keyed by its pose
    tensors and their versions (an in-place change of R or t recomputes them), so a training
    step on a dataset camera, which is on the device, does not wait for the device here."""
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
