"""4DGaussians (Wu et al. 2024): a HexPlane field over (x, y, z, t) and a small decoder.

Six feature planes, one per pair of the four coordinates (xy, xz, xt, yz, yt, zt), at several
spatial resolutions (the time resolution is the same at every scale). A point's feature is the
product over the six bilinear plane samples, concatenated over scales. A decoder maps it to
position, log-scale and raw-quaternion deltas, added *before* activation.

Coordinates: space is mapped to [-1, 1] by bounds taken from the initial points; time t in
[0, 1] is mapped to 2t - 1, so the whole time axis of the planes is used. The published code
feeds raw t in [0, 1] and so uses only half of the time axis (4DGaussians' issue tracker, #251).
"""
from __future__ import annotations

import itertools
from dataclasses import dataclass, field
from typing import List, Optional, Sequence

import numpy as np

import torch
import torch.nn.functional as F
from torch import Tensor, nn
from torch.autograd.function import once_differentiable

from .. import extension
from ..context import StepContext
from .base import BaselineConfig, Deformation, Deltas, apply_pre_activation
from .registry import register_baseline



@dataclass
class HexPlaneConfig:
    """4DGaussians HexPlane field and decoder, `baseline.hexplane.*` (docs/baselines.md)."""

    base_res: int = 64
    multires: List[int] = field(default_factory=lambda: [1, 2])
    channels: int = 32
    time_res: int = 0               # 0: half the number of distinct training times (the published values)
    grid_lr_mult: float = 10.0      # grid lr = 10 x the network lr (1.6e-3 vs 1.6e-4)
    plane_tv: float = 1e-4
    time_smooth: float = 1e-2
    l1_time: float = 1e-4
    # the field's sampling (features forward, planes' gradients backward) as one compiled kernel
    # (hexplane_compiled, below) instead of the torch ops: null = where it has been
    # verified (stdr.verified.VERIFIED: the CPU; the CUDA kernel is built but has not run on a
    # GPU yet), true = required (an error where it cannot be built), false = torch
    compiled: Optional[bool] = None


@dataclass
class HexPlaneBaselineConfig(BaselineConfig):
    """4DGaussians (Wu et al. 2024), `baseline=4dgs`: HexPlane field + decoder, deltas before
    activation. The static warm-up is its coarse stage; the network lr restarts at the fine stage
    (lr_from_warmup). depth: extra ReLU+Linear layers after feature_out (defor_depth). The lrs are
    1.6e-4 x 5: 4DGS scales the network and grid lrs by spatial_lr_scale (optim.spatial_lr_scale
    = 5); the grid gets hexplane.grid_lr_mult x these. Sizes:
    stdr/configs/budget_baseline/4dgs_<budget>.yaml."""

    name: str = "4dgs"
    depth: int = 0
    width: int = 64
    lr_init: float = 8.0e-4
    lr_final: float = 8.0e-6
    lr_from_warmup: bool = True
    hexplane: HexPlaneConfig = field(default_factory=HexPlaneConfig)


