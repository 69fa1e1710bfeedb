"""A baseline: every Gaussian moves in a straight line, mean + t * velocity, with velocity a
per-Gaussian parameter. It takes STDR's conditioning through a linear map that starts at zero."""
from dataclasses import dataclass, field

import torch
from torch import nn

from stdr.baselines import BaselineConfig, Deformation, Deltas, register_baseline


@dataclass
class LinearOptions:
    lr_velocity: float = 1.0e-4  # Adam's rate for the per-Gaussian velocities (constant)


@dataclass
class LinearConfig(BaselineConfig):
    name: str = "linear"
    linear: LinearOptions = field(default_factory=LinearOptions)


class Linear(Deformation):
    capabilities = frozenset({"conditioning"})  # STDR's separated field feeds `cond`; it starts with no effect

    def __init__(self, lr_velocity: float = 1.0e-4, cond_dim: int = 0):
        super().__init__()
        self.cond_dim, self.lr_velocity = cond_dim, lr_velocity
        self.cond_to_velocity = nn.Linear(cond_dim, 3, bias=False) if cond_dim else None
        if self.cond_to_velocity is not None:
            nn.init.zeros_(self.cond_to_velocity.weight)

    @classmethod
    def config_kwargs(cls, b, cond_dim=0, train_times=None, seed=0, schedule=None):
        return {"lr_velocity": b.linear.lr_velocity, "cond_dim": cond_dim}

    def init_gaussians(self, params):  # a per-Gaussian tensor: kept aligned by densification, saved in checkpoints
        if "velocity" not in params:
            params["velocity"] = nn.Parameter(torch.zeros_like(params["means"]))

    def param_groups(self):  # the network's group, and the velocities' rate
        return [*super().param_groups(), {"key": "velocity", "lr": self.lr_velocity}]

    def forward(self, params, t, cond=None):
        v = params["velocity"]
        if self.cond_to_velocity is not None and cond is not None:
            v = v + self.cond_to_velocity(cond)
        return Deltas(means=float(t) * v)


def register():
    register_baseline("linear", Linear, LinearConfig)
