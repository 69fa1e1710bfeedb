"""What STDR reports: TensorBoard entries (`log_to`) and the numbers of metrics.json (`stats_of`)
of a plug-in's mask and separated field."""
from __future__ import annotations

from typing import Any, Optional

import torch
from torch import Tensor

from ...ops import sigmoid
from .mask import MASK_KEY, activated, faint_fraction, temporal_entropy


def log_to(tb, plugin, params, step: int, images: bool, x: Optional[int] = None) -> None:
    """TensorBoard: the phase of iteration `step`, mask statistics; with images also the
    entropy and dynamic-probability histograms and the mask-over-time image. x: the axis value."""
    x = step if x is None else x
    tb.add_scalar("stdr/phase", int(plugin.phase(step)), x)
    if not plugin.has_mask(params):
        return
    m = params[MASK_KEY].detach()
    a = activated(m)
    tb.add_scalar("stdr/mask_mean", float(a.mean()), x)
    tb.add_scalar("stdr/mask_min_over_time_mean", float(a.amin(1).mean()), x)
    if images:
        tb.add_histogram("stdr/temporal_entropy", temporal_entropy(m), x)
        if plugin.last_dynamic is not None and plugin.last_dynamic.shape[0] == m.shape[0]:
            tb.add_histogram("stdr/dynamic_probability", plugin.last_dynamic.flatten(), x)
        tb.add_image("stdr/mask_over_time", mask_image(a), x, dataformats="HW")

def mask_image(a: Tensor, rows: int = 64, cell: int = 4) -> Tensor:
    """[rows*cell, K*cell] grey image: activated mask of evenly spaced Gaussians (rows)
    sorted by the time of their peak, time left to right."""
    n = a.shape[0]
    if n == 0:
        return torch.zeros(cell, cell, device=a.device)
    idx = torch.linspace(0, n - 1, min(rows, n), device=a.device).long()
    s = a[idx]
    s = s[torch.argsort(s.argmax(1), stable=True)]
    return s.repeat_interleave(cell, 0).repeat_interleave(cell, 1).clamp(0, 1)

def stats_of(plugin, params) -> dict[str, Any]:
    """Numbers for metrics.json: mask size and memory, KNN time, mask and field statistics."""
    out: dict[str, Any] = {"K": plugin.K, "warmup_end": plugin.warmup_end, "freeze_at": plugin.freeze_at,
                           "opacity_init": plugin.opacity_init, "mask_init": plugin.mask_init,
                           "freeze_moved": plugin.freeze_moved, "cleaned_entries": plugin.cleaned_entries,
                           "knn_seconds": plugin.neighbours.seconds, "knn_refreshes": plugin.neighbours.refreshes,
                           "field_precision": plugin.field_precision if plugin.field is not None else None}
    if plugin.has_mask(params):
        m = params[MASK_KEY].detach()
        n = m.shape[0]
        b = m.numel() * m.element_size()
        a = activated(m)
        ent = temporal_entropy(m)
        out.update({
            "num_gaussians": n,
            # an 8-bit mask (stdr.mask_bits=8, after the freeze) has no optimizer state
            "mask_bits": 8 * m.element_size(),
            "mask_bytes": b, "mask_adam_bytes": 2 * b if m.is_floating_point() else 0,
            "mask_total_mib": (3 if m.is_floating_point() else 1) * b / 2 ** 20,
            "mask_mean": float(a.mean()),
            "mask_min_over_time_mean": float(a.amin(1).mean()),
            "fraction_time_gated": float((a.amin(1) < 0.5).float().mean()),  # off at some time
            "fraction_never_off": float((a.amin(1) >= 0.5).float().mean()),
            # (Gaussian, time) entries with masked opacity in [1/255, 0.05]: faint copies
            "fraction_faint": faint_fraction(sigmoid(params["opacities"].detach()), m),
            "temporal_entropy_mean": float(ent.mean()),
            "temporal_entropy_quantiles": [float(x) for x in
                                           torch.quantile(ent.float(), torch.tensor([0.1, 0.5, 0.9], device=ent.device))]
            if n else [],
        })
    if plugin.field is not None:
        was = plugin.field.training
        plugin.field.eval()
        with torch.no_grad():
            plugin.conditioning_at(params, plugin.freeze_at)  # sets last_dynamic (eval mode)
        plugin.field.train(was)
        d = plugin.last_dynamic
        if d is not None and d.numel():
            out["dynamic_probability_mean"] = float(d.mean())
            out["fraction_dynamic"] = float((d > 0.5).float().mean())
    return out
