"""SO(3), quaternions and farthest-point sampling in torch (no lietorch / pytorch3d).

Quaternions are (w, x, y, z). Rotation vectors (axis * angle) are so(3) elements.
"""
from __future__ import annotations

from typing import Optional

import torch
from torch import Tensor

from .render.projection import quat_to_rotmat

__all__ = ["so3_exp", "so3_log", "so3_exp_quat", "quat_multiply", "quat_to_rotmat", "farthest_point_sampling",
           "hat"]


def hat(w: Tensor) -> Tensor:
    """[.., 3] -> skew-symmetric [.., 3, 3] with hat(w) @ v = w x v."""
    z = torch.zeros_like(w[..., 0])
    return torch.stack([z, -w[..., 2], w[..., 1], w[..., 2], z, -w[..., 0], -w[..., 1], w[..., 0], z],
                       -1).reshape(*w.shape[:-1], 3, 3)


def so3_exp(w: Tensor) -> Tensor:
    """Rotation vectors [.., 3] -> rotation matrices [.., 3, 3] (Rodrigues; Taylor near 0)."""
    th2 = (w * w).sum(-1, keepdim=True)[..., None]  # [.., 1, 1]
    th = th2.clamp_min(1e-24).sqrt()
    small = th2 < 1e-8
    a = torch.where(small, 1.0 - th2 / 6.0, torch.sin(th) / th)
    b = torch.where(small, 0.5 - th2 / 24.0, (1.0 - torch.cos(th)) / th2.clamp_min(1e-24))
    K = hat(w)
    eye = torch.eye(3, dtype=w.dtype, device=w.device).expand_as(K)
    return eye + a * K + b * (K @ K)


def so3_log(R: Tensor) -> Tensor:
    """Rotation matrices [.., 3, 3] -> rotation vectors [.., 3], for angles in [0, pi)."""
    cos = ((R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2] - 1.0) * 0.5).clamp(-1.0, 1.0)
    th = torch.acos(cos)
    v = torch.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    s = torch.sin(th)
    scale = torch.where(th < 1e-4, 0.5 + th * th / 12.0, th / (2.0 * s.clamp_min(1e-12)))
    return v * scale[..., None]


def so3_exp_quat(w: Tensor) -> Tensor:
    """Rotation vectors [.., 3] -> unit quaternions [.., 4] (w, x, y, z)."""
    th = w.norm(dim=-1, keepdim=True)
    half = 0.5 * th
    k = torch.where(th < 1e-6, 0.5 - th * th / 48.0, torch.sin(half) / th.clamp_min(1e-12))
    return torch.cat([torch.cos(half), w * k], -1)


def quat_multiply(a: Tensor, b: Tensor) -> Tensor:
    """Hamilton product a * b of quaternions [.., 4] (the rotation b, then a)."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([aw * bw - ax * bx - ay * by - az * bz,
                        aw * bx + ax * bw + ay * bz - az * by,
                        aw * by - ax * bz + ay * bw + az * bx,
                        aw * bz + ax * by - ay * bx + az * bw], -1)


def farthest_point_sampling(x: Tensor, m: int, generator: Optional[torch.Generator] = None,
                            start: Optional[int] = None) -> Tensor:
    """Indices [m] of m points of x [N, D] chosen greedily, each farthest from those before."""
    n = x.shape[0]
    if m > n:
        raise ValueError(f"farthest point sampling: asked for {m} of {n} points")
    idx = torch.empty(m, dtype=torch.long, device=x.device)
    first = int(torch.randint(n, (1,), generator=generator, device="cpu" if generator is None else generator.device)) \
        if start is None else start
    idx[0] = first
    d = (x - x[first]).square().sum(-1)
    for i in range(1, m):
        j = int(torch.argmax(d))
        idx[i] = j
        d = torch.minimum(d, (x - x[j]).square().sum(-1))
    return idx
