"""Fault tolerance of the training loop (docs/stability.md).

The guard checks every step's loss and gradients, and the parameters whenever it takes a
snapshot. A non-finite value, or a periodic evaluation that falls more than `divergence_db` below
the best one so far, triggers a *recovery*:
* the optimization state is restored from the last good snapshot: parameters, optimizers,
  densification state, sampler, RNG and step. A divergence restores the best evaluation's state;
* every learning rate is multiplied by `lr_factor`;
* training goes on, and the recovery is logged (console, TensorBoard, metrics.json -> guard).

After `max_recoveries` recoveries the run stops with `TrainingDiverged` and a checkpoint of the
last good state.

Snapshots live in memory and are taken at steps that are multiples of `snapshot_every`, and once
when training starts or resumes. If train.checkpoint_every is a multiple of snapshot_every, a
resumed run holds the same last snapshot as the uninterrupted one, so recoveries repeat exactly.
The divergence detector's best snapshot is not saved in checkpoints: after a resume it starts
again from the first evaluation.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Iterable, Optional

import numpy as np
import torch
from torch import Tensor

from .. import extension
from ..device import process_memory_mb
from ..verified import verified_on


def resolve_sync_free(g, device: torch.device, fused_adam: bool) -> bool:
    """Whether this run's step check is the sync-free one (train.guard.sync_free resolved)."""
    if not g.enabled:
        return False
    if g.sync_free is None:
        return fused_adam and device.type in verified_on("train.guard.sync_free")
    if g.sync_free and not fused_adam:
        raise ValueError("train.guard.sync_free=true needs optim.fused_adam=true on a CPU or CUDA device: fused Adam "
                         "is what skips a faulty step's update on the device; set train.guard.sync_free=false "
                         "(or null) to read the check every step")
    return bool(g.sync_free)


def resolve_compiled_check(g, device: torch.device) -> bool:
    """Whether this run's step check is the compiled call (train.guard.compiled resolved)."""
    if not g.enabled:
        return False
    kind = device.type
    return extension.use_compiled("train.guard.compiled", g.compiled, kind,
                                  kind in ("cpu", "cuda"), f"there is no compiled check on {device}")


class TrainingDiverged(RuntimeError):
    """More recoveries than train.guard.max_recoveries."""


MONITORS = ("auto", "val", "train")
#: data formats whose val split is held out from training and distinct from their test split
OWN_VAL_SPLIT = ("dnerf", "procedural")


def monitor_split(g, data_format: str) -> str:
    """The split the divergence detector evaluates (train.guard.monitor resolved for the data
    format). The test split is never one: a detector that reads it lets test images steer training."""
    m = str(g.monitor)
    if m == "test":
        raise ValueError("train.guard.monitor=test: the divergence detector restores earlier states, so the split "
                         "it reads steers training, and test images must not; use auto, val or train")
    if m not in MONITORS:
        raise ValueError(f"train.guard.monitor={m!r}: use one of {', '.join(MONITORS)}")
    own_val = data_format in OWN_VAL_SPLIT
    if m == "auto":
        return "val" if own_val else "train"
    if m == "val" and not own_val:
        raise ValueError(f"train.guard.monitor=val: data.format={data_format} has no val split of its own (its val "
                         "frames are its test frames); use train or auto")
    return m


def nonfinite_flags(tensors: list[Tensor]) -> Tensor:
    """One bool per tensor, on their device: whether it has a non-finite element. No host sync.

    Exact and cheap: each tensor is reduced to its minimum and maximum (one pass, no copy); NaN
    propagates through both and an infinity is one of them, while, unlike a sum, they cannot
    overflow from finite elements."""
    mins, maxs = zip(*(torch.aminmax(t.detach()) for t in tensors))
    return ~(torch.isfinite(torch.stack(mins)) & torch.isfinite(torch.stack(maxs)))


def _checkable(t: Optional[Tensor]) -> bool:
    """What the finiteness checks look at: present, floating, non-empty tensors."""
    return t is not None and t.is_floating_point() and t.numel() > 0


def all_finite(tensors: Iterable[Optional[Tensor]], compiled: bool = False) -> bool:
    """Whether every element of every (floating) tensor is finite; None and empty entries are
    skipped. One host sync. compiled: the CPU extension's check (CPU tensors only)."""
    ts = [t for t in tensors if _checkable(t)]
    if compiled and ts and all(t.device.type == "cpu" for t in ts):
        return not bool(nonfinite_flags_compiled(ts).any())
    return not ts or not bool(nonfinite_flags(ts).any())


