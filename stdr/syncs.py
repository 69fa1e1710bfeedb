"""Count the calls that make a GPU wait for the host: `.item()`, `.tolist()`, `.cpu()`,
`.numpy()`, `bool(t)`, `float(t)`, `int(t)`, `nonzero`, `unique`, `masked_select`, indexing
with a boolean tensor (which runs nonzero), and the copies of host data to the device that
torch makes blocking (`torch.tensor(..., device=...)`, `new_tensor`, a Python list as an index,
a Python number written through a tensor index). On a GPU each of them blocks the Python thread
until every queued kernel has run, so a training step with any of them cannot overlap its
launches with the GPU's work. Counted on any device (the CPU too): the same code makes the same
calls, which is what lets a CPU-only test pin a GPU property.

    with SyncCounter() as sc:
        trainer.train_step()
    sc.total, sc.sites()   # {"stdr/train/trainer.py:384 item": 3, ...}

`OpCounter` counts the ATen operators dispatched (forward and backward), a machine-independent
proxy of kernel launches: on a GPU each is at least one launch (the compiled rasterizer's own
kernels, bound through pybind, are not ATen operators and are not counted).

`DeviceSyncCounter` counts what the CUDA runtime itself reports as synchronizing
(`torch.cuda.set_sync_debug_mode`): the ground truth on a GPU, which `SyncCounter` predicts on
any device. It counts nothing on a machine without CUDA.

Calls made inside `host_only(...)` blocks (work on host tensors by design, e.g. the frame
sampler's permutation of a CPU generator) are counted apart, in `sc.host`.
"""
from __future__ import annotations

import contextlib
import os
import sys
import warnings
from collections import Counter

import torch
from torch.overrides import TorchFunctionMode
from torch.utils._python_dispatch import TorchDispatchMode

SYNC_FUNCS = frozenset({"item", "tolist", "cpu", "numpy", "__bool__", "__float__", "__int__", "__index__", "nonzero",
                        "argwhere", "unique", "unique_consecutive", "masked_select", "equal", "allclose"})
# What the CUDA rasterizer's forward reads back to size its buffers (stdr/csrc/cuda/raster_cuda.h:
# the visible rows, by nonzero, and the number of tile intersections, as the
# 3DGS and gsplat rasterizers do): syncs inside compiled code, which SyncCounter cannot see and
# DeviceSyncCounter does (measured on an H100, research/measurements/gpu_check_h100_syncfree).
RASTERIZER_SYNCS = 2

# torch's own calls that synchronize on a GPU although their result stays there: cuSOLVER's
# batched SVD checks its convergence flags on the host
DEVICE_SYNC_FUNCS = frozenset({"linalg_svd", "svd", "linalg_svdvals"})
INDEX_FUNCS = frozenset({"__getitem__", "__setitem__", "index_put_", "index_put"})
_ROOT = os.path.dirname(os.path.abspath(__file__))  # the stdr package
_THIS = os.path.abspath(__file__)
_state = {"host": 0}


@contextlib.contextmanager
def host_only():
    """Mark a block as host work by design: its synchronizing calls are counted apart."""
    _state["host"] += 1
    try:
        yield
    finally:
        _state["host"] -= 1


def _index_has(idx, pred) -> bool:
    """Whether an index (one object, or a tuple or list of them) holds a part for which pred is true."""
    if isinstance(idx, (tuple, list)) and not pred(idx):
        return any(_index_has(i, pred) for i in idx)
    return pred(idx)


def _has_bool_index(idx) -> bool:
    return _index_has(idx, lambda i: isinstance(i, torch.Tensor) and i.dtype == torch.bool)


def _has_list_index(idx) -> bool:
    """A Python list inside an index: torch makes a host tensor of it and copies it over."""
    return isinstance(idx, list) or (isinstance(idx, tuple) and any(isinstance(i, list) for i in idx))


def _has_tensor_index(idx) -> bool:
    return _index_has(idx, lambda i: isinstance(i, torch.Tensor))


