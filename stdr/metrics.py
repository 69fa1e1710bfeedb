"""Image metrics shared by the training loss and the evaluation (one implementation each).

SSIM follows the 3DGS convention: 11x11 Gaussian window, sigma 1.5, zero-padded "same"
convolution, C1 = 0.01^2, C2 = 0.03^2 (data range 1), mean over pixels and channels.
"""
from __future__ import annotations


import torch
import torch.nn.functional as F
from torch import Tensor
from torch.autograd.function import once_differentiable

from . import extension
from .ops import fixed_mean

_WINDOWS: dict = {}


def _gauss1d(size: int, sigma: float) -> Tensor:
    x = torch.arange(size, dtype=torch.float64, device="cpu") - size // 2  # built on the host, then moved
    g = torch.exp(-x * x / (2 * sigma * sigma))
    return g / g.sum()  # [size], float64


def _window(size: int, sigma: float, channels: int, dtype, device) -> Tensor:
    """The 2D window [channels, 1, size, size] (the outer product of `_gauss1d`)."""
    key = (size, sigma, channels, dtype, device)
    if key not in _WINDOWS:
        g = _gauss1d(size, sigma)
        w = (g[:, None] @ g[None, :]).to(dtype=dtype, device=device)
        _WINDOWS[key] = w.expand(channels, 1, size, size).contiguous()
    return _WINDOWS[key]


def _windows_1d(size: int, sigma: float, channels: int, dtype, device) -> tuple[Tensor, Tensor]:
    """The same window as two passes: [channels, 1, size, 1] (down) and [channels, 1, 1, size]."""
    key = ("1d", size, sigma, channels, dtype, device)
    if key not in _WINDOWS:
        g = _gauss1d(size, sigma).to(dtype=dtype, device=device)
        _WINDOWS[key] = (g.view(1, 1, size, 1).expand(channels, 1, size, 1).contiguous(),
                         g.view(1, 1, 1, size).expand(channels, 1, 1, size).contiguous())
    return _WINDOWS[key]


def _to_bchw(img: Tensor) -> Tensor:
    """[H, W, C] -> [1, C, H, W]; [B, C, H, W] passes through."""
    return img.permute(2, 0, 1)[None] if img.dim() == 3 else img


def _blur(x: Tensor, size: int, sigma: float) -> Tensor:
    """Zero-padded "same" Gaussian filter of x [B, C, H, W] per channel, as a vertical then a
    horizontal pass: with zero padding the two passes equal the 2D window's convolution (the
    window is separable), at 2 x size instead of size^2 products a pixel."""
    wv, wh = _windows_1d(size, sigma, x.shape[1], x.dtype, x.device)
    pad = size // 2
    x = F.conv2d(x, wv, padding=(pad, 0), groups=x.shape[1])
    return F.conv2d(x, wh, padding=(0, pad), groups=x.shape[1])


def _ssim_map(mu1, mu2, s1, s2, s12) -> Tensor:
    C1, C2 = 0.01 ** 2, 0.03 ** 2
    mu12 = mu1 * mu2
    return ((2 * mu12 + C1) * (2 * (s12 - mu12) + C2)) / \
        ((mu1 * mu1 + mu2 * mu2 + C1) * (s1 - mu1 * mu1 + s2 - mu2 * mu2 + C2))


def ssim(img1: Tensor, img2: Tensor, window_size: int = 11, sigma: float = 1.5) -> Tensor:
    """Mean SSIM of two images [H, W, C] (or [B, C, H, W]) with values in [0, 1].

    The window is applied as two 1D passes (`_blur`), and the five filtered images go through
    two batched calls: the three that depend on img1 (the one a loss differentiates: img1,
    img1^2, img1 img2) and the two of img2 alone. `ssim_2d` is the direct 2D form (the 3DGS
    code's); the two agree to float rounding (tests/test_metrics.py)."""
    a, b = _to_bchw(img1), _to_bchw(img2)
    C = a.shape[1]
    fa = _blur(torch.cat([a, a * a, a * b], 1), window_size, sigma)
    fb = _blur(torch.cat([b, b * b], 1), window_size, sigma)
    mu1, s1, s12 = fa[:, :C], fa[:, C:2 * C], fa[:, 2 * C:]
    mu2, s2 = fb[:, :C], fb[:, C:]
    return fixed_mean(_ssim_map(mu1, mu2, s1, s2, s12))


def ssim_2d(img1: Tensor, img2: Tensor, window_size: int = 11, sigma: float = 1.5) -> Tensor:
    """`ssim` with the 2D window in one convolution per filtered image (the reference form)."""
    a, b = _to_bchw(img1), _to_bchw(img2)
    C = a.shape[1]
    w = _window(window_size, sigma, C, a.dtype, a.device)
    pad = window_size // 2

    def blur(x):
        return F.conv2d(x, w, padding=pad, groups=C)
    return fixed_mean(_ssim_map(blur(a), blur(b), blur(a * a), blur(b * b), blur(a * b)))


def psnr(img1: Tensor, img2: Tensor) -> Tensor:
    """PSNR in dB for data range 1, over all pixels and channels."""
    mse = fixed_mean((img1 - img2) ** 2)
    return 10.0 * torch.log10(1.0 / mse.clamp_min(1e-20))


def l1(img1: Tensor, img2: Tensor) -> Tensor:
    return fixed_mean((img1 - img2).abs())


def image_loss(img: Tensor, gt: Tensor, lam: float) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The photometric training loss: (loss, l1, dssim, psnr), 0-d tensors, with
    loss = (1 - lam) * l1(img, gt) + lam * (1 - ssim(img, gt)). With lam = 0 the D-SSIM is
    computed without a gradient (for the log only). The torch twin of
    `image_loss_compiled` (below; `fused_loss`)."""
    loss_l1 = l1(img, gt)
    if lam > 0:
        loss_dssim = 1.0 - ssim(img, gt)
        loss = (1 - lam) * loss_l1 + lam * loss_dssim
    else:  # its backward would add exact zeros
        with torch.no_grad():
            loss_dssim = 1.0 - ssim(img.detach(), gt)
        loss = loss_l1
    return loss, loss_l1, loss_dssim, psnr(img.detach(), gt)


def fused_loss(setting, device: torch.device, dtype: torch.dtype = torch.float32) -> bool:
    """Whether a run's loss is the compiled one (optim.fused_loss resolved): null = where it has
    been verified and the extension builds; true insists (an error says why it cannot)."""
    kind = device.type
    return extension.use_compiled("optim.fused_loss", setting, kind,
                                  dtype in LOSS_DTYPES.get(kind, ()),
                                  f"the compiled loss runs in float32/float64 on the CPU and float32 on CUDA, this run "
                                  f"is {dtype} on {device}")


# ----------------------------------------------------------------- its compiled form (stdr/csrc/cpu/loss_cpu.h)
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
    twin is `image_loss` (above); tests/test_fused_loss.py pins the two together. The CPU
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
    ext = extension.load_extension(kind)
    loss, stats = _ImageLoss.apply(img.contiguous(), gt.contiguous(), float(lam), int(window), float(sigma), ext)
    return loss, stats[0], stats[1], stats[2]
