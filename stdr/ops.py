"""Small tensor helpers shared across modules."""
from __future__ import annotations

import sys

import torch
from torch import Tensor, nn


class _Sigmoid(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x):
        y = torch.neg(x).exp_().add_(1.0).reciprocal_()
        ctx.save_for_backward(y)
        return y

    @staticmethod
    def backward(ctx, g):
        (y,) = ctx.saved_tensors
        return torch.rsub(y, 1.0).mul_(y).mul_(g)


def sigmoid(x: Tensor) -> Tensor:
    """1 / (1 + exp(-x)), same shape, with the same bits on any CPU thread count.

    torch.sigmoid on the CPU computes whole SIMD vectors with one formula and the leftover
    elements of each thread's share with another (scalar) one, so which elements take which
    formula, and so the last bits of a large tensor's sigmoid, change with the thread count
    (measured: a [1500, 40] STDR mask differs between 1 and 2 threads; torch.exp, add and
    reciprocal do not). Here: exp, add and reciprocal forward, y (1 - y) g backward (each
    element's arithmetic fixed), ~1 ms more than torch.sigmoid on 2M elements on 2 cores. On
    CUDA (deterministic per element there) it is torch.sigmoid. Saturates like it: -inf -> 0, +inf -> 1."""
    if x.device.type == "cuda":
        return torch.sigmoid(x)
    return _Sigmoid.apply(x)


ROW = 1024  # fixed_mean's row length


def fixed_sum(x: Tensor, dims: tuple[int, ...] | None = None, keepdim: bool = False) -> Tensor:
    """x.sum(dims) (all dimensions when None) added in an order fixed by the shape alone: the
    reduced elements of each output in rows of 1024 (each row summed, then the rows in order, then
    the remainder), so the result is bitwise the same on any CPU thread count. torch's CPU sum of
    one large reduction splits it between threads, and so its last bits follow the thread count
    (measured: the PSNR of a 200x200 image in the 8th digit). Differentiable (sums and views).
    Off the CPU (deterministic there per launch configuration) it is torch's sum, one kernel."""
    if x.device.type != "cpu" or x.dim() == 0:
        return x.sum() if dims is None else x.sum(dims, keepdim=keepdim)
    if dims is None:
        dims = tuple(range(x.dim()))
    dims = tuple(sorted(d % x.dim() for d in dims)) if x.dim() else ()
    keep = [d for d in range(x.dim()) if d not in dims]
    y = x.permute(*keep, *dims).reshape(*[x.shape[d] for d in keep], -1)  # [..., reduced]
    n = y.shape[-1]
    full = n // ROW * ROW
    out = y[..., :full].reshape(*y.shape[:-1], -1, ROW).sum(-1).sum(-1) if full else y.new_zeros(y.shape[:-1])
    if full < n:
        out = out + y[..., full:].sum(-1)
    if keepdim:
        for d in dims:
            out = out.unsqueeze(d)
    return out


def fixed_mean(x: Tensor, dims: tuple[int, ...] | None = None, keepdim: bool = False) -> Tensor:
    """x.mean(dims) with fixed_sum's order: the same bits on any CPU thread count."""
    count = x.numel() if dims is None else int(torch.tensor([x.shape[d] for d in dims]).prod())
    return fixed_sum(x, dims, keepdim) / max(count, 1)


class Sigmoid(nn.Module):
    """`sigmoid` as a module (for nn.Sequential)."""

    def forward(self, x: Tensor) -> Tensor:
        return sigmoid(x)


class BatchNorm1d(nn.BatchNorm1d):
    """nn.BatchNorm1d (same parameters, buffers and state dict) whose training-mode statistics of
    a [N, C] CPU batch give the same bits on any thread count: torch's CPU batch norm splits its
    per-channel sums by thread (measured: a [4725, 64] batch differs between 1 and 2 threads),
    while the column means used here do not. The batch's biased variance normalizes; the running
    statistics are updated as torch's are (momentum, or the cumulative average with momentum None;
    unbiased variance). Evaluation, CUDA and other shapes take torch's form."""

    def forward(self, x: Tensor) -> Tensor:
        if not self.training or x.device.type != "cpu" or x.dim() != 2:
            return super().forward(x)
        n = x.shape[0]
        if n < 2:
            raise ValueError(f"BatchNorm1d in training needs more than one row per batch, got {n}")
        mean = x.mean(0)
        d = x - mean
        var = d.square().mean(0)
        self.track(mean, var, n)
        y = d * torch.rsqrt(var + self.eps)
        return y * self.weight + self.bias if self.affine else y

    @torch.no_grad()
    def track(self, mean: Tensor, var: Tensor, n: int) -> None:
        """Update the running statistics from a training batch of n rows: its column means [C]
        and biased variances [C] (torch's update: momentum, or the cumulative average)."""
        if self.track_running_stats and self.running_mean is not None:
            self.num_batches_tracked.add_(1)
            m = 1.0 / float(self.num_batches_tracked) if self.momentum is None else self.momentum
            self.running_mean.mul_(1.0 - m).add_(mean.detach(), alpha=m)
            self.running_var.mul_(1.0 - m).add_(var.detach(), alpha=m * n / (n - 1))


