"""Image metrics shared by the training loss and the evaluation (one implementation each).

SSIM follows the 3DGS convention: 11x11 Gaussian window, sigma 1.5, zero-padded "same"
convolution, C1 = 0.01^2, C2 = 0.03^2 (data range 1), mean over pixels and channels.
"""
from __future__ import annotations


import torch
import torch.nn.functional as F
from torch import Tensor

_WINDOWS: dict = {}


def _window(size: int, sigma: float, channels: int, dtype, device) -> Tensor:
    key = (size, sigma, channels, dtype, device)
    if key not in _WINDOWS:
        x = torch.arange(size, dtype=torch.float64, device="cpu") - size // 2  # built on the host, then moved
        g = torch.exp(-x * x / (2 * sigma * sigma))
        g = g / g.sum()
        w = (g[:, None] @ g[None, :]).to(dtype=dtype, device=device)
        _WINDOWS[key] = w.expand(channels, 1, size, size).contiguous()
    return _WINDOWS[key]


def _to_bchw(img: Tensor) -> Tensor:
    """[H, W, C] -> [1, C, H, W]; [B, C, H, W] passes through."""
    return img.permute(2, 0, 1)[None] if img.dim() == 3 else img


def ssim(img1: Tensor, img2: Tensor, window_size: int = 11, sigma: float = 1.5) -> Tensor:
    """Mean SSIM of two images [H, W, C] (or [B, C, H, W]) with values in [0, 1]."""
    a, b = _to_bchw(img1), _to_bchw(img2)
    C = a.shape[1]
    w = _window(window_size, sigma, C, a.dtype, a.device)
    pad = window_size // 2
    mu1 = F.conv2d(a, w, padding=pad, groups=C)
    mu2 = F.conv2d(b, w, padding=pad, groups=C)
    mu1_sq, mu2_sq, mu12 = mu1 * mu1, mu2 * mu2, mu1 * mu2
    s1 = F.conv2d(a * a, w, padding=pad, groups=C) - mu1_sq
    s2 = F.conv2d(b * b, w, padding=pad, groups=C) - mu2_sq
    s12 = F.conv2d(a * b, w, padding=pad, groups=C) - mu12
    C1, C2 = 0.01 ** 2, 0.03 ** 2
    m = ((2 * mu12 + C1) * (2 * s12 + C2)) / ((mu1_sq + mu2_sq + C1) * (s1 + s2 + C2))
    return m.mean()


def psnr(img1: Tensor, img2: Tensor) -> Tensor:
    """PSNR in dB for data range 1, over all pixels and channels."""
    mse = torch.mean((img1 - img2) ** 2)
    return 10.0 * torch.log10(1.0 / mse.clamp_min(1e-20))


def l1(img1: Tensor, img2: Tensor) -> Tensor:
    return (img1 - img2).abs().mean()
