"""STDR's regularizers: the weighted L_temp and L_spatial of a mask, and the spatial term's cache of
sampled queries and their nearest neighbours."""
from __future__ import annotations

import time
from typing import Any, Callable, Optional

import torch
from torch import Tensor

from .mask import sample_neighbours, spatial_kl, temporal_loss


def regularizer_terms(cfg, mask: Tensor, neighbours: Callable[[], tuple[Tensor, Tensor]]) -> dict[str, Tensor]:
    """{"temporal": lambda_temp * L_temp, "spatial": lambda_spatial * L_spatial} of the mask logits
    [N, K], each where its switch is on and its weight positive; `neighbours()` gives the spatial
    term's (queries [Q], their neighbours [Q, k]) when it is needed."""
    out = {}
    if cfg.temporal_reg and cfg.lambda_temp > 0:
        out["temporal"] = cfg.lambda_temp * temporal_loss(mask, cfg.temporal_reduction)
    if cfg.spatial_reg and cfg.lambda_spatial > 0:
        q, nbr = neighbours()
        out["spatial"] = cfg.lambda_spatial * spatial_kl(mask, q, nbr)
    return out


class NeighbourCache:
    """The spatial term's sampled queries and their K nearest neighbours (stdr.knn_samples,
    knn_candidates, knn_k), refreshed every stdr.knn_every steps (0: never by age) and whenever the
    mask tensor was replaced (densification edits rows). Draws come from its own generator."""

    def __init__(self, cfg, seed: int, device: torch.device):
        self.cfg, self.device = cfg, device
        self.gen = torch.Generator().manual_seed(seed + 7919)
        self.pairs: Optional[tuple[Tensor, Tensor]] = None
        self.built_for: Optional[Tensor] = None  # the mask tensor the cache was built for
        self.step = -1
        self.seconds = 0.0
        self.refreshes = 0

    def get(self, means: Tensor, mask: Tensor, step: int) -> tuple[Tensor, Tensor]:
        due = self.pairs is None or self.built_for is not mask or \
            (self.cfg.knn_every > 0 and step - self.step >= self.cfg.knn_every)
        if due:
            t0 = time.perf_counter()
            self.pairs = sample_neighbours(means, self.cfg.knn_samples, self.cfg.knn_candidates, self.cfg.knn_k, self.gen)
            self.seconds += time.perf_counter() - t0
            self.refreshes += 1
            self.built_for, self.step = mask, step
        return self.pairs

    def to(self, device: torch.device) -> None:
        self.device = device
        if self.pairs is not None:
            self.pairs = tuple(x.to(device) for x in self.pairs)

    def state_dict(self, mask: Optional[Tensor]) -> dict[str, Any]:
        """Its part of the plug-in's state; `mask`: the model's mask tensor now (or None)."""
        return {"gen": self.gen.get_state(), "knn": self.pairs, "knn_step": self.step,
                # whether the cache is of the current rows: densification replaces the mask tensor, and
                # the next regularized step rebuilds the cache; a run resumed from a checkpoint written
                # in between must do the same
                "knn_valid": self.pairs is not None and mask is not None and self.built_for is mask,
                "knn_seconds": self.seconds, "knn_refreshes": self.refreshes}

    def load_state_dict(self, s: dict[str, Any], mask: Optional[Tensor]) -> None:
        if s["gen"] is not None:  # None in a compact file (Plugin.compact_form): the draws start afresh
            self.gen.set_state(s["gen"])
        self.pairs = None if s["knn"] is None else tuple(x.to(self.device) for x in s["knn"])
        self.step = int(s["knn_step"])
        self.built_for = mask if self.pairs is not None and s.get("knn_valid", True) else None
        self.seconds = float(s["knn_seconds"])
        self.refreshes = int(s["knn_refreshes"])