def hexplane_time_res(b, train_times: Optional[np.ndarray]) -> int:
    """baseline.hexplane.time_res, or half the number of distinct training times when 0 (the
    published per-scene values are exactly that: bouncingballs 150 frames -> 75, ...)."""
    if b.hexplane.time_res > 0:
        return int(b.hexplane.time_res)
    if train_times is None or len(train_times) == 0:
        raise ValueError("baseline.hexplane.time_res=0 takes half the number of training times, but none were "
                         "given: build the model from a scene with a train split or from a checkpoint that "
                         "holds them (stdr.model.load_model), or set baseline.hexplane.time_res")
    return max(2, len(train_times) // 2)


PAIRS = list(itertools.combinations(range(4), 2))  # (0,1) (0,2) (0,3) (1,2) (1,3) (2,3)
TIME_PLANES = [i for i, p in enumerate(PAIRS) if 3 in p]   # 2, 4, 5
SPACE_PLANES = [i for i, p in enumerate(PAIRS) if 3 not in p]  # 0, 1, 3


def sample_plane(plane: Tensor, uv: Tensor) -> Tensor:
    """Bilinear sample of plane [C, H, W] at uv [N, 2] in [-1, 1] (u along W, v along H;
    -1 and 1 are the centres of the corner cells, zero outside) -> [N, C].

    `F.grid_sample(align_corners=True, padding_mode="zeros")` itself. When uv needs no
    gradient (the HexPlane field samples at detached positions) the backward is one
    `index_add_` of the bilinear corners' weighted gradients into the plane: 4-5x faster than grid_sample's
    backward on the CPU (docs/performance.md), deterministic, and within float rounding of it
    (tests/test_baselines.py pins the two together)."""
    if uv.requires_grad:
        return _grid_sample(plane, uv)
    return _PlaneSample.apply(plane, uv)


def sample_plane_row(plane: Tensor, u: Tensor, v: float) -> Tensor:
    """`sample_plane(plane, uv)` for uv = (u [N], v) with one v for every point (a time plane
    at the frame's time): the two rows around v are blended once into a line [C, W], then each
    point takes two samples of it instead of four of the plane."""
    C, H, W = plane.shape
    if u.requires_grad:
        return _grid_sample(plane, torch.stack([u, torch.full_like(u, v)], -1))
    y = (v + 1) * 0.5 * (H - 1)
    y0 = int(np.floor(y))
    fy = y - y0
    line = plane.new_zeros(C, 1, W)
    for yi, wy in ((y0, 1.0 - fy), (y0 + 1, fy)):
        if 0 <= yi < H:
            line = line + wy * plane[:, yi:yi + 1, :]
    return _PlaneSample.apply(line, torch.stack([u, torch.zeros_like(u)], -1))  # H = 1: any v is row 0


def _grid_sample(plane: Tensor, uv: Tensor) -> Tensor:
    out = F.grid_sample(plane[None], uv[None, :, None, :], mode="bilinear", padding_mode="zeros",
                        align_corners=True)  # [1, C, N, 1]
    return out[0, :, :, 0].T


def _bilinear_corners(uv: Tensor, H: int, W: int) -> tuple[Tensor, Tensor]:
    """(idx [K, N] int64 rows of a [H*W, C] plane, w [K, N]) of the K = 4 bilinear corners of
    uv [N, 2] (K = 2 for a one-row plane, a line); a corner outside the plane gets weight 0
    (and row 0)."""
    x = (uv[:, 0] + 1) * (0.5 * (W - 1))  # [N] pixel coordinates (align_corners)
    y = (uv[:, 1] + 1) * (0.5 * (H - 1))
    x0, y0 = torch.floor(x), torch.floor(y)
    fx, fy = x - x0, y - y0
    x0, y0 = x0.long(), y0.long()
    idx, w = [], []
    corners = ((0, 0, (1 - fx) * (1 - fy)), (0, 1, fx * (1 - fy)), (1, 0, (1 - fx) * fy), (1, 1, fx * fy))
    for dy, dx, wk in corners[:2] if H == 1 else corners:
        xi, yi = x0 + dx, y0 + dy
        ok = (xi >= 0) & (xi < W) & (yi >= 0) & (yi < H)
        idx.append(torch.where(ok, yi * W + xi, torch.zeros_like(xi)))
        w.append(torch.where(ok, wk, torch.zeros_like(wk)))
    return torch.stack(idx), torch.stack(w)


class _PlaneSample(torch.autograd.Function):
    """`_grid_sample(plane, uv)` forward (the same values); backward for the plane only, as one
    deterministic `index_add_` of the bilinear corners' weighted gradients (grid_sample's CPU backward also
    computes the unneeded position gradient and is 4-5x slower)."""

    @staticmethod
    def forward(ctx, plane: Tensor, uv: Tensor) -> Tensor:
        ctx.save_for_backward(uv)
        ctx.shape = tuple(plane.shape)
        return _grid_sample(plane, uv)

    @staticmethod
    def backward(ctx, g: Tensor):
        uv, = ctx.saved_tensors
        C, H, W = ctx.shape
        idx, w = _bilinear_corners(uv, H, W)  # [K, N]
        grad = g.new_zeros(H * W, C)
        grad.index_add_(0, idx.reshape(-1), (g[None] * w[:, :, None]).reshape(-1, C))
        return grad.view(H, W, C).permute(2, 0, 1), None


def second_difference_smoothness(plane: Tensor) -> Tensor:
    """mean over the plane of the squared second difference along its H axis (for a time
    plane, along time). plane [C, H, W]."""
    d1 = plane[:, 1:, :] - plane[:, :-1, :]
    d2 = d1[:, 1:, :] - d1[:, :-1, :]
    return d2.square().mean()


# ----------------------------------------------------------------- the compiled sampling (stdr/csrc/cpu/hexplane_cpu.h)
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
    order of `stdr.baselines.fourdgs.PAIRS`), the product over its planes of the bilinear samples
    at the coordinate pairs, zero outside the planes (grid_sample, align_corners=True). The
    torch twin is `stdr.baselines.fourdgs.HexPlaneField.features_torch`; tests/test_compiled.py
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
    ext = extension.load_extension(kind)
    return _HexPlane.apply(coords.detach().contiguous(), ext, *[p.contiguous() for p in planes])


