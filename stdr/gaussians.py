"""Gaussian parameters, all per-Gaussian tensors in one dict.

Every tensor in the dict has N rows (the Gaussian count) and is edited row-wise by the
densification strategy, so any per-Gaussian attribute added later (STDR's N x K mask) stays
aligned through clone/split/prune with no extra code.

Keys and their stored (pre-activation) form:
    means     [N, 3]      world position
    scales    [N, 3]      log of the standard deviations
    quats     [N, 4]      rotation quaternion (w, x, y, z), unnormalized
    opacities [N]         logit of opacity
    sh0       [N, 1, 3]   SH DC coefficient
    shN       [N, K-1, 3] higher SH bands, K = (max_sh_degree+1)^2
"""
from __future__ import annotations

import math
from typing import NamedTuple, Optional

import numpy as np
import torch
from torch import Tensor, nn

from .ops import sigmoid
from .render.sh import num_sh_bases, rgb_to_sh
from .device import available_bytes
from .errors import ConfigError
from .knn import KNN_CHUNK, knn

GAUSSIAN_KEYS = ("means", "scales", "quats", "opacities", "sh0", "shN")


class Gaussians(NamedTuple):
    """Activated Gaussians, as the renderer takes them."""

    means: Tensor      # [N, 3]
    quats: Tensor      # [N, 4]
    scales: Tensor     # [N, 3]
    opacities: Tensor  # [N]
    sh: Tensor         # [N, K, 3]


def inverse_sigmoid(x: Tensor) -> Tensor:
    return torch.log(x / (1 - x))


def init_params(points: Tensor, colors: Optional[Tensor] = None, sh_degree: int = 3,
                init_opacity: float = 0.1, knn_k: int = 3) -> nn.ParameterDict:
    """Gaussians at `points` [N, 3] with colours [N, 3] in [0, 1] (random if None).

    Initial scale: sqrt of the mean squared distance to the `knn_k` nearest neighbours
    (isotropic), identity rotation, opacity `init_opacity` - the 3DGS initialization.
    """
    points = points.float()
    N = points.shape[0]
    if N < knn_k + 1:
        raise ValueError(f"init_params: need at least {knn_k + 1} points, got {N}")
    if colors is None:
        colors = torch.rand(N, 3, device=points.device)
    d2, _ = knn(points, points, knn_k, exclude_self=True)
    dist = torch.sqrt(d2.mean(1).clamp_min(1e-7))
    K = num_sh_bases(sh_degree)
    dev = points.device
    quats = torch.zeros(N, 4, device=dev)
    quats[:, 0] = 1.0
    return nn.ParameterDict({
        "means": nn.Parameter(points.clone()),
        "scales": nn.Parameter(torch.log(dist)[:, None].repeat(1, 3)),
        "quats": nn.Parameter(quats),
        "opacities": nn.Parameter(torch.full((N,), math.log(init_opacity / (1 - init_opacity)), device=dev)),
        "sh0": nn.Parameter(rgb_to_sh(colors.float())[:, None, :]),
        "shN": nn.Parameter(torch.zeros(N, K - 1, 3, device=dev)),
    })


def random_cube_points(n: int, extent: float, generator: Optional[torch.Generator] = None) -> Tensor:
    """n points uniform in [-extent, extent]^3 (D-NeRF init: 100k in [-1.3, 1.3]^3)."""
    dev = "cpu" if generator is None else generator.device
    return (torch.rand(n, 3, generator=generator, device=dev) * 2 - 1) * extent


def activate(params) -> Gaussians:
    return Gaussians(
        means=params["means"],
        quats=params["quats"],
        scales=torch.exp(params["scales"]),
        opacities=sigmoid(params["opacities"]),
        sh=torch.cat([params["sh0"], params["shN"]], 1),
    )


def num_gaussians(params) -> int:
    return int(params["means"].shape[0])


def scene_extent(camera_centers: np.ndarray) -> float:
    """3DGS 'cameras_extent': 1.1 x the largest distance of a camera centre from their mean."""
    c = np.asarray(camera_centers, dtype=np.float64)
    return float(1.1 * np.linalg.norm(c - c.mean(0), axis=1).max())


def check_init_fits(model_cfg, device: torch.device) -> None:
    """model.init_num random Gaussians must fit in `device`'s free memory: their parameters
    (means, scales, quaternion, opacity and the colour coefficients in float32) and the peak of
    the nearest-neighbour search that sets their initial scales are a lower bound of what training
    needs. Refused by name (ConfigError) instead of an allocator's traceback."""
    if model_cfg.init != "random":
        return
    n = int(model_cfg.init_num)
    floats = 3 + 3 + 4 + 1 + 3 * (int(model_cfg.sh_degree) + 1) ** 2
    # the initial scales' nearest-neighbour search (stdr.knn: distances of KNN_CHUNK points to all n)
    params, search = n * floats * 4, min(KNN_CHUNK, n) * n * 4
    need, free = params + search, available_bytes(device)
    if free is not None and need > free:
        raise ConfigError(f"model.init_num={n}: {n:,} Gaussians need at least {need / 2 ** 30:,.1f} GiB ("
                          f"{params / 2 ** 30:,.1f} for their parameters, {search / 2 ** 30:,.1f} for the nearest-"
                          f"neighbour search of their initial scales), more than the {free / 2 ** 30:,.1f} GiB free on "
                          f"{device}; the budgets start from 10,000 to 100,000 (docs/budgets.md)")


def initial_points(model_cfg, scene_points: Optional[np.ndarray], scene_colors: Optional[np.ndarray],
                   seed: int, where: str = "the scene") -> tuple[Tensor, Tensor]:
    """(points [N, 3], colours [N, 3]) the Gaussians start from, by model.init: a random cube or
    the scene's points (SfM / the loader's). Random draws come from a CPU generator seeded with
    `seed`, so every device starts from the same Gaussians."""
    gen = torch.Generator().manual_seed(seed)
    if model_cfg.init == "random":
        pts = random_cube_points(model_cfg.init_num, model_cfg.init_extent, gen)
    elif model_cfg.init == "points":
        if scene_points is None:
            raise ValueError(f"model.init=points but {where} provides no points; use model.init=random")
        pts = torch.from_numpy(scene_points).float()
    else:
        raise ValueError(f"model.init={model_cfg.init!r}: use 'random' or 'points'")
    colors = torch.rand(pts.shape[0], 3, generator=gen)
    if model_cfg.init == "points" and scene_colors is not None:
        colors = torch.from_numpy(scene_colors).float()
    return pts, colors
