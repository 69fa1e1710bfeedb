"""Plug-ins: components that attach to any baseline (STDR is one).

A plug-in may add per-Gaussian parameters (kept aligned by densification because they live in
the model's parameter dict), networks with their own parameter groups and learning-rate
schedules, a conditioning input for the deformation network, a factor on opacity, loss terms,
and its own say in the densification's opacity reset and pruning. The model and the training
loop call the hooks below on every plug-in in order; every default does nothing, so a plug-in
implements only what it changes.

A plug-in's phase boundaries come from the run's one schedule (stdr.schedule), which its
factory receives with the config.

Several plug-ins combine as follows: their conditionings are concatenated in order (the
deformation network is built for the sum of their `cond_dim`), delta scales and opacity factors
multiply, loss terms are summed (logged as `loss/<plug-in>_<term>`), and the first plug-in whose
`reset_opacity` returns True handles the densification's opacity reset.
"""
from __future__ import annotations

from typing import Any, Optional

import torch
from torch import Tensor, nn


class Plugin:
    """Base class; `name` labels the plug-in's state in checkpoints, metrics.json and logs."""

    name: str = "plugin"

    # ---------------------------------------------------------------- construction
    @property
    def cond_dim(self) -> int:
        """Width of the per-Gaussian conditioning this plug-in feeds the deformation network."""
        return 0

    def init_gaussians(self, params) -> None:
        """Once the Gaussians exist: add per-Gaussian tensors to `params`, set initial values."""

    def gaussian_lr(self, key: str) -> Optional[float]:
        """Learning rate of a per-Gaussian parameter this plug-in added (None: not one of its)."""
        return None

    def param_groups(self) -> list[dict]:
        """Network parameter groups: {"params", "name"} and optionally a schedule of their own,
        "lr_init", "lr_final", "lr_max_steps", "lr_delay" (log-linear from lr_init at step
        lr_delay to lr_final lr_max_steps later). Without one, a group follows the deformation
        network's schedule."""
        return []

    def modules(self) -> list[nn.Module]:
        """Networks that switch between train and eval mode and move with the model."""
        return []

    # ---------------------------------------------------------------- per step
    def configure_step(self, params, step: int) -> None:
        """Before the step's forward pass: which parameters train in this phase."""

    def conditioning(self, params, step: int) -> tuple[Optional[Tensor], Optional[Tensor]]:
        """(cond [N, cond_dim] or None, delta scale [N, 1] or None) at `step`."""
        return None, None

    def opacity_factor(self, params, t: float, step: int) -> Optional[Tensor]:
        """[N] factor on the activated opacity at time t, or None."""
        return None

    def regularizers(self, params, step: int) -> dict[str, Tensor]:
        """Named loss terms, already weighted."""
        return {}

    def reset_opacity(self, params, value: float, step: int) -> bool:
        """Handle the densification's opacity reset; False leaves it to the strategy."""
        return False

    def prune_factor(self, params, step: int) -> Optional[Tensor]:
        """[N] factor on sigmoid(opacity) for the densification's opacity pruning, or None."""
        return None

    # ---------------------------------------------------------------- state and monitoring
    def to(self, device: torch.device | str) -> "Plugin":
        for m in self.modules():
            m.to(device)
        return self

    def state_dict(self) -> dict[str, Any]:
        return {}

    def load_state_dict(self, state: dict[str, Any], params) -> None:
        pass

    def log(self, tb, params, step: int, images: bool, x: Optional[int] = None) -> None:
        """TensorBoard entries for iteration `step` (x: the axis value)."""

    def stats(self, params) -> dict[str, Any]:
        """Numbers for metrics.json, under the plug-in's name."""
        return {}
