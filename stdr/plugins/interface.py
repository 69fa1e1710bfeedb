"""The plug-in interface: `Plugin` (what every plug-in is) and the optional roles a plug-in adds
by also subclassing them: `Conditioner` (inputs of the deformation), `Densifying` (a say in
the densification) and `Reporting` (TensorBoard and metrics.json). A compact model file's form
of a plug-in's state is one more role (stdr.plugins.stdr.compact_form).

A minimal plug-in implements two methods, `from_config` and one hook:

    class VelocityL1(Plugin):
        name = "velocity_l1"
        def __init__(self, weight): self.weight = weight
        @classmethod
        def from_config(cls, pcfg, cfg, schedule, train_times, device): return cls(pcfg.weight)
        def regularizers(self, ctx): return {"l1": self.weight * ctx.params["velocity"].abs().mean()}

Every hook takes the step's one context (stdr.context.StepContext: step, phase, time, camera, the
parameter dict, the conditioning, the deformation's output and the render); every default does
nothing, so a plug-in implements only what it changes.
"""
from __future__ import annotations

from typing import Any, Optional

import numpy as np
import torch
from torch import Tensor, nn

from ..context import StepContext, check_hooks
from ..errors import RegistrationError


class Plugin:
    """Base class; `name` labels the plug-in's state in checkpoints, metrics.json and logs."""

    name: str = "plugin"

    # ---------------------------------------------------------------- construction
    @classmethod
    def from_config(cls, pcfg, cfg, schedule, train_times: Optional[np.ndarray], device: torch.device) -> "Plugin":
        """The plug-in of a run: `pcfg` is its config node (cfg.<name>, enabled), `cfg` the whole
        config, `schedule` the run's (its values in schedule.plugins[name]), `train_times` the
        training times (None when a bare model is built), `device` where its tensors live."""
        raise NotImplementedError(f"{cls.__name__}.from_config")

    @classmethod
    def stages(cls, pcfg, cfg, schedule) -> dict[str, Any]:
        """The plug-in's phase boundaries in the run's schedule: add Events (schedule.events) and
        notes, call schedule.never_trains(msg) for a phase at or after the end, and return the
        resolved values (kept in schedule.plugins[name], shown in the derived `schedule` node)."""
        return {}

    def init_gaussians(self, params) -> None:
        """Once the Gaussians exist: add per-Gaussian tensors to `params`, set initial values
        (densification keeps every tensor of the dict aligned with the Gaussians)."""

    def param_groups(self) -> list[dict]:
        """Network parameter groups: {"params", "name"} and optionally a schedule of their own,
        "lr_init", "lr_final", "lr_max_steps", "lr_delay" (log-linear from lr_init at step
        lr_delay to lr_final lr_max_steps later); without one, a group follows the deformation
        network's schedule. And one {"key", "lr"} per per-Gaussian tensor the plug-in adds in
        `init_gaussians`: its rate, constant over the run and not scaled by
        optim.spatial_lr_scale."""
        return []

    def modules(self) -> list[nn.Module]:
        """Networks that switch between train and eval mode and move with the model."""
        return []

    def frozen_keys(self, params) -> set[str]:
        """The keys of the per-Gaussian parameter dict this plug-in holds fixed for good: no
        gradient, no optimizer, the values kept as stored (e.g. STDR's mask once stored in 8 bits).
        The trainer drops their optimizers. A key frozen for a phase only is before_step's
        (requires_grad) instead. Default: none."""
        return set()

    def to(self, device: torch.device | str) -> "Plugin":
        """Move the plug-in's networks (and whatever else it keeps on a device) to `device`."""
        for m in self.modules():
            m.to(device)
        return self

    # ---------------------------------------------------------------- per step
    def before_step(self, ctx: StepContext) -> None:
        """Before the step's forward pass (ctx: step, phase, time, camera, params): which
        parameters train in this phase (requires_grad), state changes at a phase boundary."""

    def regularizers(self, ctx: StepContext) -> dict[str, Tensor]:
        """Named loss terms, already weighted, added to the step's loss (logged as
        `loss/<plug-in>_<term>`). Called on every step, the static warm-up included (ctx.phase
        tells them apart; a baseline's own terms start after the warm-up), after the render:
        ctx holds the conditioning, the deformed Gaussians and the render."""
        return {}

    # ---------------------------------------------------------------- state
    def state_dict(self) -> dict[str, Any]:
        return {}

    def load_state_dict(self, state: dict[str, Any], params) -> None:
        pass


