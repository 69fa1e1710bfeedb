import json

import cv2
import pytest
import torch

from stdr.eval.lpips import LPIPS
from stdr.metrics import psnr, ssim


def test_psnr_known_value():
    a = torch.zeros(4, 4, 3)
    b = torch.full((4, 4, 3), 0.1)
    assert float(psnr(a, b)) == pytest.approx(20.0, abs=1e-4)


def test_ssim_identity_and_against_direct_window_computation():
    g = torch.Generator().manual_seed(0)
    a = torch.rand(20, 18, 3, generator=g)
    assert float(ssim(a, a)) == pytest.approx(1.0, abs=1e-6)
    b = (a + 0.1 * torch.randn(20, 18, 3, generator=g)).clamp(0, 1)
    # direct computation at one interior pixel/channel, 11x11 Gaussian window sigma 1.5
    x = torch.arange(11, dtype=torch.float64) - 5
    w1 = torch.exp(-x ** 2 / 4.5)
    w = (w1[:, None] * w1[None]) / (w1.sum() ** 2)
    pa, pb = a[5:16, 4:15, 1].double(), b[5:16, 4:15, 1].double()
    mu_a, mu_b = (w * pa).sum(), (w * pb).sum()
    va = (w * pa * pa).sum() - mu_a ** 2
    vb = (w * pb * pb).sum() - mu_b ** 2
    cov = (w * pa * pb).sum() - mu_a * mu_b
    C1, C2 = 0.01 ** 2, 0.03 ** 2
    direct = ((2 * mu_a * mu_b + C1) * (2 * cov + C2)) / ((mu_a ** 2 + mu_b ** 2 + C1) * (va + vb + C2))
    from stdr import metrics
    import torch.nn.functional as F
    win = metrics._window(11, 1.5, 3, torch.float64, a.device)
    A, B = a.double().permute(2, 0, 1)[None], b.double().permute(2, 0, 1)[None]
    m1, m2 = F.conv2d(A, win, padding=5, groups=3), F.conv2d(B, win, padding=5, groups=3)
    s1 = F.conv2d(A * A, win, padding=5, groups=3) - m1 ** 2
    s2 = F.conv2d(B * B, win, padding=5, groups=3) - m2 ** 2
    s12 = F.conv2d(A * B, win, padding=5, groups=3) - m1 * m2
    mp = ((2 * m1 * m2 + C1) * (2 * s12 + C2)) / ((m1 ** 2 + m2 ** 2 + C1) * (s1 + s2 + C2))
    assert float(mp[0, 1, 10, 9]) == pytest.approx(float(direct), abs=1e-10)
    assert float(ssim(a.double(), b.double())) == pytest.approx(float(mp.mean()), abs=1e-12)


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-12), (torch.float32, 1e-6)])
def test_separable_ssim_equals_the_2d_window_with_gradients(dtype, tol):
    """The loss's SSIM (two 1D passes, zero padding) equals the 2D window's (ssim_2d) in value
    and in the gradient for the rendered image, border pixels included, on a non-square image."""
    from stdr.metrics import ssim_2d
    g = torch.Generator().manual_seed(1)
    a = torch.rand(23, 31, 3, generator=g, dtype=torch.float64).to(dtype).requires_grad_(True)
    b = torch.rand(23, 31, 3, generator=g, dtype=torch.float64).to(dtype)
    x, y = ssim(a, b), ssim_2d(a, b)
    assert abs(float(x) - float(y)) <= tol
    gx, = torch.autograd.grad(x, a)
    gy, = torch.autograd.grad(y, a)
    assert float((gx - gy).abs().max() / gy.abs().max()) <= (1e-10 if dtype == torch.float64 else 1e-4)
    assert float(gy[0, 0].abs().sum()) > 0  # the corner pixel has a gradient to compare


def _img(path):
    return torch.from_numpy(cv2.imread(str(path))[..., ::-1].copy()).float() / 255


@pytest.mark.slow
@pytest.mark.parametrize("net", ["vgg", "alex"])
def test_lpips_calibration(shared_dir, net):
    root = shared_dir / "data" / "lpips_calibration"
    ref = json.loads((root / "scores.json").read_text())[f"lpips_{net}"]
    m = LPIPS(net, weights_dir=shared_dir / "weights" / "lpips")
    for name, score in ref.items():
        got = float(m(_img(root / "ref" / f"{name}.png"), _img(root / "dist" / f"{name}.png")))
        assert got == pytest.approx(score, abs=1e-3), name


def test_lpips_missing_weights_message(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"vgg16_features.pth.*eval.lpips_weights"):
        LPIPS("vgg", weights_dir=tmp_path)


def _cpuinfo(family, model, flags, name="AMD EPYC"):
    one = (f"processor\t: {{}}\nvendor_id\t: AuthenticAMD\ncpu family\t: {family}\nmodel\t\t: {model}\n"
           f"model name\t: {name}\nstepping\t: 1\nflags\t\t: fpu sse4_2 {flags}\n")
    return one.format(0) + "\n" + one.format(1).replace(name, "second processor ignored")


def test_machine_label_tells_apart_cpus_sold_under_one_name():
    # float32 results differ between two "AMD EPYC" machines of other families or SIMD widths,
    # so the label recorded with every metric must tell them apart
    from stdr.eval.evaluate import machine_name
    zen3 = machine_name(_cpuinfo(25, 1, "avx avx2"))
    zen4 = machine_name(_cpuinfo(25, 17, "avx avx2 avx512f"))
    rome = machine_name(_cpuinfo(23, 49, "avx avx2"))
    assert zen3.startswith("AMD EPYC, family 25 model 1 stepping 1, AVX2, ")
    assert "AVX512F" in zen4 and "AVX2" not in zen4  # the widest level only
    assert len({zen3, zen4, rome}) == 3 and all(s.endswith("logical CPUs") for s in (zen3, zen4, rome))
    assert "second processor" not in zen3
    # no /proc/cpuinfo (macOS, Windows): the platform's name, still with the CPU count
    assert machine_name("").endswith("logical CPUs") and "family" not in machine_name("")
