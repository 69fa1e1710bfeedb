"""STDR's spatio-temporal mask: stateless functions with shape contracts.

The mask is a per-Gaussian row of K logits, m [N, K], one column per *knot time*
tau_0 < ... < tau_{K-1} (the distinct training timestamps, or `time_bins` evenly spaced bins).
It is activated with a sigmoid like opacity; at time t the activated mask is read between the two
neighbouring knots (linearly by default, `mask_at`; exact at knots, clamped outside
[tau_0, tau_{K-1}]), and multiplies the Gaussian's opacity.
"""
from __future__ import annotations

import bisect
import math

import numpy as np
import torch
from torch import Tensor

from ...ops import sigmoid, take_rows
from ...knn import knn

#: the mask's key in the model's parameter dict ([N, K] logits, or uint8 once stored in 8 bits)
MASK_KEY = "stdr_mask"
#: the separated field's output [N, cond_dim] stored in place of the mask (the compact file's `derived` form)
COND_KEY = "stdr_cond"


def knot_times(train_times, time_bins: int = 0) -> Tensor:
    """Knot times [K] (float64): the sorted distinct training times, or `time_bins` bins on [0, 1]."""
    if time_bins:
        if time_bins < 2:
            raise ValueError(f"stdr.time_bins={time_bins}: use 0 (one column per training time) or >= 2")
        return torch.linspace(0.0, 1.0, time_bins, dtype=torch.float64, device="cpu")
    t = np.unique(np.asarray(train_times, dtype=np.float64))
    if t.size == 0:
        raise ValueError("STDR needs at least one training timestamp")
    return torch.from_numpy(t)


def interp_weights(t: float, knots) -> tuple[int, int, float]:
    """(j0, j1, w): the mask at t is (1 - w) * col j0 + w * col j1. Exact (w = 0) at knots.
    `knots`: the sorted knot times, a float64 tensor or a sequence of floats (the plug-in passes
    its host copy, so a training step does not read a tensor here)."""
    ks = tuple(knots.tolist()) if isinstance(knots, Tensor) else knots
    K = len(ks)
    t = float(t)
    if K == 1 or t <= ks[0]:
        return 0, 0, 0.0
    if t >= ks[-1]:
        return K - 1, K - 1, 0.0
    j1 = bisect.bisect_right(ks, t)  # = torch.searchsorted(knots, t, right=True)
    j0 = j1 - 1
    t0, t1 = ks[j0], ks[j1]
    w = (t - t0) / (t1 - t0)
    if w == 0.0:
        return j0, j0, 0.0
    return j0, j1, w


#: the logit an 8-bit entry of 0 reads back as (an entry switched off: sigmoid ~ 1e-13), and of 255
OFF_LOGIT = -30.0


def activated(mask: Tensor) -> Tensor:
    """The activated mask in [0, 1], same shape: sigmoid of float logits, or q / 255 for a mask
    stored in 8 bits (uint8 q, `quantize`), read directly from that form."""
    if mask.dtype == torch.uint8:
        return mask.float() / 255.0
    return sigmoid(mask)


def quantize(logits: Tensor) -> Tensor:
    """uint8 q = round(255 * sigmoid(m)): the frozen mask in 8 bits (a quarter of float32). An entry
    switched off (sigmoid below 1/510) becomes 0 and reads back as exactly 0."""
    return torch.round(sigmoid(logits.detach().float()) * 255.0).to(torch.uint8)


def logits_of(mask: Tensor) -> Tensor:
    """Float logits of a mask: the logits themselves, or for an 8-bit mask the logit of q / 255
    (0 -> OFF_LOGIT, 255 -> -OFF_LOGIT): what the softmax over time (the field's input, the
    entropy) reads."""
    if mask.dtype != torch.uint8:
        return mask
    q = mask.float()
    # logit(q / 255) = log q - log(255 - q), from the integers (1 - a would round to 0 in float32
    # near a = 1); the ends, +-inf, are clamped to +-30
    return (torch.log(q) - torch.log(255.0 - q)).clamp(OFF_LOGIT, -OFF_LOGIT)


#: how `mask_at` reads the mask between two knots (stdr.mask_between)
BETWEEN = ("linear", "nearest", "logit")


def mask_at(logits: Tensor, t: float, knots, between: str = "linear") -> Tensor:
    """Activated mask [N] at time t from logits [N, K] (or an 8-bit mask). At a knot, its column;
    between two knots (weight w of the later one), by `between`: linear = (1 - w) a0 + w a1 of the
    activated columns; nearest = the nearer column (the earlier one at w = 1/2); logit = the
    activation of (1 - w) m0 + w m1 (the logits interpolated: an entry on at one knot and off at
    the next crosses 1/2 once, where linear holds both halves)."""
    if between not in BETWEEN:
        raise ValueError(f"stdr.mask_between={between!r}: use one of {BETWEEN}")
    j0, j1, w = interp_weights(t, knots)
    if w == 0.0:
        return activated(logits[:, j0])
    if between == "nearest":
        return activated(logits[:, j1 if w > 0.5 else j0])
    if between == "logit":
        return sigmoid((1.0 - w) * logits_of(logits[:, j0]).float() + w * logits_of(logits[:, j1]).float())
    return (1.0 - w) * activated(logits[:, j0]) + w * activated(logits[:, j1])