class Conditioner:
    """Role: the plug-in feeds the deformation (STDR's separated field). A baseline takes a
    conditioning only with the capability "conditioning" (register_plugin's `requires`)."""

    @property
    def cond_dim(self) -> int:
        """Width of the per-Gaussian conditioning this plug-in feeds the deformation network."""
        return 0

    def conditioning(self, ctx: StepContext) -> tuple[Optional[Tensor], Optional[Tensor]]:
        """(cond [N, cond_dim] or None, delta scale [N, 1] or None) at ctx.step, from ctx.params:
        one per step, the same for every time."""
        return None, None

    def opacity_factor(self, ctx: StepContext) -> Optional[Tensor]:
        """[N] factor on the activated opacity at time ctx.t, or None. With a factor, temporal
        culling (render.cull) skips the rows it brings below 1/255."""
        return None


class Densifying:
    """Role: the plug-in has a say in the densification's opacity reset and pruning."""

    def reset_opacity(self, ctx: StepContext, value: float) -> bool:
        """Handle the densification's opacity reset to `value`; False leaves it to the strategy
        (the first plug-in that returns True handles it)."""
        return False

    def prune_factor(self, ctx: StepContext) -> Optional[Tensor]:
        """[N] factor on sigmoid(opacity) for the densification's opacity pruning, or None."""
        return None


class Reporting:
    """Role: the plug-in reports to TensorBoard and metrics.json."""

    def log(self, tb, ctx: StepContext, images: bool, x: Optional[int] = None) -> None:
        """TensorBoard entries for iteration ctx.step (x: the axis value; images: an image step)."""

    def stats(self, params) -> dict[str, Any]:
        """Numbers for metrics.json, under the plug-in's name."""
        return {}


#: the hooks that take the step's context first (name -> arguments after self)
CONTEXT_HOOKS = {"before_step": 1, "regularizers": 1, "conditioning": 1, "opacity_factor": 1, "prune_factor": 1,
                 "reset_opacity": 2}
#: names of the earlier interface, and what replaced each
RENAMED = {"configure_step": "before_step(ctx) replaced configure_step(params, step)",
           "gaussian_lr": "give a per-Gaussian tensor's rate as an entry {'key': ..., 'lr': ...} of param_groups()",
           "removed_keys": "pass removed_keys=(...) to register_plugin"}
ROLES = (Conditioner, Densifying, Reporting)


def check_plugin_class(register: str, cls: type) -> None:
    """At registration: the hooks take the step's context, no name of the earlier interface is
    defined, and a hook of a role (Conditioner, Densifying, Reporting) comes with the role (it
    would never be called otherwise); a TypeError names the class and the fix."""
    check_hooks(register, cls, Plugin, CONTEXT_HOOKS, RENAMED)
    for role in ROLES:
        own = [k for k in vars(role) if not k.startswith("_")]
        defined = [k for k in own if any(k in vars(c) for c in cls.__mro__ if c not in (role, object))]
        if defined and not issubclass(cls, role):
            raise RegistrationError(f"{register}: {cls.__name__} defines {', '.join(defined)} of the {role.__name__} role "
                            f"but does not take the role, so they would never be called: "
                            f"class {cls.__name__}({role.__name__}, Plugin) (stdr.plugins.{role.__name__})")


def roles(plugins, role: type) -> list:
    """The plug-ins of `plugins` that take `role` (Conditioner, Densifying, Reporting), in order."""
    return [p for p in plugins if isinstance(p, role)]
