"""The optimizers' helpers: one step over several fused Adams with fewer operator launches
(`adam_step`, `clear_grads`), and the learning-rate schedule (`exp_lr`).

The trainer keeps one `torch.optim.Adam` per per-Gaussian parameter (densification edits each
one's state by key, as gsplat's strategies do) and one for the networks. Stepping them one by one
launches, per optimizer, a step-count increment, the fused Adam kernel, a decrement when a
`found_inf` flag is given, and two profiler records for `step()` and two for `zero_grad()`.
`adam_step` launches one increment over every step count, one fused kernel per parameter group
(each group has its own learning rate) and one decrement: the same kernels on the same tensors,
so the result is bit-identical to calling each optimizer's `step()` (tests/test_adam.py).
"""
from __future__ import annotations

import math
from typing import Iterable, Optional

import torch
from torch import Tensor

from ..errors import ConfigError


def _fusable(opt: torch.optim.Optimizer) -> bool:
    """A plain torch Adam whose every group is fused, not differentiable, without capturable
    state and without amsgrad (so the fused kernel's arguments are the group's)."""
    return type(opt) is torch.optim.Adam and all(
        g.get("fused") and not g.get("differentiable") and not g.get("amsgrad") and not g.get("capturable")
        for g in opt.param_groups)


@torch.no_grad()
def adam_step(optimizers: Iterable[torch.optim.Optimizer], found_inf: Optional[Tensor] = None) -> None:
    """Step every optimizer of `optimizers` as its own `step()` would, with `found_inf` (a 0-d
    float tensor, 1 where this step's gradients are not to be applied: torch's fused Adam then
    leaves parameters, moments and step counts as they were) read by each. Optimizers that are
    not plain fused Adams are stepped by their own `step()`; parameters without a gradient are
    not updated and get no state, as in `step()`."""
    work = []  # (group, params, grads, exp_avgs, exp_avg_sqs, steps)
    for opt in optimizers:
        if not _fusable(opt):
            opt.found_inf = found_inf
            opt.step()
            continue
        for group in opt.param_groups:
            params, grads, avgs, sqs, steps = [], [], [], [], []
            for p in group["params"]:
                if p.grad is None:
                    continue
                if p.grad.is_sparse:
                    raise RuntimeError("adam_step: sparse gradients are not supported (torch's Adam neither)")
                state = opt.state[p]
                if len(state) == 0:  # as Adam._init_group creates it for a fused group
                    state["step"] = torch.zeros((), dtype=torch.float32, device=p.device)
                    state["exp_avg"] = torch.zeros_like(p, memory_format=torch.preserve_format)
                    state["exp_avg_sq"] = torch.zeros_like(p, memory_format=torch.preserve_format)
                params.append(p)
                grads.append(p.grad)
                avgs.append(state["exp_avg"])
                sqs.append(state["exp_avg_sq"])
                steps.append(state["step"])
            if params:
                work.append((group, params, grads, avgs, sqs, steps))
    if not work:
        return
    by_device: dict[torch.device, list[Tensor]] = {}
    for *_, steps in work:
        for s in steps:
            by_device.setdefault(s.device, []).append(s)
    flags = {} if found_inf is None else {d: found_inf.to(d, non_blocking=True) for d in by_device}
    for steps in by_device.values():
        torch._foreach_add_(steps, 1)
    for group, params, grads, avgs, sqs, steps in work:
        beta1, beta2 = group["betas"]
        kernel = torch._fused_adamw_ if group.get("decoupled_weight_decay") else torch._fused_adam_
        devices = {p.device for p in params}
        if len(devices) != 1 or len({p.dtype for p in params}) != 1:
            raise RuntimeError("adam_step: a parameter group spans devices or dtypes; keep each group on one "
                               "device and dtype (the trainer's groups are)")
        dev = devices.pop()
        kernel(params, grads, avgs, sqs, [], steps, amsgrad=False, lr=group["lr"], beta1=float(beta1),
               beta2=float(beta2), weight_decay=group["weight_decay"], eps=group["eps"],
               maximize=group["maximize"], grad_scale=None, found_inf=flags.get(dev))
    for d, steps in by_device.items():
        if d in flags:
            torch._foreach_sub_(steps, [flags[d]] * len(steps))


def clear_grads(optimizers: Iterable[torch.optim.Optimizer]) -> None:
    """`zero_grad(set_to_none=True)` of each optimizer, without its profiler records."""
    for opt in optimizers:
        for group in opt.param_groups:
            for p in group["params"]:
                p.grad = None