class HexPlaneField(nn.Module):
    def __init__(self, base_res: int = 64, multires: Sequence[int] = (1, 2), channels: int = 32,
                 time_res: int = 25, compiled: Optional[bool] = None):
        super().__init__()
        self.compiled = compiled
        if time_res < 2:
            raise ValueError(f"HexPlane time resolution must be >= 2, got {time_res}")
        self.channels, self.multires = channels, tuple(multires)
        self.grids = nn.ModuleList()
        for m in self.multires:
            res = [base_res * m] * 3 + [time_res]
            planes = nn.ParameterList()
            for i, j in PAIRS:
                # plane for coordinates (i, j): W along coordinate i, H along coordinate j
                shape = (channels, res[j], res[i])
                p = torch.ones(shape) if j == 3 else torch.empty(shape).uniform_(0.1, 0.5)
                planes.append(nn.Parameter(p))
            self.grids.append(planes)
        self.register_buffer("aabb", torch.tensor([[-1.0] * 3, [1.0] * 3]))  # [2, 3] min, max

    @property
    def feat_dim(self) -> int:
        return self.channels * len(self.multires)

    def set_bounds(self, points: Tensor) -> None:
        lo, hi = points.min(0).values, points.max(0).values
        pad = 1e-6 * (hi - lo).clamp_min(1e-6)
        self.aabb.copy_(torch.stack([lo - pad, hi + pad]))

    def normalize(self, xyz: Tensor, t: float) -> Tensor:
        """[N, 3] world points and a time in [0, 1] -> [N, 4] coordinates in [-1, 1]."""
        lo, hi = self.aabb[0], self.aabb[1]
        x = (xyz - lo) / (hi - lo) * 2.0 - 1.0
        tt = torch.full_like(x[:, :1], 2.0 * float(t) - 1.0)
        return torch.cat([x, tt], -1)

    def compiled_kind(self, c: Tensor) -> Optional[str]:
        """The compiled backend that samples coordinates `c` ('cpu' / 'cuda'), or None for the
        torch ops (baseline.hexplane.compiled; coordinates that need a gradient always take torch)."""
        if self.compiled is False or c.requires_grad:
            return None
        kind = c.device.type
        use = extension.use_compiled("baseline.hexplane.compiled", self.compiled, kind,
                                     c.dtype in HEXPLANE_DTYPES.get(kind, ()),
                                     f"no compiled HexPlane sampling for {c.dtype} on {kind}")
        return kind if use else None

    def forward(self, xyz: Tensor, t: float) -> Tensor:  # [N, 3] -> [N, feat_dim]
        c = self.normalize(xyz, t)
        kind = self.compiled_kind(c)
        if kind is not None:
            return hexplane_compiled(c, [p for planes in self.grids for p in planes], kind)
        return self.features_torch(c, t)

    def features_torch(self, c: Tensor, t: float) -> Tensor:
        """The features of normalized coordinates c [N, 4] (time 2t - 1) in torch ops: the twin
        of the compiled sampling."""
        tc = 2.0 * float(t) - 1.0  # c[:, 3], one value: the time planes are sampled by row
        feats = []
        for planes in self.grids:
            f = 1.0
            for (i, j), plane in zip(PAIRS, planes):
                f = f * (sample_plane_row(plane, c[:, i], tc) if j == 3 else sample_plane(plane, torch.stack([c[:, i], c[:, j]], -1)))
            feats.append(f)
        return torch.cat(feats, -1)

    def regularizers(self) -> dict[str, Tensor]:
        """The published terms, unweighted: smoothness of the space planes (second differences,
        named plane_tv in the paper's code), smoothness along time, and L1 of (1 - time planes)."""
        space = sum(second_difference_smoothness(g[i]) for g in self.grids for i in SPACE_PLANES)
        time = sum(second_difference_smoothness(g[i]) for g in self.grids for i in TIME_PLANES)
        l1 = sum((1.0 - g[i]).abs().mean() for g in self.grids for i in TIME_PLANES)
        return {"plane_tv": space, "time_smooth": time, "l1_time": l1}


