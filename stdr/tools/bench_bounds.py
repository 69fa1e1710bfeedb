"""Each section of a training step against its bound (`stdr-tool bench-train`'s second table).

The machine's two limits are measured where the step runs: the matrix-multiply rate (a 2048²
`torch.mm`, in fp32 and in bf16) and the memory bandwidth (a 256 MiB `copy_`, its bytes read plus
written). One more training step then runs under `Tally`, which sees every ATen operator the step
dispatches, forward and backward, and every call of the compiled extension:

* an operator's FLOPs are its matrix products' (torch.utils.flop_counter's formulas: mm, addmm,
  bmm, convolutions, ...), at the rate of its inputs' precision (bf16 or half: the bf16 rate);
* its bytes are those of its tensor arguments and results, each counted once, plus the arguments it
  writes in place; a view, an alias or an allocation moves nothing; a compiled kernel's bytes are
  those of its tensor arguments and results;
* its bound is the larger of FLOPs / rate and bytes / bandwidth (the roofline of one operator).

A section's bound is the sum over its operators: the time the step's operators, as the code calls
them, would take if each ran at the machine's limit for it. A ratio well above 1 names a section
whose operators run far from the machine's limits (time to make them faster); a fusion that removes
a round trip through memory lowers the bound as well as the time. The backward is split as the
timing splits it (stdr.train.timing.Profiler's watched groups).
"""
from __future__ import annotations

import statistics
import time
from collections import defaultdict
from contextlib import contextmanager

import torch
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_leaves
from torch.utils.flop_counter import flop_registry

from ..device import synchronize
from ..extension import observe_calls
from ..train.timing import Profiler

#: operators that allocate or alias without reading or writing a tensor's data
MOVES_NOTHING = frozenset({"empty", "empty_like", "empty_strided", "new_empty", "new_empty_strided",
                           "detach", "lift_fresh", "alias", "set_", "resize_", "_local_scalar_dense"})
LOW_PRECISION = (torch.bfloat16, torch.float16)
OUTSIDE = "outside the sections"


def mm_reference(device: torch.device, n: int = 2048, repeats: int = 5, dtype=torch.float32) -> float:
    """Median milliseconds of one n x n torch.mm in `dtype` on `device` (the machine's yardstick)."""
    a = torch.randn(n, n, device=device).to(dtype)
    b = torch.randn(n, n, device=device).to(dtype)
    torch.mm(a, b)
    times = []
    for _ in range(repeats):
        synchronize(device)
        t0 = time.perf_counter()
        torch.mm(a, b)
        synchronize(device)
        times.append(time.perf_counter() - t0)
    return statistics.median(times) * 1e3


def copy_bandwidth(device: torch.device, mib: int = 256, repeats: int = 5) -> float:
    """Bytes per second of a `mib` MiB float32 copy_ (read + write), the median of `repeats`."""
    src = torch.ones(mib * 2 ** 18, device=device)
    dst = torch.empty_like(src)
    dst.copy_(src)
    times = []
    for _ in range(repeats):
        synchronize(device)
        t0 = time.perf_counter()
        dst.copy_(src)
        synchronize(device)
        times.append(time.perf_counter() - t0)
    return 2 * src.numel() * src.element_size() / statistics.median(times)


def machine_rates(device: torch.device) -> dict:
    """{"fp32", "bf16"}: FLOP/s of a 2048² torch.mm in each; "bandwidth": bytes/s of a copy."""
    n = 2048
    return {"fp32": 2 * n ** 3 / (mm_reference(device, n) * 1e-3),
            "bf16": 2 * n ** 3 / (mm_reference(device, n, dtype=torch.bfloat16) * 1e-3),
            "bandwidth": copy_bandwidth(device)}


def nbytes(t: torch.Tensor) -> int:
    """A tensor's data bytes (an expanded view counts its storage once)."""
    size = t.numel() * t.element_size()
    try:
        return min(size, t.untyped_storage().nbytes())
    except (RuntimeError, NotImplementedError):  # no storage (a subclass): its logical size
        return size


def _tensors(tree) -> list:
    return [t for t in tree_leaves(tree) if isinstance(t, torch.Tensor)]


def _unique_bytes(tensors) -> int:
    seen, total = set(), 0
    for t in tensors:
        key = (t.data_ptr(), t.storage_offset(), tuple(t.shape), t.dtype)
        if key not in seen:
            seen.add(key)
            total += nbytes(t)
    return total