#: which int16 lane of an int64 holds its top 16 bits (random_ draws 63 random bits: that lane has 15)
_TOP_LANE = 3 if sys.byteorder == "little" else 0


def dropout_keep(n: int, p: float, device: torch.device | str) -> tuple[Tensor, float]:
    """(keep [n] bool, kept fraction q): each entry kept with probability q = 1 - round(32768 p) /
    32768 (p to 1/32768), from one 64-bit draw of the default generator for every four entries
    (its four 16-bit lanes; the top one holds 15 random bits and is cut at half the value), where
    torch's dropout draws one per entry (on the CPU its draws are serial: a quarter of that work).
    Divide the kept entries by q for an unbiased dropout. The same bits on any thread count."""
    if not 0.0 <= p < 1.0:
        raise ValueError(f"dropout probability {p} must lie in [0, 1)")
    cut = round(p * 32768)
    lanes = torch.empty((n + 3) // 4, dtype=torch.int64, device=device).random_().view(torch.int16).view(-1, 4)
    # a full lane read as int16 is uniform on [-32768, 32768): keep where it is >= 2 cut - 32768; the top
    # lane is uniform on [0, 32768): keep where it is >= cut
    thr = torch.full((4,), 2 * cut - 32768, dtype=torch.int16, device=device)
    thr[_TOP_LANE] = cut
    return (lanes >= thr).view(-1)[:n], 1.0 - cut / 32768.0


class _NormReluDropout(torch.autograd.Function):
    """relu(batch_norm(x) * w + b) * gate in one function (see norm_relu_dropout)."""

    @staticmethod
    def forward(ctx, x, weight, bias, keep_scale, eps):
        mean = x.mean(0)
        d = x - mean
        var = d.square().mean(0)
        rstd = torch.rsqrt(var + eps)
        xh = d.mul_(rstd)  # d is not needed again
        y = torch.addcmul(bias, xh, weight)
        gate = (y > 0).to(x.dtype)
        if keep_scale is not None:
            gate.mul_(keep_scale)
        ctx.save_for_backward(xh, rstd, weight, gate)
        ctx.mark_non_differentiable(mean, var)
        return y.mul_(gate), mean, var

    @staticmethod
    def backward(ctx, g, _gm, _gv):
        xh, rstd, weight, gate = ctx.saved_tensors
        gy = g * gate
        gw = (gy * xh).sum(0)
        gb = gy.sum(0)
        gxh = gy.mul_(weight)
        # d/dx of (x - mean) * rstd: rstd * (gxh - mean(gxh) - xh * mean(gxh * xh))
        c = (gxh * xh).mean(0)
        gx = gxh.sub_(gxh.mean(0)).sub_(xh * c).mul_(rstd)
        return gx, gw, gb, None, None


def norm_relu_dropout(x: Tensor, bn: BatchNorm1d, p: float) -> Tensor:
    """relu(bn(x)) with dropout p, x [N, C] float32 -> [N, C]: a BatchNorm1d of C channels, ReLU
    and Dropout(p) as one function with a hand-written backward (a third of the passes over
    [N, C] of their composition), the dropout's draws from `dropout_keep`. In training mode the
    batch statistics normalize (biased variance) and the running ones are updated as torch's
    BatchNorm1d does; in eval mode: torch's batch norm on the running statistics, ReLU, no
    dropout. Column means throughout: the same bits on any CPU thread count."""
    if not bn.training:
        return torch.relu(bn(x))
    if x.dim() != 2 or x.shape[0] < 2 or not bn.affine:
        raise ValueError(f"norm_relu_dropout needs an affine batch norm and [N >= 2, C] rows, got {tuple(x.shape)}")
    keep_scale = None
    if p > 0:
        keep, q = dropout_keep(x.numel(), p, x.device)
        keep_scale = keep.view_as(x).to(x.dtype).mul_(1.0 / q)
    out, mean, var = _NormReluDropout.apply(x, bn.weight, bn.bias, keep_scale, bn.eps)
    bn.track(mean, var, x.shape[0])
    return out


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
