"""Contribution pruning: remove the Gaussians no training view needs.

A Gaussian's significance in one view is its blending weight alpha * T summed over the pixels
(`stdr.render.contribution`, the compiled score pass); over the training frames it is a matrix
S [N, T], one column per distinct training time (views at one time add up). Summed over time it
is LightGaussian's global significance; its columns tell how long each Gaussian is seen.

At each step of `prune.at` the `prune.share` least significant Gaussians are removed (every
per-Gaussian tensor, Adam moment and strategy statistic with them, `strategy.remove`) and
training goes on. With `prune.time_weight` w > 0 the ranking is total * (seen fraction)^w, the
seen fraction being the share of training times at which the Gaussian contributes at all: a
Gaussian seen only at few times and weakly goes first.

Stateless functions with shape contracts; the trainer calls `prune_event`.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any, List, Optional

import torch
from torch import Tensor
from ..render import contribution, project_for_render
from .strategy import remove


@dataclass
class PruneConfig:
    """`prune.*`: contribution pruning during training (off while share is 0)."""

    share: float = 0.0  # fraction of the Gaussians removed at each event (0 = off)
    # events: a step (e.g. "1800"), a fraction of optim.iterations in (0, 1) (e.g. "0.9") or
    # "refine_stop" (the step densification stops)
    at: List[str] = field(default_factory=lambda: ["refine_stop", "0.9"])
    # rank by total significance x (fraction of training times seen)^time_weight; 0 = the total alone
    time_weight: float = 0.0


def check_prune_config(p) -> None:
    share, tw = float(p.share), float(p.time_weight)
    if not 0.0 <= share < 1.0:
        raise ValueError(f"prune.share={share}: use a fraction in [0, 1) (0 = no pruning)")
    if tw < 0 or not math.isfinite(tw):
        raise ValueError(f"prune.time_weight={tw}: use a number >= 0 (0 = rank by total significance)")


def prune_steps(p, iterations: int, refine_stop: int) -> list[int]:
    """The steps at which pruning runs (once that many optimizer steps are done, before the next),
    sorted and unique; empty when prune.share is 0. Each entry of prune.at is a step, a fraction of the run in
    (0, 1) or 'refine_stop'."""
    check_prune_config(p)
    if float(p.share) == 0.0:
        return []
    out = []
    for raw in p.at:
        s = str(raw).strip()
        if s == "refine_stop":
            step = int(refine_stop)
        else:
            try:
                v = float(s)
            except ValueError:
                raise ValueError(f"prune.at entry {raw!r}: use a step (e.g. 1800), a fraction of optim.iterations "
                                 "in (0, 1) (e.g. 0.9) or refine_stop") from None
            if 0.0 < v < 1.0:
                step = int(round(v * iterations))
            elif v >= 1.0 and v == int(v):
                step = int(v)
            else:
                raise ValueError(f"prune.at entry {raw!r}: a step must be a whole number >= 1, a fraction in (0, 1)")
        if not 1 <= step < iterations:  # (a step at or after the end would never be followed by training)
            raise ValueError(f"prune.at entry {raw!r} resolves to step {step}, outside [1, optim.iterations="
                             f"{iterations}): pruning there would never be followed by training")
        out.append(step)
    return sorted(set(out))


def time_columns(times) -> tuple[Tensor, dict[float, int]]:
    """(distinct times [T] float64 sorted, time -> column)."""
    ts = sorted({float(t) for t in times})
    return torch.tensor(ts, dtype=torch.float64), {t: i for i, t in enumerate(ts)}


@torch.no_grad()
def significance(model, frames, step: Optional[int] = None) -> tuple[Tensor, Tensor]:
    """(S [N, T] float32 on the model's device, times [T]): each Gaussian's blending weight summed
    over the pixels of every training frame, frames at one time summed into that time's column.
    The model renders as in evaluation (eval mode, no culling: a row below 1/255 scores 0), with
    its own backend's score pass. The model is left in eval mode."""
    model.eval()
    step = model.step if step is None else step
    times, col = time_columns(f.time for f in frames)
    n = model.num_gaussians
    S = torch.zeros(n, times.numel(), device=model.device)
    cs = model.conditioning(step)  # does not depend on the time
    r = model.cfg.render
    for f in frames:
        g = model.deformed(f.time, step, cs)
        cam = f.camera
        proj = project_for_render(g.means, g.quats, g.scales, g.opacities, g.sh, cam, model.sh_degree(step),
                                  backend=model.backend, near=r.near, eps2d=r.eps2d, antialiased=r.antialiased,
                                  compiled_projection=r.get("compiled_projection"))
        s = contribution(proj.means2d, proj.conics, proj.opacities, proj.depths, proj.radii, cam.width,
                         cam.height, tile_size=r.tile_size, backend=model.backend)
        S[:, col[float(f.time)]] += s.float()
    return S, times


def ranking(S: Tensor, time_weight: float = 0.0) -> Tensor:
    """Per-Gaussian value [N] to keep by (the smallest go first): the total significance S.sum(1),
    times (fraction of the T times with S > 0) ** time_weight when time_weight > 0."""
    total = S.sum(1)
    if time_weight > 0:
        seen = (S > 0).float().mean(1)
        total = total * seen.pow(time_weight)
    return total


def select_pruned(rank: Tensor, share: float) -> Tensor:
    """Bool mask [N]: the floor(share * N) rows of smallest rank (ties in index order)."""
    n = rank.shape[0]
    k = min(int(math.floor(share * n)), max(n - 1, 0))  # never the whole model
    mask = torch.zeros(n, dtype=torch.bool, device=rank.device)
    if k > 0:
        order = torch.sort(rank, stable=True).indices
        mask[order[:k]] = True
    return mask


def seen_per_frame(S: Tensor) -> float:
    """Mean over the time columns of the fraction of Gaussians that contribute at that time."""
    if S.numel() == 0:
        return 0.0
    return float((S > 0).float().mean(0).mean())


def prune_event(model, frames, optimizers, strategy_state, p, step: int) -> dict[str, Any]:
    """Score `model` on the training `frames`, remove the `p.share` least significant rows (`p`:
    the prune config; the rows go from the parameter dict, their `optimizers`' moments and the
    densification's `strategy_state`), return the event's record: step, before, after, seen per
    frame (fraction of the model contributing at one time) before and after, and the seconds of the
    score pass and of the whole event."""
    t0 = time.perf_counter()
    S, _ = significance(model, frames, step=step)
    t_score = time.perf_counter() - t0
    mask = select_pruned(ranking(S, float(p.time_weight)), float(p.share))
    before = model.num_gaussians
    rec = {"step": int(step), "before": before, "seen_before": seen_per_frame(S),
           "seen_after": seen_per_frame(S[~mask]), "frames": len(frames)}
    remove(model.params, optimizers, strategy_state, mask)
    rec.update(after=model.num_gaussians, score_seconds=t_score, seconds=time.perf_counter() - t0)
    return rec