# ----------------------------------------------------------------- the compiled check (stdr/csrc/cpu/guard_cpu.h)
def nonfinite_flags_compiled(tensors: list[Tensor]) -> Tensor:
    """One bool per CPU tensor: whether it has a NaN or an infinity (the torch form is
    `nonfinite_flags`)."""
    return extension.load_extension("cpu").nonfinite_flags([t.detach() for t in tensors])


def guard_update_compiled(tensors: list[Tensor], flag: Tensor, bad_step: Tensor, bad_index: Tensor, step: int) -> None:
    """The sync-free guard's per-step update in one call, in place (the torch form is in
    `Guard.flag_step`): when a tensor is non-finite, flag = 1 and, if no step was
    recorded yet (bad_step < 0), bad_step = step and bad_index = the first such tensor's index.
    On the flag's device: the CPU (any floating dtype) or CUDA (float32 tensors; a fill and two
    launches, no host sync)."""
    extension.load_extension(flag.device.type).guard_update([t.detach() for t in tensors], flag, bad_step, bad_index, int(step))


def first_nonfinite(named: Iterable[tuple[str, Optional[Tensor]]]) -> Optional[str]:
    """The name of the first tensor with a non-finite element (None: all finite)."""
    for name, t in named:
        if t is not None and not all_finite([t]):
            return name
    return None


def clone_tree(x: Any) -> Any:
    """A deep copy of nested dicts / lists / tuples whose tensors are cloned (detached)."""
    if torch.is_tensor(x):
        return x.detach().clone()
    if isinstance(x, dict):
        return {k: clone_tree(v) for k, v in x.items()}
    if isinstance(x, list):
        return [clone_tree(v) for v in x]
    if isinstance(x, tuple):
        return tuple(clone_tree(v) for v in x)
    return x


