"""Test helpers: random scenes and a brute-force per-pixel renderer (independent of tiles)."""
from __future__ import annotations

import math

import torch

from stdr.cameras import Camera
from stdr.render.projection import SIGMA_EXTENT


def look_at_camera(eye, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0), width=32, height=24,
                   fov_x=0.8, dtype=torch.float32, cx=None, cy=None) -> Camera:
    eye = torch.tensor(eye, dtype=torch.float64)
    f = torch.tensor(target, dtype=torch.float64) - eye
    f = f / f.norm()
    r = torch.linalg.cross(f, torch.tensor(up, dtype=torch.float64))
    r = r / r.norm()
    d = torch.linalg.cross(f, r)  # camera y points down
    R = torch.stack([r, d, f])
    t = -R @ eye
    fx = 0.5 * width / math.tan(0.5 * fov_x)
    return Camera(R=R.to(dtype), t=t.to(dtype), fx=fx, fy=fx, cx=width / 2 if cx is None else cx,
                  cy=height / 2 if cy is None else cy, width=width, height=height)


def random_gaussians(n, seed=0, dtype=torch.float32, spread=0.6, scale=(-2.5, -1.2)):
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g, dtype=dtype) * 2 - 1) * spread
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    scales = torch.exp(torch.rand(n, 3, generator=g, dtype=dtype) * (scale[1] - scale[0]) + scale[0])
    opac = torch.rand(n, generator=g, dtype=dtype) * 0.9 + 0.05
    colors = torch.rand(n, 3, generator=g, dtype=dtype)
    return means, quats, scales, opac, colors


def brute_force_composite(means2d, conics, opacities, features, depths, radii, width, height):
    """Per-pixel loop over all Gaussians in depth order: the semantics, written the slow way."""
    order = sorted(range(means2d.shape[0]), key=lambda i: (float(depths[i]), i))
    order = [i for i in order if int(radii[i]) > 0]
    F = features.shape[1]
    img = torch.zeros(height, width, F, dtype=means2d.dtype)
    Tm = torch.ones(height, width, dtype=means2d.dtype)
    for y in range(height):
        for x in range(width):
            T = 1.0
            acc = torch.zeros(F, dtype=means2d.dtype)
            for i in order:
                dx = x + 0.5 - means2d[i, 0]
                dy = y + 0.5 - means2d[i, 1]
                a, b, c = conics[i]
                maha = a * dx * dx + 2 * b * dx * dy + c * dy * dy
                if maha > SIGMA_EXTENT ** 2:
                    continue
                alpha = min(0.99, float(opacities[i] * torch.exp(-0.5 * maha)))
                if alpha < 1.0 / 255.0:
                    continue
                test_T = T * (1 - alpha)
                if test_T < 1e-4:
                    break
                acc = acc + alpha * T * features[i]
                T = test_T
            img[y, x] = acc
            Tm[y, x] = T
    return img, Tm


def hard_case_scene(dtype=torch.float64, extra_rows=()):
    """(means, quats, scales, opacities, colors) of the rasterizer's hard cases, seen from
    look_at_camera((3, 0, 0)): row 1 is behind the camera and row 7 entirely off-screen."""
    rows = [
        ([0.0, 0.0, 0.0], [0.2, 0.2, 0.2], 0.5),      # central
        ([4.0, 0.0, 0.0], [0.2, 0.2, 0.2], 0.9),      # behind the camera
        ([0.0, 1.2, 0.0], [0.3, 0.3, 0.3], 0.8),      # partly off-screen
        ([0.0, 0.0, 0.1], [0.001, 0.5, 0.001], 0.9),  # very thin
        ([0.5, 0.0, 0.0], [3.0, 3.0, 3.0], 0.3),      # very large
        ([0.0, 0.1, 0.1], [0.1, 0.1, 0.1], 1.0),      # saturated alpha (clamped to 0.99)
        ([0.0, -0.1, 0.1], [0.1, 0.1, 0.1], 1.0),     # equal depth to the previous one
        ([0.0, 9.0, 9.0], [0.1, 0.1, 0.1], 0.9),      # entirely off-screen: empty tiles elsewhere
        *extra_rows,
    ]
    means = torch.tensor([r[0] for r in rows], dtype=dtype)
    scales = torch.tensor([r[1] for r in rows], dtype=dtype)
    opac = torch.tensor([r[2] for r in rows], dtype=dtype)
    quats = torch.tensor([[1.0, 0, 0, 0]], dtype=dtype).repeat(len(rows), 1)
    colors = torch.rand(len(rows), 3, dtype=dtype, generator=torch.Generator().manual_seed(0))
    return means, quats, scales, opac, colors


def load_script(path, name: str):
    """A script of the checkout (e.g. studies/results.py) imported as module `name` (registered in
    sys.modules, where dataclasses look their module up)."""
    import importlib.util
    import sys
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod
