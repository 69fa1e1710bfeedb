"""Wall time per named section of a training step (the run's train_profile.json)."""
from __future__ import annotations

import time
from collections import defaultdict
from contextlib import contextmanager
from typing import Optional

import torch
from torch import Tensor

from ..device import synchronize


class Profiler:
    """Accumulated wall time per named section of the training step.

    For benchmarks (`stdr-tool bench-train`): `device` set synchronizes it at every section
    boundary (CUDA runs asynchronously, so unsynchronized sections measure launches), and
    `split_backward` splits the backward at the tensors given to `watch`: each watched group
    names the part of the backward that ends when the gradient reaches the group (the last of
    its tensors); what follows the last group is `after`. The parts go to `backward_parts`, not
    into `seconds` (they are inside "backward"). Both are off in training: no hooks, no syncs."""

    def __init__(self, split_backward: bool = False, device: Optional[torch.device] = None,
                 after: str = "rest"):
        self.seconds: dict[str, float] = defaultdict(float)
        self.backward_parts: dict[str, float] = defaultdict(float)
        self.split_backward, self.device, self.after = split_backward, device, after
        self._marks: dict[str, float] = {}

    def _now(self) -> float:
        if self.device is not None:
            synchronize(self.device)
        return time.perf_counter()

    @contextmanager
    def __call__(self, name: str):
        t0 = self._now()
        yield
        self.seconds[name] += self._now() - t0

    def watch(self, name: str, tensors) -> None:
        """With split_backward: mark when the backward has reached `tensors` (those computed in
        this step's graph; a leaf's hook would outlive the step, so leaves are not watched)."""
        if not self.split_backward:
            return
        for t in tensors:
            if isinstance(t, Tensor) and t.requires_grad and t.grad_fn is not None:
                t.register_hook(lambda grad, n=name: self._mark(n))

    def _mark(self, name: str) -> None:
        self._marks[name] = self._now()

    def backward(self, loss: Tensor) -> None:
        """loss.backward() timed as "backward", split at the watched groups when asked."""
        t0 = self._now()
        loss.backward()
        t1 = self._now()
        self.seconds["backward"] += t1 - t0
        prev = t0
        for name, tm in sorted(self._marks.items(), key=lambda kv: kv[1]):
            self.backward_parts[name] += tm - prev
            prev = tm
        if self._marks:
            self.backward_parts[self.after] += t1 - prev
        self._marks.clear()

    def summary(self, iterations: int) -> dict:
        """train_profile.json: seconds and share per section over `iterations` timed steps."""
        tot = sum(self.seconds.values()) or 1.0
        out = {"seconds": dict(self.seconds), "fraction": {k: v / tot for k, v in self.seconds.items()},
               "iterations_timed": iterations}
        if self.backward_parts:
            out["backward_parts"] = dict(self.backward_parts)
        return out
