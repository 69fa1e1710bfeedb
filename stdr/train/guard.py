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

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, List, Optional

import torch
from torch import Tensor


@dataclass
class GuardConfig:
    """train.guard: non-finite and divergence recovery."""

    # on by default: without a fault it changes nothing (tests/test_guard.py: bit-identical to
    # enabled=false for deform and every baseline with STDR) and costs 0.2-0.6 % of a step
    enabled: bool = True
    snapshot_every: int = 100    # steps between in-memory snapshots of the last good state
    lr_factor: float = 0.5       # every learning rate x this at each recovery
    max_recoveries: int = 3      # one more stops the run (TrainingDiverged, checkpoint of the last good state)
    # a periodic evaluation (train.eval_every) more than this many dB below the best one so far
    # restores the best one's state (0 = off)
    divergence_db: float = 10.0
    # what the divergence detector evaluates. It restores earlier states, so what it reads steers
    # training, and it never reads the test split: auto = val where the scene has a val split of
    # its own (D-NeRF, the embedded scene), else train (Nerfies format: its val frames are its
    # test frames); or val, or train (a fixed seeded subset of the training frames)
    monitor: str = "auto"
    # frames of the detector's own evaluation (a fixed seeded subset; 0 = all). When the monitor
    # split is data.eval_split, the periodic evaluation itself is used (train.eval_frames)
    monitor_frames: int = 10
    # fault injection, for tests and drills: a NaN in the gradient of the means at each step
    # listed (counted from 1), once per process
    inject_nan_grad_at: List[int] = field(default_factory=list)


class TrainingDiverged(RuntimeError):
    """More recoveries than train.guard.max_recoveries."""


def check_guard_config(g) -> None:
    """Errors that name the key, for values that cannot work."""
    if g.snapshot_every < 1:
        raise ValueError(f"train.guard.snapshot_every={g.snapshot_every}: must be at least 1")
    if not 0.0 < g.lr_factor <= 1.0:
        raise ValueError(f"train.guard.lr_factor={g.lr_factor}: must be in (0, 1] (each recovery multiplies "
                         "every learning rate by it)")
    if g.max_recoveries < 0:
        raise ValueError(f"train.guard.max_recoveries={g.max_recoveries}: must be 0 or more")
    if g.divergence_db < 0:
        raise ValueError(f"train.guard.divergence_db={g.divergence_db}: must be 0 (off) or positive")
    if g.monitor_frames < 0:
        raise ValueError(f"train.guard.monitor_frames={g.monitor_frames}: must be 0 (all frames) or positive")


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


def all_finite(tensors: Iterable[Optional[Tensor]]) -> bool:
    """Whether every element of every (floating) tensor is finite; None entries are skipped.

    Fast and exact: a tensor's sum is finite only if all its elements are (inf and NaN
    propagate through addition), so one small reduction per tensor decides; only a sum that
    overflowed from finite elements is looked at element by element."""
    ts = [t.detach() for t in tensors if t is not None and t.is_floating_point()]
    if not ts:
        return True
    sums = torch.stack([t.sum(dtype=torch.float32) for t in ts])
    ok = torch.isfinite(sums)
    if bool(ok.all()):
        return True
    return all(bool(torch.isfinite(t).all()) for t, good in zip(ts, ok.tolist()) if not good)


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


def process_memory_mb(device: torch.device) -> Optional[float]:
    """The training's memory now, in MiB: on CUDA the peak torch allocated on `device` since the
    run reset it (Trainer.train); elsewhere the process's resident set (Linux /proc/self/statm),
    which also holds what earlier runs of the same process (an in-process multirun) left behind.
    None where neither can be read."""
    if device.type == "cuda":
        return torch.cuda.max_memory_allocated(device) / 2**20
    try:
        pages = int(Path("/proc/self/statm").read_text().split()[1])  # [1]: resident pages
        return pages * os.sysconf("SC_PAGE_SIZE") / 2**20
    except (OSError, ValueError, IndexError, AttributeError):
        return None


MEMORY_CONVENTION = {"cuda": "torch.cuda.max_memory_allocated since the run began",
                     "cpu": "resident set of the process (/proc/self/statm), sampled every train.log_every steps"}


@dataclass
class GuardState:
    """What the guard keeps across recoveries (saved in checkpoints, except the snapshots)."""

    lr_scale: float = 1.0
    recoveries: list[dict[str, Any]] = field(default_factory=list)
    peak_gaussians: int = 0
    peak_memory_mb: Optional[float] = None  # process_memory_mb's largest sample
    monitor: Optional[str] = None  # the divergence detector's split (None: no detector in this run)
    best: Optional[dict[str, Any]] = None          # the best periodic evaluation: {step, psnr}
    snapshot: Optional[dict[str, Any]] = None      # last good state (a checkpoint payload, cloned)
    best_snapshot: Optional[dict[str, Any]] = None  # the state at `best`
    fired: set = field(default_factory=set)        # injected faults already fired (this process)

    def state_dict(self) -> dict[str, Any]:
        return {"lr_scale": self.lr_scale, "recoveries": list(self.recoveries), "peak_gaussians": self.peak_gaussians,
                "peak_memory_mb": self.peak_memory_mb, "monitor": self.monitor}

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
                "peak_memory_mb": self.peak_memory_mb, "monitor": self.monitor}