def _host_copy(name: str, args, kwargs) -> bool:
    """A call that copies host data into a tensor of the given device: on a GPU a blocking
    copy, which the CUDA runtime reports as synchronizing (a tensor made from Python values
    for a device, a list index, a Python number written through a tensor index)."""
    if name in ("tensor", "as_tensor", "asarray"):
        return (kwargs or {}).get("device") is not None
    if name == "new_tensor":
        return True
    if name in INDEX_FUNCS and len(args) > 1 and _has_list_index(args[1]):
        return True
    return name == "__setitem__" and len(args) > 2 and isinstance(args[2], (int, float)) \
        and not isinstance(args[2], bool) and _has_tensor_index(args[1])


def _site() -> str:
    """file:line of the innermost frame in the stdr package that made the call (outside this module)."""
    f = sys._getframe(2)
    while f is not None:
        fn = os.path.abspath(f.f_code.co_filename)
        if fn.startswith(_ROOT) and fn != _THIS:
            return f"{os.path.relpath(fn, os.path.dirname(_ROOT))}:{f.f_lineno}"
        f = f.f_back
    return "(outside the stdr package)"


class _Sites:
    """`calls` (a Counter by site) as a total and a sorted dict."""
    calls: Counter

    @property
    def total(self) -> int:
        return sum(self.calls.values())

    def sites(self) -> dict[str, int]:
        return dict(sorted(self.calls.items()))


class SyncCounter(_Sites, TorchFunctionMode):
    def __init__(self):
        super().__init__()
        self.calls: Counter = Counter()
        self.host: Counter = Counter()

    def __torch_function__(self, func, types, args=(), kwargs=None):
        name = getattr(func, "__name__", "")
        sync = name in SYNC_FUNCS or name in DEVICE_SYNC_FUNCS or (name in INDEX_FUNCS and len(args) > 1 and _has_bool_index(args[1])) \
            or (name == "repeat_interleave" and not (kwargs or {}).get("output_size")
                and len(args) > 1 and isinstance(args[1], torch.Tensor)) \
            or (name == "where" and len(args) == 1 and not kwargs) or _host_copy(name, args, kwargs)
        if sync:
            (self.host if _state["host"] else self.calls)[f"{_site()} {name}"] += 1
        return func(*args, **(kwargs or {}))


class OpCounter(TorchDispatchMode):
    """ATen operators dispatched while active (`ops`, and `by_op` per operator name)."""

    def __init__(self):
        super().__init__()
        self.ops = 0
        self.by_op: Counter = Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.ops += 1
        self.by_op[str(func.overloadpacket)] += 1
        return func(*args, **(kwargs or {}))


class DeviceSyncCounter(_Sites):
    """Synchronizing CUDA calls made while active, as the CUDA caching layer reports them
    (`torch.cuda.set_sync_debug_mode("warn")`: a copy to the host, a stream or device
    synchronize, `nonzero`, `item`, ...), with the Python file:line that made each (`sites()`).
    Zero on a machine without CUDA. Not reentrant; restores the previous mode on exit."""

    MARK = "synchroniz"  # torch's message: "called a synchronizing CUDA operation"

    def __init__(self):
        self.calls: Counter = Counter()
        self._on = torch.cuda.is_available()

    def __enter__(self):
        if self._on:
            self._prev = torch.cuda.get_sync_debug_mode()
            self._cm = warnings.catch_warnings(record=True)
            self._rec = self._cm.__enter__()
            warnings.simplefilter("always")
            torch.cuda.set_sync_debug_mode("warn")
        return self

    def __exit__(self, *exc):
        if self._on:
            torch.cuda.set_sync_debug_mode(self._prev)
            for w in self._rec:
                if self.MARK in str(w.message):
                    fn = os.path.abspath(w.filename)
                    where = os.path.relpath(fn, os.path.dirname(_ROOT)) if fn.startswith(_ROOT) else fn
                    self.calls[f"{where}:{w.lineno}"] += 1
            self._cm.__exit__(*exc)
        return False