@dataclass
class Guard:
    """The guard the training loop calls: its state (saved in checkpoints, except the snapshots)
    and what it does with it. The loop asks it to `check_step` after each backward, to take a
    `snapshot` every train.guard.snapshot_every steps, to judge each monitor evaluation
    (`after_evaluation`) and to `recover`. It reaches the run through the `RunState` it is given
    (stdr.train.state: parameters and gradients, `payload` / `restore`, `save`) and writes to the
    run's `RunLog`; `cfg` is the run's train.guard node (None: a guard read back for a report)."""

    lr_scale: float = 1.0
    recoveries: list[dict[str, Any]] = field(default_factory=list)
    peak_gaussians: int = 0
    peak_memory_mb: Optional[float] = None  # process_memory_mb's largest sample
    monitor: Optional[str] = None  # the divergence detector's split (None: no detector in this run)
    best: Optional[dict[str, Any]] = None          # the best periodic evaluation: {step, psnr}
    snapshot: Optional[dict[str, Any]] = None      # last good state (a checkpoint payload, cloned)
    best_snapshot: Optional[dict[str, Any]] = None  # the state at `best`
    fired: set = field(default_factory=set)        # injected faults already fired (this process)
    checks: bool = False     # whether this run checks its steps (train.guard.enabled)
    sync_free: bool = False  # ... without a host sync (resolve_sync_free); not saved: each run's own
    compiled: bool = False   # ... with the compiled call (resolve_compiled_check); not saved either
    # the sync-free check's device-side state (None until its first step; cleared by each read):
    # found_inf for fused Adam (float 0-d, 1 from the first faulty step on), that step (-1: none),
    # the index of its first non-finite tensor, and the tensors' names from each step they changed
    flag: Optional[Tensor] = None
    bad_step: Optional[Tensor] = None
    bad_index: Optional[Tensor] = None
    names: list = field(default_factory=list)
    cfg: Any = None  # train.guard of the run (not saved)

    def state_dict(self) -> dict[str, Any]:
        # forms: how this run checked its steps, for the report of a re-evaluation (`from_state`);
        # a resumed run checks as its own config says (load_state_dict leaves them alone)
        return {"lr_scale": self.lr_scale, "recoveries": list(self.recoveries), "peak_gaussians": self.peak_gaussians,
                "peak_memory_mb": self.peak_memory_mb, "monitor": self.monitor,
                "forms": {"checks": self.checks, "sync_free": self.sync_free, "compiled": self.compiled}}

    @classmethod
    def from_state(cls, s: dict[str, Any]) -> "Guard":
        """The guard of a saved run, for its report (metrics.json -> guard): its state and how it
        checked its steps, as the checkpoint recorded them."""
        g = cls()
        g.load_state_dict(s)
        forms = s.get("forms") or {}
        g.checks, g.sync_free, g.compiled = (bool(forms.get(k, False)) for k in ("checks", "sync_free", "compiled"))
        return g

    def load_state_dict(self, s: dict[str, Any]) -> None:
        self.lr_scale = float(s.get("lr_scale", 1.0))
        self.recoveries = list(s.get("recoveries", []))
        self.peak_gaussians = int(s.get("peak_gaussians", 0))
        self.peak_memory_mb = s.get("peak_memory_mb")
        self.monitor = s.get("monitor")  # the divergence detector's split, as the run recorded it

    def note_memory(self, device: torch.device) -> Optional[float]:
        mb = process_memory_mb(device)
        if mb is not None:
            self.peak_memory_mb = max(self.peak_memory_mb or 0.0, mb)
        return mb

    def summary(self, cap: Optional[int]) -> dict[str, Any]:
        """metrics.json -> guard."""
        return {"recoveries": list(self.recoveries), "n_recoveries": len(self.recoveries),
                "lr_scale": self.lr_scale, "peak_gaussians": self.peak_gaussians, "max_gaussians": cap,
                "peak_memory_mb": self.peak_memory_mb, "monitor": self.monitor,
                "check": ("sync-free" if self.sync_free else "every step") if self.checks else None,
                "compiled_check": self.compiled if self.checks else None}

    # ------------------------------------------------------------------ what the loop calls
    def _step_tensors(self, state, loss: Tensor, step: int) -> list[tuple[str, Tensor]]:
        """The loss and every gradient of step `step`, named; train.guard.inject_nan_grad_at puts a
        NaN into the gradient of the means first."""
        params = state.model.params
        if step in self.cfg.inject_nan_grad_at and ("nan", step) not in self.fired:
            self.fired.add(("nan", step))
            if params["means"].grad is not None:
                params["means"].grad[0, 0] = float("nan")
        named = [("loss", loss)] + [(f"grad of {k}", p.grad) for k, p in params.items()] + \
            [(f"grad of {k}", p.grad) for k, p in state.network_params()]
        return [(n, t) for n, t in named if _checkable(t)]

    def check_step(self, state, loss: Tensor, step: int) -> Optional[str]:
        """After the backward of step `step`: what is non-finite (the loss, or the gradient of a
        named parameter), or None. One host sync."""
        named = self._step_tensors(state, loss, step)
        return None if all_finite((t for _, t in named), self.compiled) else f"non-finite {first_nonfinite(named)}"

    def flag_step(self, state, loss: Tensor, step: int) -> Tensor:
        """The sync-free form of `check_step`: the verdict stays on the device. Returns the flag
        for fused Adam's found_inf (1 from the first faulty step on, so that no update is applied
        until `poll` reads it); the first faulty step and what failed are kept for `poll`."""
        named = self._step_tensors(state, loss, step)
        names = tuple(n for n, _ in named)
        if self.flag is None:
            self.flag = torch.zeros((), dtype=torch.float32, device=loss.device)
            self.bad_step = torch.full((), -1, dtype=torch.int64, device=loss.device)
            self.bad_index = torch.full((), -1, dtype=torch.int64, device=loss.device)
        if not self.names or self.names[-1][1] != names:
            self.names.append((step, names))
        ts = [t for _, t in named]
        if self.compiled and (loss.device.type == "cpu" or all(t.dtype == torch.float32 for t in ts)):
            # the torch operators' update below, in one call
            guard_update_compiled(ts, self.flag, self.bad_step, self.bad_index, step)
            return self.flag
        bad = nonfinite_flags(ts)
        anybad = bad.any()
        new = anybad & (self.bad_step < 0)
        self.bad_step = torch.where(new, step, self.bad_step)
        self.bad_index = torch.where(new, bad.to(torch.int32).argmax(), self.bad_index)
        self.flag = torch.maximum(self.flag, anybad.to(torch.float32))
        return self.flag

    def poll(self) -> Optional[tuple[int, str]]:
        """Read the sync-free check (one host sync): (the first faulty step since the last read, what
        was non-finite) or None. Clears it either way."""
        if self.bad_step is None:
            return None
        step, index = int(self.bad_step), int(self.bad_index)
        names = self.names
        self.clear()
        if step < 0:
            return None
        return step, f"non-finite {next(n for s, n in reversed(names) if s <= step)[index]}"

    def clear(self) -> None:
        """Forget the sync-free check's state (after a read, a recovery or a load)."""
        self.flag = self.bad_step = self.bad_index = None
        self.names = []

    def take_snapshot(self, state, log) -> None:
        """Keep the current state as the last good one (after checking the parameters)."""
        named = [(f"parameter {k}", p) for k, p in state.model.params.items()] + \
            [(f"parameter of {k}", p) for k, p in state.network_params()]
        if not all_finite(t for _, t in named):
            self.recover(state, log, f"non-finite {first_nonfinite(named)}")
        else:
            self.snapshot = clone_tree(state.payload())

    def after_evaluation(self, state, log, psnr: float, after_reset: bool = False) -> None:
        """The divergence detector: a new best is kept (with its state); a drop of more than
        train.guard.divergence_db below the best restores the best one's state. `after_reset`: the
        evaluation lies within train.guard.after_reset steps of an opacity reset, so it is only
        checked for being finite (the reset's drop is planned; it is neither a best nor a divergence)."""
        gc = self.cfg
        if not np.isfinite(psnr):
            self.recover(state, log, f"non-finite evaluation PSNR ({psnr})")
        elif after_reset:
            return
        elif self.best is None or psnr > self.best["psnr"]:
            self.best = {"step": state.step, "psnr": float(psnr)}
            self.best_snapshot = clone_tree(state.payload())
        elif gc.divergence_db > 0 and psnr < self.best["psnr"] - gc.divergence_db:
            self.recover(state, log, f"divergence: evaluation PSNR {psnr:.2f} dB is more than {gc.divergence_db:g} dB "
                                     f"below the best, {self.best['psnr']:.2f} dB at step {self.best['step']}", best=True)

    def recover(self, state, log, reason: str, best: bool = False, step: Optional[int] = None) -> None:
        """Restore the last good state (the best evaluation's with best=True), lower every lr
        by train.guard.lr_factor and log it; past train.guard.max_recoveries, save the last good
        state as the checkpoint and stop (TrainingDiverged). `step`: the faulty step when it came
        before the step that found it (the sync-free check; default: now)."""
        gc = self.cfg
        found_at = state.step
        detected = found_at if step is None else step
        self.clear()
        snap = self.best_snapshot if best and self.best_snapshot is not None else self.snapshot
        if snap is None:
            raise TrainingDiverged(f"{reason} at step {detected}, before any good state was kept")
        seconds, history = state.train_seconds, state.history  # time spent and evaluations made stay
        state.restore(clone_tree(snap), "guard snapshot")
        state.train_seconds, state.history = seconds, history
        if best:
            self.snapshot = clone_tree(snap)  # later states are not good ones
        stop = len(self.recoveries) >= gc.max_recoveries
        if not stop:
            self.lr_scale *= gc.lr_factor
        rec = {"step": detected, "found_at": found_at, "restored_to": state.step, "reason": reason,
               "lr_scale": self.lr_scale, "train_seconds": state.train_seconds, "stopped": stop}
        self.recoveries.append(rec)
        log.scalar("guard/recoveries", len(self.recoveries), detected)
        log.scalar("guard/lr_scale", self.lr_scale, detected)
        if stop:
            state.save()
            raise TrainingDiverged(
                f"training stopped at step {detected}: {reason}, after {len(self.recoveries) - 1} recoveries "
                f"(train.guard.max_recoveries={gc.max_recoveries}). The last good state (iteration {state.step}) is "
                f"saved in {state.checkpoint_path}; lower the learning rates (optim.*, baseline.lr_init) or raise "
                "train.guard.max_recoveries, then run again to resume from it")
        print(f"[stdr] guard: {reason} at step {detected}; restored iteration {state.step}, learning rates x "
              f"{self.lr_scale:g} (recovery {len(self.recoveries)} of at most {gc.max_recoveries})", flush=True)
