"""EWA projection of 3D Gaussians to screen space (pure torch, differentiable).

Follows 3DGS/gsplat: covariance R S S^T R^T, the affine (first-order) perspective Jacobian with
the view-frustum clamp of 1.3 x the field of view, a 0.3 px^2 low-pass added to the 2D
covariance, and a 3-sigma screen radius. The `antialiased` mode is Mip-Splatting's: the
low-pass is compensated by scaling opacity by sqrt(det(S) / det(S + 0.3 I)).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..cameras import Camera
from .sh import eval_sh

SIGMA_EXTENT = 3.0  # a Gaussian's footprint is its 3-sigma ellipse; alpha is 0 outside it


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """quats [N, 4] as (w, x, y, z), any norm -> rotation matrices [N, 3, 3]."""
    q = quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], -1).reshape(-1, 3, 3)


def covariance_3d(quats: Tensor, scales: Tensor) -> Tensor:
    """quats [N, 4], scales [N, 3] (activated, sign irrelevant) -> covariances [N, 3, 3]."""
    M = quat_to_rotmat(quats) * scales[:, None, :]  # R @ diag(s)
    return M @ M.transpose(1, 2)


def frustum_limits(camera: Camera) -> tuple[float, float, float, float]:
    """(lim_xp, lim_xn, lim_yp, lim_yn): the Jacobian is evaluated at x/z clamped to
    [-lim_xn, lim_xp] and y/z to [-lim_yn, lim_yp], 1.3x the frustum, as 3DGS/gsplat do."""
    fx, fy, cx, cy, W, H = camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height
    tan_x, tan_y = 0.5 * W / fx, 0.5 * H / fy
    return (W - cx) / fx + 0.3 * tan_x, cx / fx + 0.3 * tan_x, (H - cy) / fy + 0.3 * tan_y, cy / fy + 0.3 * tan_y


@dataclass
class Projection:
    means2d: Tensor    # [N, 2] pixel coordinates (pixel centres at i + 0.5)
    depths: Tensor     # [N] camera-space z
    conics: Tensor     # [N, 3] (a, b, c) of the inverse 2D covariance
    opacities: Tensor  # [N] opacities after the antialiasing compensation (if any)
    radii: Tensor      # [N] int32 screen radius in pixels, 0 = culled


def project_gaussians(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor,
                      camera: Camera, near: float = 0.01, far: float = 1e10, eps2d: float = 0.3,
                      antialiased: bool = False) -> Projection:
    """Project N Gaussians.

    means [N, 3], quats [N, 4], scales [N, 3] (activated), opacities [N] (activated).
    """
    N = means.shape[0]
    R = camera.R.to(means)
    t = camera.t.to(means)
    xc = means @ R.T + t  # [N, 3]
    x, y, z = xc.unbind(-1)
    in_depth = (z > near) & (z < far)
    zs = torch.where(in_depth, z, torch.ones_like(z))  # keep culled rows finite

    fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy
    W, H = camera.width, camera.height
    lim_xp, lim_xn, lim_yp, lim_yn = frustum_limits(camera)
    tx = zs * torch.clamp(x / zs, -lim_xn, lim_xp)
    ty = zs * torch.clamp(y / zs, -lim_yn, lim_yp)
    zero = torch.zeros_like(zs)
    J = torch.stack([fx / zs, zero, -fx * tx / (zs * zs),
                     zero, fy / zs, -fy * ty / (zs * zs)], -1).reshape(N, 2, 3)

    cov_w = covariance_3d(quats, scales)
    cov_c = R @ cov_w @ R.T
    cov2d = J @ cov_c @ J.transpose(1, 2)  # [N, 2, 2]
    a0, b0, c0 = cov2d[:, 0, 0], cov2d[:, 0, 1], cov2d[:, 1, 1]
    a, b, c = a0 + eps2d, b0, c0 + eps2d
    det = a * c - b * b
    valid = in_depth & (det > 0)
    det_s = torch.where(valid, det, torch.ones_like(det))
    conics = torch.stack([c / det_s, -b / det_s, a / det_s], -1)
    if antialiased:
        det0 = (a0 * c0 - b0 * b0).clamp_min(0.0)
        opacities = opacities * torch.sqrt(det0 / det_s)

    with torch.no_grad():
        mid = 0.5 * (a + c)
        lam = mid + torch.sqrt((mid * mid - det).clamp_min(0.1))
        radii = torch.ceil(SIGMA_EXTENT * torch.sqrt(lam)).to(torch.int32)
        radii = torch.where(valid, radii, torch.zeros_like(radii))

    means2d = torch.stack([fx * x / zs + cx, fy * y / zs + cy], -1)
    with torch.no_grad():  # cull footprints that miss the image entirely
        r = radii.to(means.dtype)
        off = ((means2d[:, 0] + r <= 0) | (means2d[:, 0] - r >= W)
               | (means2d[:, 1] + r <= 0) | (means2d[:, 1] - r >= H))
        radii = torch.where(off, torch.zeros_like(radii), radii)
    return Projection(means2d=means2d, depths=z, conics=conics, opacities=opacities, radii=radii)


def project_and_shade(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, sh: Tensor,
                      camera: Camera, sh_degree: int, near: float = 0.01, eps2d: float = 0.3,
                      antialiased: bool = False) -> tuple[Projection, Tensor]:
    """(Projection, colours [N, 3]): `project_gaussians` and SH at the normalized view direction
    (camera centre to Gaussian; the gradient flows through it, as in 3DGS). The torch twin of
    `compiled.project_sh_compiled`."""
    proj = project_gaussians(means, quats, scales, opacities, camera, near=near, eps2d=eps2d,
                             antialiased=antialiased)
    dirs = means - camera.center.to(means)
    dirs = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    return proj, eval_sh(sh_degree, sh, dirs)
