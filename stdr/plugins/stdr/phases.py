"""STDR's phases: mask warm-up, regularized phase and freeze, resolved from the config and placed
in the run's one schedule; the mask's and opacity's initial values."""
from __future__ import annotations

import math
from enum import IntEnum
from typing import Optional

from ...schedule import Event, keep_out_of_windows


class Phase(IntEnum):
    WARMUP = 0       # [0, warmup_end): opacity frozen (stdr.freeze_opacity), mask trains, regularized
    REGULARIZED = 1  # [warmup_end, freeze_at): opacity and mask train, regularized
    FROZEN = 2       # [freeze_at, end): mask frozen, separated field on


def resolve_phases(stdr_cfg, baseline_warmup: int, iterations: int) -> tuple[int, int]:
    """(warmup_end, freeze_at) by `stdr.phase_rule`; explicit warmup_end / freeze_at win.

    static_warmup: the baseline's static warm-up, and twice it (the paper's 3000 / 6000 at
    Deformable 3DGS's 3000-step warm-up). fraction: the paper's share of the run,
    warmup_fraction / freeze_fraction of `iterations` (3000 / 40000, 6000 / 40000).
    """
    rule = stdr_cfg.phase_rule
    if rule == "static_warmup":
        w_auto = int(baseline_warmup)
    elif rule == "fraction":
        w_auto = int(round(stdr_cfg.warmup_fraction * iterations))
    else:
        raise ValueError(f"stdr.phase_rule={rule!r}: use 'static_warmup' or 'fraction'")
    w = w_auto if stdr_cfg.warmup_end is None else int(stdr_cfg.warmup_end)
    if stdr_cfg.freeze_at is not None:
        f = int(stdr_cfg.freeze_at)
    elif rule == "fraction" and stdr_cfg.warmup_end is None:
        f = int(round(stdr_cfg.freeze_fraction * iterations))
    else:
        f = 2 * w
    if w < 0 or f < w:
        raise ValueError(f"stdr.warmup_end={w} and stdr.freeze_at={f}: need 0 <= warmup_end <= freeze_at")
    if f == 0 and stdr_cfg.mask:
        raise ValueError("stdr.freeze_at resolves to 0, which freezes the mask at its initial value before it "
                         "ever trains (stdr.warmup_end=0 gives freeze_at = 2 x 0). Set stdr.freeze_at to a step "
                         "> 0, or switch the mask off with stdr.mask=false")
    return w, f


def phase_at(step: int, warmup_end: int, freeze_at: int) -> Phase:
    if step >= freeze_at:
        return Phase.FROZEN
    return Phase.WARMUP if step < warmup_end else Phase.REGULARIZED


def logit(p: float) -> float:
    return math.log(p / (1.0 - p))


def resolve_init(cfg, init_opacity: float) -> tuple[Optional[float], float]:
    """(opacity the Gaussians start with, or None to keep model.init_opacity; initial mask logit).

    stdr.mask_init=null: the logit that makes sigmoid(o) * sigmoid(m) equal to model.init_opacity
    at the start, so the mask, not the frozen opacity, carries the opacity during the warm-up
    (it needs stdr.opacity_init > model.init_opacity)."""
    o = cfg.opacity_init
    if o is not None and not 0.0 < o < 1.0:
        raise ValueError(f"stdr.opacity_init={o}: must lie in (0, 1), or be null (model.init_opacity)")
    if cfg.mask_init is not None:
        return o, float(cfg.mask_init)
    base = init_opacity if o is None else o
    if init_opacity >= base:
        raise ValueError(f"stdr.mask_init=null needs stdr.opacity_init > model.init_opacity ({init_opacity}), "
                         f"got {o}: the mask can only lower opacity")
    return o, logit(init_opacity / base)


def add_stages(pcfg, schedule) -> dict:
    """Mask warm-up, regularized phase and freeze (resolve_phases), the freeze kept out of the
    baseline's switch windows (stdr.schedule.keep_out_of_windows): the events and notes go into
    `schedule`, the resolved values are returned (Plugin.stages)."""
    total = schedule.iterations
    w, f = resolve_phases(pcfg, schedule.static_warmup_end, total)
    f, moved = keep_out_of_windows(f, w, schedule.windows, "stdr.freeze_at", explicit=pcfg.freeze_at is not None)
    if f >= total:
        schedule.never_trains(f"STDR's freeze resolves to step {f}, at or after the run's end (optim.iterations="
                              f"{total}): the mask never freezes and the separated field never feeds the "
                              "network in this run. Set stdr.freeze_at (or stdr.warmup_end) below the end, or "
                              "use stdr.phase_rule=fraction")
    held = "opacity frozen" if pcfg.freeze_opacity else "opacity trains"
    schedule.events.append(Event(0, "stdr", f"STDR mask warm-up ({held}), L_temp and L_spatial on"))
    schedule.events.append(Event(w, "stdr.warmup_end", "STDR warm-up ends" + (
        ": opacity trains again, mask still regularized" if pcfg.freeze_opacity else
        " (no change: stdr.freeze_opacity=false)")))
    schedule.events.append(Event(f, "stdr.freeze_at" + (" (moved)" if moved else ""),
                                 "STDR mask frozen, regularizers off, separated field feeds the network"))
    if moved:
        schedule.notes.append(f"STDR freeze moved {moved}")
    return {"warmup_end": w, "freeze_at": f, "freeze_moved": moved}
