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


class RowView:
    """A per-Gaussian parameter dict restricted to rows [M] (int64): `view[k]` is
    take_rows(params[k], rows), computed on first access and cached, so only the keys a module
    reads are gathered. Gradients flow back into the full tensors (culled rows get zeros)."""

    def __init__(self, params, rows: Tensor):
        self.params = params
        self.rows = rows
        self._cache: dict[str, Tensor] = {}

    def __getitem__(self, key: str) -> Tensor:
        if key not in self._cache:
            self._cache[key] = take_rows(self.params[key], self.rows)
        return self._cache[key]

    def __contains__(self, key: object) -> bool:
        return key in self.params

    def __iter__(self):
        return iter(self.params.keys())

    def __len__(self) -> int:
        return len(self.params)

    def keys(self):
        return self.params.keys()

    def get(self, key: str, default=None):
        return self[key] if key in self.params else default


def rows_of(x, rows):
    """x restricted to rows (x itself when rows is None; None stays None)."""
    return x if rows is None or x is None else take_rows(x, rows)
