"""The model at one time as a standard 3DGS PLY, for splat viewers (`stdr-export`).

`gaussians_at(model, t)` is what `model.render(camera, t)` rasterizes (deformed after the static
warm-up, opacity times the plug-ins' factors, e.g. STDR's mask), written back in 3DGS's stored
form: log scales (of |s|: the covariance uses s squared), opacity logits, SH bands above the model's active degree set to zero (a viewer
renders every band it finds). Reading such a file with `load_ply` and `activate` gives Gaussians
that render the same image as the model (tests/test_export.py).
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import torch

from ..errors import BadInput
from .ply import save_ply

OPACITY_EPS = 1e-7  # opacities are clamped into [eps, 1 - eps] before the logit


@torch.no_grad()
def gaussians_at(model, t: float, step: Optional[int] = None) -> dict[str, torch.Tensor]:
    """{means, quats, scales, opacities, sh0, shN} (3DGS's stored form) of `model` at time t."""
    step = model.step if step is None else step
    g = model.deformed(t, step)
    deg = model.sh_degree(step)
    sh = g.sh.clone()
    sh[:, (deg + 1) ** 2:] = 0.0  # the bands the model does not use yet
    op = g.opacities.clamp(OPACITY_EPS, 1.0 - OPACITY_EPS)
    # Deformable 3DGS adds its scale deltas after the exp, so a deformed scale can be <= 0; the
    # covariance depends on its square only, so |s| renders the same (the log needs it positive)
    scales = torch.log(g.scales.abs().clamp_min(1e-12))
    return {"means": g.means, "quats": g.quats, "scales": scales,
            "opacities": torch.log(op) - torch.log1p(-op), "sh0": sh[:, :1], "shN": sh[:, 1:]}


def check_times(times: list[float]) -> None:
    """Every time in [0, 1] (NaN is not): else one BadInput naming the bad ones."""
    bad = [t for t in times if not 0.0 <= float(t) <= 1.0]
    if bad:
        raise BadInput(f"--times {' '.join(str(t) for t in bad)}: the model's times run over [0, 1] (0: the "
                       "first training frame's time, 1: the last); give times in that range")
    twice = sorted({float(t) for t in times if [float(x) for x in times].count(float(t)) > 1})
    if twice:
        raise BadInput(f"--times {' '.join(str(t) for t in twice)}: given more than once; each time is one file")


def time_names(times: list[float]) -> list[str]:
    """The file name of each time, t_<time>.ply: 4 decimals, or as many more as it takes for
    different times to get different names (0.12341 and 0.12344: t_0.12341.ply, t_0.12344.ply),
    never one file written over another."""
    ts = [float(t) for t in times]
    for d in range(4, 18):
        names = [f"t_{t:.{d}f}.ply" for t in ts]
        if len(set(names)) == len(set(ts)):
            return names
    return [f"t_{t!r}.ply" for t in ts]


def export_times(model, times: list[float], out: str | Path, source: str = "") -> list[Path]:
    """One PLY per time, out/t_<time>.ply (time_names); returns the paths. `source`: the model's
    checkpoint (stdr.io.checkpoint.source_line), a header comment of every file with its time."""
    check_times(times)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for t, name in zip(times, time_names(times)):
        p = out / name
        save_ply(gaussians_at(model, float(t)), p, comments=[c for c in (source, f"stdr time t={float(t)!r}") if c])
        paths.append(p)
    return paths