def exp_lr(step: int, lr_init: float, lr_final: float, max_steps: int) -> float:
    """Log-linear interpolation from lr_init (step 0) to lr_final (step >= max_steps), as in 3DGS."""
    if max_steps <= 0 or lr_init == lr_final:
        return lr_final
    s = min(max(step / max_steps, 0.0), 1.0)
    return math.exp(math.log(lr_init) * (1 - s) + math.log(lr_final) * s)


# ----------------------------------------------------------------- the run's optimizers
def uses_fused_adam(cfg, device: torch.device) -> bool:
    """optim.fused_adam: torch's fused Adam (one kernel per parameter instead of ~10 elementwise
    passes) where torch has it (CPU and CUDA)."""
    return bool(cfg.optim.get("fused_adam", True)) and device.type in ("cpu", "cuda")


def gaussian_lr(cfg, model, key: str, step: int, lrs: dict[str, float] | None = None) -> float:
    """The learning rate of per-Gaussian parameter `key` at `step`: 3DGS's schedule for the six
    Gaussian tensors, the owner's (the deformation module or a plug-in) for one it added."""
    o = cfg.optim
    s = o.spatial_lr_scale
    if key == "means":
        return exp_lr(step, o.means_lr_init * s, o.means_lr_final * s, o.means_lr_max_steps)
    fixed = {"scales": o.scales_lr * s, "quats": o.quats_lr, "opacities": o.opacities_lr,
             "sh0": o.sh0_lr, "shN": o.shN_lr}
    if key in fixed:
        return fixed[key]
    lrs = gaussian_lrs(model) if lrs is None else lrs
    if key in lrs:
        return lrs[key]
    owners = ", ".join(type(o).__name__ for o in [model.deform, *model.plugins])
    raise ConfigError(f"per-Gaussian parameter {key!r} has no learning rate: the module whose init_gaussians adds "
                      f"it must give its rate in param_groups, as {{'key': {key!r}, 'lr': ...}} (asked: {owners}; "
                      "docs/baselines.md, 'Adding a baseline')")


def gaussian_lrs(model) -> dict[str, float]:
    """The rates the deformation module and the plug-ins give their per-Gaussian tensors (the
    {"key", "lr"} entries of their param_groups)."""
    out: dict[str, float] = {}
    for owner in [model.deform, *model.plugins]:
        for g in owner.param_groups():
            if "key" in g:
                out.setdefault(g["key"], float(g["lr"]))
    return out


def make_optimizers(cfg, model, fused: bool) -> dict[str, torch.optim.Optimizer]:
    """One Adam per per-Gaussian parameter, including those a plug-in freezes for a phase, so the
    optimizer set does not depend on the step; a parameter without a gradient is not updated."""
    frozen = model.frozen_keys()
    return {k: torch.optim.Adam([{"params": [p], "lr": gaussian_lr(cfg, model, k, 0), "name": k}], eps=1e-15,
                                fused=fused)
            for k, p in model.params.items() if k not in frozen}


def net_groups(model) -> list[dict]:
    """Network parameter groups: the deformation's (each with an lr multiplier on the baseline's
    schedule), then each plug-in's (the baseline's schedule, or their own)."""
    groups = [dict(g) for g in model.deform.param_groups() if "key" not in g]
    for p in model.plugins:
        groups += [dict(g) for g in p.param_groups() if "key" not in g]
    return groups


def net_lr(cfg, g: dict, step: int) -> float:
    """The learning rate of network group `g` at `step`: its own schedule when it gives one, else
    the baseline's (from the warm-up's end with baseline.lr_from_warmup) times its multiplier."""
    if "lr_init" in g:
        s = max(step - int(g.get("lr_delay", 0)), 0)
        return exp_lr(s, g["lr_init"], g["lr_final"], int(g["lr_max_steps"]))
    b = cfg.baseline
    s = max(step - b.warmup, 0) if b.lr_from_warmup else step
    return exp_lr(s, b.lr_init, b.lr_final, b.lr_max_steps) * g.get("lr_mult", 1.0)


def update_lrs(cfg, state, groups: list[dict], step: int) -> None:
    """Every optimizer's learning rate at `step`, times the guard's scale (1 until a recovery
    lowers it, train.guard.lr_factor); `groups`: net_groups of the run's model."""
    scale = state.guard.lr_scale
    lrs = gaussian_lrs(state.model)  # the owners' constant rates, read once a step
    for k, opt in state.optimizers.items():
        for g in opt.param_groups:
            g["lr"] = gaussian_lr(cfg, state.model, k, step, lrs) * scale
    for spec, g in zip(groups, state.net_opt.param_groups):
        g["lr"] = net_lr(cfg, spec, step) * scale