class HexPlaneDeformation(Deformation):
    """HexPlane field + decoder (`feature_out` Linear, `depth` x [ReLU, Linear], then per head
    ReLU-Linear-ReLU-Linear) giving dxyz, dlog-scale, dquat. STDR's conditioning enters the
    decoder input (zero-initialized columns)."""

    capabilities = frozenset({"conditioning"})  # STDR's separated field feeds its network

    apply_rule = staticmethod(apply_pre_activation)

    @classmethod
    def config_kwargs(cls, b, cond_dim=0, train_times=None, seed=0, schedule=None) -> dict:
        c = b.hexplane
        return dict(base_res=c.base_res, multires=list(c.multires), channels=c.channels,
                    time_res=hexplane_time_res(b, train_times), depth=b.depth, width=b.width, cond_dim=cond_dim,
                    head_init_std=b.head_init_std, grid_lr_mult=c.grid_lr_mult,
                    weights={"plane_tv": c.plane_tv, "time_smooth": c.time_smooth, "l1_time": c.l1_time},
                    compiled=getattr(c, "compiled", None))

    def __init__(self, base_res: int = 64, multires: Sequence[int] = (1, 2), channels: int = 32,
                 time_res: int = 25, depth: int = 0, width: int = 64, cond_dim: int = 0,
                 head_init_std: Optional[float] = None, grid_lr_mult: float = 10.0,
                 weights: Optional[dict] = None, compiled: Optional[bool] = None):
        super().__init__()
        self.cond_dim = cond_dim
        self.grid = HexPlaneField(base_res, multires, channels, time_res, compiled=compiled)
        self.grid_lr_mult = grid_lr_mult
        self.weights = dict(weights or {"plane_tv": 1e-4, "time_smooth": 1e-2, "l1_time": 1e-4})
        layers: list[nn.Module] = [nn.Linear(self.grid.feat_dim + cond_dim, width)]
        for _ in range(depth):
            layers += [nn.ReLU(), nn.Linear(width, width)]
        self.feature_out = nn.Sequential(*layers)

        def head(k):
            return nn.Sequential(nn.ReLU(), nn.Linear(width, width), nn.ReLU(), nn.Linear(width, k))
        self.head_xyz, self.head_scale, self.head_rot = head(3), head(3), head(4)
        if cond_dim:
            with torch.no_grad():
                self.feature_out[0].weight[:, -cond_dim:] = 0.0
        if head_init_std is not None:
            for h in (self.head_xyz, self.head_scale, self.head_rot):
                nn.init.normal_(h[-1].weight, std=head_init_std)
                nn.init.zeros_(h[-1].bias)

    def init_gaussians(self, params) -> None:
        """The grid's bounds from the Gaussians' means."""
        if params is not None and "means" in params and params["means"].shape[0] > 0:
            self.grid.set_bounds(params["means"].detach())

    def param_groups(self) -> list[dict]:
        grid = list(self.grid.parameters())
        ids = {id(p) for p in grid}
        return [{"params": [p for p in self.parameters() if id(p) not in ids], "name": "deform", "lr_mult": 1.0},
                {"params": grid, "name": "hexplane", "lr_mult": self.grid_lr_mult}]

    def forward(self, params, t: float, cond: Optional[Tensor] = None) -> Deltas:
        xyz = params["means"].detach()
        h = self.grid(xyz, t)
        if self.cond_dim:
            if cond is None:
                raise ValueError("this deformation was built with cond_dim > 0 and needs cond")
            h = torch.cat([h, cond], -1)
        h = self.feature_out(h)
        return Deltas(means=self.head_xyz(h), scales=self.head_scale(h), quats=self.head_rot(h))

    def regularizers(self, ctx: StepContext) -> dict[str, Tensor]:
        return {f"hexplane_{k}": self.weights[k] * v for k, v in self.grid.regularizers().items()
                if self.weights.get(k, 0.0) > 0}


register_baseline("4dgs", HexPlaneDeformation, HexPlaneBaselineConfig, in_grids=True)
