
import pytest
import torch

from stdr.render import render
from stdr.render.projection import project_gaussians
from stdr.render.reference import rasterize_reference
from stdr.render.sh import C0, eval_sh

from helpers import brute_force_composite, hard_case_scene, look_at_camera, random_gaussians


def _compare(means, quats, scales, opac, colors, cam, tile_sizes=(16, 8, 4), chunk=4):
    p = project_gaussians(means, quats, scales, opac, cam)
    feat = torch.cat([colors, p.depths[:, None]], -1)
    ref_img, ref_T = brute_force_composite(p.means2d, p.conics, p.opacities, feat, p.depths, p.radii,
                                           cam.width, cam.height)
    for ts in tile_sizes:
        img, T = rasterize_reference(p.means2d, p.conics, p.opacities, feat, p.depths, p.radii,
                                     cam.width, cam.height, tile_size=ts, chunk=chunk)
        assert torch.allclose(img, ref_img, atol=1e-10), (ts, (img - ref_img).abs().max())
        assert torch.allclose(T, ref_T, atol=1e-10)
    return p, ref_T


def test_reference_matches_brute_force_random_scene():
    cam = look_at_camera((2.5, 0.3, 0.8), width=23, height=17, dtype=torch.float64)
    _, T = _compare(*random_gaussians(80, seed=1, dtype=torch.float64), cam)
    assert T.min() < 1e-3  # early termination was exercised


def test_reference_hard_cases():
    d = torch.float64
    cam = look_at_camera((3.0, 0.0, 0.0), width=20, height=14, dtype=d)
    means, quats, scales, opac, colors = hard_case_scene(d)
    p, _ = _compare(means, quats, scales, opac, colors, cam)
    assert int(p.radii[1]) == 0 and int(p.radii[7]) == 0  # culled
    assert int(p.radii[2]) > 0


@pytest.mark.parametrize("n", [0, 1])
def test_reference_tiny_counts(n):
    cam = look_at_camera((2.5, 0.3, 0.8), width=9, height=7, dtype=torch.float64)
    m, q, s, o, c = random_gaussians(max(n, 1), seed=3, dtype=torch.float64, spread=0.05, scale=(-1.5, -1.0))
    _compare(m[:n], q[:n], s[:n], o[:n], c[:n], cam)


def test_one_pixel_image():
    cam = look_at_camera((2.5, 0.0, 0.0), width=1, height=1, fov_x=0.5, dtype=torch.float64)
    _compare(*random_gaussians(10, seed=4, dtype=torch.float64, spread=0.05, scale=(-1.5, -1.0)), cam)


@pytest.mark.slow
def test_render_gradcheck_float64():
    d = torch.float64
    cam = look_at_camera((2.0, 0.4, 0.5), width=6, height=5, fov_x=0.9, dtype=d)
    m, q, s, o, c = random_gaussians(3, seed=5, dtype=d, spread=0.15, scale=(-1.4, -1.0))
    sh = torch.zeros(3, 4, 3, dtype=d)
    sh[:, 0] = (c - 0.5) / C0
    sh[:, 1:] = 0.1 * torch.randn(3, 3, 3, dtype=d, generator=torch.Generator().manual_seed(0))
    o = o.clamp(0.2, 0.8)  # away from the 0.99 clamp kink
    bg = torch.tensor([0.2, 0.3, 0.4], dtype=d)

    def f(m, q, s, o, sh):
        out = render(m, q, s, o, sh, cam, sh_degree=1, background=bg)
        return out.image, out.alpha, out.depth

    inputs = [x.clone().requires_grad_() for x in (m, q, s, o, sh)]
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)


def test_background_and_outputs():
    cam = look_at_camera((2.5, 0.3, 0.8), width=16, height=12)
    m, q, s, o, c = random_gaussians(30, seed=6)
    sh = ((c - 0.5) / C0)[:, None, :]
    bg = torch.tensor([1.0, 0.0, 0.5])
    out = render(m, q, s, o, sh, cam, sh_degree=0, background=bg)
    out0 = render(m, q, s, o, sh, cam, sh_degree=0)
    assert out.image.shape == (12, 16, 3) and out.alpha.shape == (12, 16) and out.depth.shape == (12, 16)
    assert torch.allclose(out.image, out0.image + (1 - out.alpha)[..., None] * bg, atol=1e-6)
    assert (out.alpha >= 0).all() and (out.alpha <= 1).all()


def test_render_shape_contract():
    cam = look_at_camera((2.5, 0.3, 0.8))
    m, q, s, o, c = random_gaussians(4)
    with pytest.raises(ValueError, match="scales must have shape"):
        render(m, q, s[:, :2], o, c[:, None], cam, sh_degree=0)


def test_sh_degree0_and_view_dependence():
    sh = torch.randn(5, 16, 3)
    dirs = torch.nn.functional.normalize(torch.randn(5, 3), dim=-1)
    assert torch.allclose(eval_sh(0, sh, dirs), (C0 * sh[:, 0] + 0.5).clamp_min(0))
    a, b = eval_sh(3, sh, dirs), eval_sh(3, sh, -dirs)
    assert not torch.allclose(a, b)  # odd bands flip sign with the direction


def test_float32_matches_float64_reference():
    """The float32 path (matmul-expanded exponent) stays within 1e-4 of the float64 result."""
    cam64 = look_at_camera((2.5, 0.3, 0.8), width=64, height=48, dtype=torch.float64)
    g64 = random_gaussians(400, seed=7, dtype=torch.float64, spread=0.7, scale=(-4.0, -2.0))
    cam32 = look_at_camera((2.5, 0.3, 0.8), width=64, height=48, dtype=torch.float32)
    g32 = tuple(x.float() for x in g64)
    sh64 = ((g64[4] - 0.5) / C0)[:, None, :]
    a = render(*g64[:4], sh64, cam64, sh_degree=0)
    b = render(*g32[:4], sh64.float(), cam32, sh_degree=0)
    assert (a.image.float() - b.image).abs().max() < 1e-4
    assert (a.alpha.float() - b.alpha).abs().max() < 1e-4


def test_antialiased_mode_compensates_opacity():
    cam = look_at_camera((2.5, 0.3, 0.8), width=32, height=24)
    m, q, s, o, c = random_gaussians(20, seed=8, scale=(-5.0, -4.0))  # sub-pixel Gaussians
    from stdr.render.projection import project_gaussians
    plain = project_gaussians(m, q, s, o, cam)
    aa = project_gaussians(m, q, s, o, cam, antialiased=True)
    vis = plain.radii > 0
    ratio = aa.opacities[vis] / plain.opacities[vis]
    assert (ratio < 1).all() and (ratio > 0).all()  # tiny Gaussians are dimmed, not enlarged
    big = project_gaussians(m, q, s * 200, o, cam, antialiased=True)
    assert (big.opacities[big.radii > 0] / o[big.radii > 0]).min() > 0.95  # large ones barely change
