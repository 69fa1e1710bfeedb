"""One entry point, `render()`: project, shade (SH), rasterize with the selected backend."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch
from torch import Tensor

from ..cameras import Camera
from .projection import Projection, project_gaussians
from .reference import rasterize_reference
from .sh import eval_sh

BACKENDS = ("reference",)


def resolve_backend(name: str) -> str:
    """Map a `render.backend` value to an available backend.

    `auto` picks the fastest available one (compiled backends arrive in their own module;
    until then `auto` means `reference`).
    """
    if name == "auto":
        return "reference"
    if name not in BACKENDS:
        raise ValueError(f"render.backend={name!r} is not one of {('auto',) + BACKENDS}")
    return name


@dataclass
class RenderOutput:
    image: Tensor      # [H, W, 3] colour composited over the background
    alpha: Tensor      # [H, W] accumulated opacity (1 - final transmittance)
    depth: Tensor      # [H, W] expected camera depth (alpha-weighted, not normalized)
    means2d: Tensor    # [N, 2] screen-space means; .grad after backward feeds densification
    radii: Tensor      # [N] int32 screen radius in pixels (0 = not rendered)
    projection: Projection


def render(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, sh: Tensor,
           camera: Camera, sh_degree: int, background: Optional[Tensor] = None,
           backend: str = "reference", near: float = 0.01, eps2d: float = 0.3,
           antialiased: bool = False, tile_size: int = 8) -> RenderOutput:
    """Render N Gaussians seen by `camera`.

    means [N, 3]; quats [N, 4] (w, x, y, z; any norm); scales [N, 3] (activated);
    opacities [N] (activated, in [0, 1]); sh [N, K, 3] SH coefficients (K >= (sh_degree+1)^2);
    background [3] colour or None for black.
    """
    N = means.shape[0]
    for name, x, shape in (("means", means, (N, 3)), ("quats", quats, (N, 4)),
                           ("scales", scales, (N, 3)), ("opacities", opacities, (N,))):
        if tuple(x.shape) != shape:
            raise ValueError(f"render: {name} must have shape {shape}, got {tuple(x.shape)}")
    backend = resolve_backend(backend)
    proj = project_gaussians(means, quats, scales, opacities, camera, near=near, eps2d=eps2d,
                             antialiased=antialiased)
    means2d = proj.means2d
    if means2d.requires_grad:
        means2d.retain_grad()
    dirs = means - camera.center.to(means)  # gradient flows through the view direction, as in 3DGS
    dirs = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    colors = eval_sh(sh_degree, sh, dirs)  # [N, 3]
    feats = torch.cat([colors, proj.depths[:, None]], -1)  # depth rides along as a 4th channel
    acc, T = rasterize_reference(means2d, proj.conics, proj.opacities, feats, proj.depths,
                                 proj.radii, camera.width, camera.height, tile_size=tile_size)
    image = acc[..., :3]
    if background is not None:
        image = image + T[..., None] * background.to(image)
    return RenderOutput(image=image, alpha=1.0 - T, depth=acc[..., 3], means2d=means2d,
                        radii=proj.radii, projection=proj)