def temporal_loss(logits: Tensor, reduction: str = "mean") -> Tensor:
    """L_temp over the activated mask a = sigmoid(m) [N, K]: sum_{i,t} (a_i^t - a_i^{t+1})^2.

    reduction="sum" is the paper's formula: the gradient on each mask entry is
    2 * lambda_1 * (difference to its neighbours) whatever N and K are, so lambda_1 weighs
    smoothness against that entry's own photometric gradient. "mean" divides by N(K-1)
    (~1e6 at N = 10^4, K = 150), which leaves the term almost without effect (docs/stdr.md).
    """
    if reduction not in ("sum", "mean"):
        raise ValueError(f"stdr.temporal_reduction={reduction!r}: use 'sum' (the paper's formula) or 'mean'")
    if logits.shape[1] < 2 or logits.shape[0] == 0:
        return logits.sum() * 0.0
    a = sigmoid(logits)  # [N, K]
    d2 = (a[:, 1:] - a[:, :-1]).square()
    return d2.sum() if reduction == "sum" else d2.mean()


def spatial_kl(logits: Tensor, query: Tensor, neighbours: Tensor) -> Tensor:
    """mean over queries i [M] and their neighbours j [M, k] of KL(p_i || p_j), p = softmax_t(m)."""
    if query.numel() == 0:
        return logits.sum() * 0.0
    logp_i = torch.log_softmax(take_rows(logits, query), -1)       # [M, K]
    logp_j = torch.log_softmax(take_rows(logits, neighbours), -1)  # [M, k, K]
    kl = (logp_i.exp()[:, None] * (logp_i[:, None] - logp_j)).sum(-1)  # [M, k]
    return kl.mean()


def faint_fraction(opacities: Tensor, logits: Tensor, lo: float = 1.0 / 255.0, hi: float = 0.05) -> float:
    """Share of (Gaussian, knot) entries whose masked opacity sigmoid(m) * o lies in [lo, hi]:
    faint copies that can reappear as ghosts when opacity grows. opacities [N] (activated)."""
    if logits.numel() == 0:
        return 0.0
    e = activated(logits) * opacities[:, None]
    return float(((e >= lo) & (e <= hi)).float().mean())


def temporal_entropy(logits: Tensor) -> Tensor:
    """Entropy of p_i = softmax_t(m_i) divided by log K: [N] in [0, 1] (1 = spread over all times)."""
    K = logits.shape[1]
    logits = logits_of(logits)
    if K < 2:
        return torch.zeros(logits.shape[0], dtype=logits.dtype, device=logits.device)
    logp = torch.log_softmax(logits, -1)
    return -(logp.exp() * logp).sum(-1) / math.log(K)


def sample_neighbours(means: Tensor, n_query: int, n_candidates: int, k: int,
                      generator: torch.Generator) -> tuple[Tensor, Tensor]:
    """Query rows [M] and their k nearest neighbours [M, k] in xyz, both indices into means [N, 3].

    Candidates: at most n_candidates rows drawn without replacement; queries: at most n_query of
    the candidates; neighbours are searched among the candidates (the query itself excluded).
    Returns empty tensors when there are not more than k candidates.
    """

    N = means.shape[0]
    dev = means.device
    empty = torch.zeros(0, dtype=torch.long, device=dev), torch.zeros(0, k, dtype=torch.long, device=dev)
    if N <= k:
        return empty
    # drawn with the CPU generator (same stream as before), then moved to the points' device
    g_dev = generator.device
    cand = (torch.randperm(N, generator=generator, device=g_dev)[:min(n_candidates, N)] if N > n_candidates
            else torch.arange(N, device=g_dev)).to(dev)
    q_local = torch.randperm(cand.numel(), generator=generator, device=g_dev)[:min(n_query, cand.numel())].to(dev)
    pts = means[cand].detach()
    _, nbr_local = knn(pts[q_local], pts, k + 1)  # the query is among the candidates
    # drop the query itself (distance 0, but ties with duplicates are possible): remove its index
    is_self = nbr_local == q_local[:, None]
    keep = torch.where(is_self.any(1, keepdim=True), ~is_self, torch.arange(k + 1, device=dev) < k)
    # the k kept entries of each row, in order (a stable sort puts them first; no boolean
    # indexing, which would wait for the device)
    nbr_local = nbr_local.gather(1, torch.sort((~keep).to(torch.uint8), dim=1, stable=True).indices[:, :k])
    return cand[q_local], cand[nbr_local]