class Tally(TorchDispatchMode):
    """FLOPs, bytes and bound (seconds) of the operators dispatched while it is open, per section
    (`section`, set by WorkProfiler) and, in the backward, per part of it."""

    def __init__(self, rates: dict):
        super().__init__()
        self.rates = rates
        self.section = OUTSIDE
        self.sections: dict[str, list] = defaultdict(lambda: [0.0, 0.0, 0.0, 0.0])  # flops, bytes, bound s, FLOP-limited s
        self.parts: dict[str, list] = defaultdict(lambda: [0.0, 0.0, 0.0, 0.0])
        self.pending = None  # in a backward: the part not yet closed

    def add(self, flops: float, moved: float, low_precision: bool) -> None:
        t_flops = flops / self.rates["bf16" if low_precision else "fp32"]
        t_bytes = moved / self.rates["bandwidth"]
        bound = max(t_flops, t_bytes)
        work = (flops, moved, bound, bound if t_flops >= t_bytes and flops else 0.0)
        for acc in (self.sections[self.section], self.pending):
            if acc is not None:
                for i, v in enumerate(work):
                    acc[i] += v

    def close_part(self, name: str) -> None:
        if self.pending is not None:
            for i, v in enumerate(self.pending):
                self.parts[name][i] += v
            self.pending = [0.0, 0.0, 0.0, 0.0]

    def kernel(self, name: str, args, result) -> None:
        """A compiled kernel's call (extension.observe_calls): its arguments' and results' bytes."""
        self.add(0.0, _unique_bytes(_tensors(args) + _tensors(result)), False)

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        out = func(*args, **kwargs)
        name = func._overloadpacket.__name__
        if func.is_view or name in MOVES_NOTHING:
            return out
        inputs = _tensors((args, kwargs))
        written = _tensors(out)
        for i, a in enumerate(func._schema.arguments):  # arguments written in place (fused Adam's states, out=)
            if a.alias_info is not None and a.alias_info.is_write:
                written += _tensors(args[i] if i < len(args) else kwargs.get(a.name))
        f = flop_registry.get(func._overloadpacket)
        flops = float(f(*args, **kwargs, out_val=out)) if f is not None else 0.0
        self.add(flops, _unique_bytes(inputs) + _unique_bytes(written),
                 any(t.dtype in LOW_PRECISION for t in inputs))
        return out

    def summary(self, steps: int) -> dict:
        def per_step(acc):
            return {"gflop": acc[0] / steps / 1e9, "mb": acc[1] / steps / 1e6, "bound_ms": acc[2] / steps * 1e3,
                    "flop_limited_ms": acc[3] / steps * 1e3}
        total = [sum(a[i] for a in self.sections.values()) for i in range(4)]
        return {"sections": {k: per_step(v) for k, v in self.sections.items()},
                "backward_parts": {k: per_step(v) for k, v in self.parts.items()},
                "step": per_step(total), "steps": steps}


class WorkProfiler(Profiler):
    """The trainer's profiler interface, tallying work per section instead of timing it."""

    def __init__(self, tally: Tally, after: str):
        super().__init__(split_backward=True, after=after)
        self.tally = tally

    @contextmanager
    def __call__(self, name: str):
        prev, self.tally.section = self.tally.section, name
        try:
            yield
        finally:
            self.tally.section = prev

    def _mark(self, name: str) -> None:
        self.tally.close_part(name)

    def backward(self, loss: torch.Tensor) -> None:
        prev, self.tally.section = self.tally.section, "backward"
        self.tally.pending = [0.0, 0.0, 0.0, 0.0]
        try:
            loss.backward()
            self.tally.close_part(self.after)
        finally:
            self.tally.section, self.tally.pending = prev, None


def tally_steps(trainer, rates: dict, after: str, steps: int = 1) -> dict:
    """Run `steps` training steps of `trainer` under a Tally; its summary per step."""
    tally = Tally(rates)
    saved = trainer.profile
    trainer.profile = WorkProfiler(tally, after)
    try:
        with tally, observe_calls(tally.kernel):
            for _ in range(steps):
                trainer.train_step()
    finally:
        trainer.profile = saved
    return tally.summary(steps)


def bound_rows(row: dict, sections, parts) -> list[list[str]]:
    """Table rows (section, ms, GFLOP, MB, bound ms, x bound, limited by) of one bench-train row."""
    work = row.get("work")
    if not work:
        return []
    timed = [(s, row["sections_ms"].get(s), work["sections"].get(s)) for s in sections]
    timed += [(f"bwd: {p}", row["backward_parts_ms"].get(p), work["backward_parts"].get(p)) for p in parts]
    timed.append(("whole step", row["ms"], work["step"]))
    out = []
    for name, ms, w in timed:
        if ms is None and w is None:
            continue
        bound = None if w is None else w["bound_ms"]
        ratio = f"{ms / bound:.1f}" if ms is not None and bound else "–"
        limited = "–" if not bound else ("FLOPs" if w["flop_limited_ms"] >= bound / 2 else "bytes")
        out.append([name, "–" if ms is None else f"{ms:.1f}", "–" if w is None else f"{w['gflop']:.2f}",
                    "–" if w is None else f"{w['mb']:.0f}", "–" if bound is None else f"{bound:.1f}", ratio, limited])
    return out
