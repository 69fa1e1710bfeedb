"""A plug-in: an L1 penalty on the linear baseline's velocities, so that what does not move stays
still. It applies to `linear` only, and stays out of stdr's default grids."""
from dataclasses import dataclass

from stdr.plugins import Plugin, Reporting, register_plugin


@dataclass
class VelocityL1Config:
    enabled: bool = False
    weight: float = 0.01


class VelocityL1(Reporting, Plugin):
    name = "velocity_l1"

    def __init__(self, weight: float):
        self.weight = weight

    @classmethod
    def from_config(cls, pcfg, cfg, schedule, train_times, device):
        return cls(pcfg.weight)

    def regularizers(self, ctx):  # named terms, already weighted, added to the loss
        return {"l1": self.weight * ctx.params["velocity"].abs().mean()}

    def stats(self, params):  # the Reporting role: into metrics.json under "velocity_l1"
        return {"mean_speed": float(params["velocity"].norm(dim=-1).mean())}


def register():
    register_plugin("velocity_l1", VelocityL1, VelocityL1Config, label="+L1v", baselines=("linear",))
