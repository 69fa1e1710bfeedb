"""Small tensor helpers shared across modules."""
from __future__ import annotations

from torch import Tensor


def take_rows(x: Tensor, idx: Tensor) -> Tensor:
    """x[idx] for x [M, ...] and integer idx of any shape -> [*idx.shape, ...].

    Use it where gradients flow into x and idx repeats rows: advanced indexing backpropagates
    with index_put_(accumulate=True), whose float sums on the CPU depend on thread scheduling
    (measured: two identical steps differ), while index_select's backward (index_add_) is
    deterministic. Bit-exact resume depends on it.
    """
    return x.index_select(0, idx.reshape(-1)).reshape(*idx.shape, *x.shape[1:])
