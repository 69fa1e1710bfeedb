"""Small tensor helpers shared across modules."""
from __future__ import annotations

import torch
from torch import Tensor


def take_rows(x: Tensor, idx: Tensor) -> Tensor:
    """x[idx] for x [M, ...] and integer idx of any shape -> [*idx.shape, ...].

    Use it where gradients flow into x and idx repeats rows: advanced indexing backpropagates
    with index_put_(accumulate=True), whose float sums on the CPU depend on thread scheduling
    (measured: two identical steps differ), while index_select's backward (index_add_) is
    deterministic. Bit-exact resume depends on it.
    """
    return x.index_select(0, idx.reshape(-1)).reshape(*idx.shape, *x.shape[1:])


def scatter_mean(values: Tensor, index: Tensor, weights: Tensor, m: int) -> tuple[Tensor, Tensor]:
    """Weighted means per target: values [N, K, D] sent to index [N, K] with weights [N, K] ->
    ([m, D] means, [m] total weight)."""
    D = values.shape[-1]
    num = torch.zeros(m, D, dtype=values.dtype, device=values.device).index_add_(0, index.reshape(-1),
                                                           (values * weights[..., None]).reshape(-1, D))
    den = torch.zeros(m, dtype=values.dtype, device=values.device).index_add_(0, index.reshape(-1), weights.reshape(-1))
    return num / den.clamp_min(1e-12)[:, None], den
