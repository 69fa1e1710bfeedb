"""The one context every training hook gets: baselines' (`Deformation.before_step`,
`Deformation.regularizers`) and plug-ins' (`Plugin.before_step`, `Plugin.regularizers`,
`Conditioner.conditioning`, `Conditioner.opacity_factor`, the densification and reporting hooks).

A hook reads what it needs and ignores the rest; a field that the caller does not have at that
point is None (before the render there is no `render`; outside a training step no `camera`).

    def regularizers(self, ctx: StepContext) -> dict[str, Tensor]:
        if ctx.phase == STATIC:          # the static warm-up: the Gaussians are not deformed
            return {}
        return {"l1": self.weight * ctx.params["velocity"].abs().mean()}
"""
from __future__ import annotations

import inspect
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Optional

from torch import Tensor

from .errors import RegistrationError

if TYPE_CHECKING:  # (annotations only: the classes live in lower layers)
    from .cameras import Camera
    from .gaussians import Gaussians
    from .render import RenderOutput

#: ctx.phase before the baseline's static warm-up ends: the Gaussians are rendered undeformed
STATIC = "static"
#: ctx.phase from the end of the warm-up on: the deformation runs
DEFORMING = "deforming"


@dataclass
class StepContext:
    """One training step (or one render) as the hooks see it.

    step: iterations trained before this one (the step being taken, counted from 0).
    params: the per-Gaussian parameter dict (every baseline's and plug-in's tensors in it).
    warmup_end: the step the baseline's static warm-up ends (`phase` compares with it).
    t: the frame's time in [0, 1]; camera: the frame's camera.
    cond: the step's conditioning [N, cond_dim] from the plug-ins (None without one or in the
    warm-up): the tensor the render uses.
    deformed: the deformation's output, activated Gaussians (the rows `rows` [M] of the model, or
    all when None); render: the step's RenderOutput.
    """

    step: int
    params: Any
    warmup_end: int = 0
    t: Optional[float] = None
    camera: Optional["Camera"] = None
    cond: Optional[Tensor] = None
    deformed: Optional["Gaussians"] = None
    rows: Optional[Tensor] = None
    render: Optional["RenderOutput"] = None

    @property
    def phase(self) -> str:
        """STATIC before the warm-up's end, DEFORMING from it on."""
        return STATIC if self.step < self.warmup_end else DEFORMING


def check_hooks(register: str, cls: type, base: type, hooks: dict[str, int], renamed: dict[str, str]) -> None:
    """At registration (`register`: e.g. "register_plugin('mine')"): each hook of `hooks` (name ->
    how many arguments it takes after self, the context first) that `cls` (a subclass of the
    interface `base`) defines takes that many, and `cls` defines none of the names of `renamed`
    (an earlier interface's name -> what replaced it). A TypeError names the class, the hook and
    the fix; a hook with the earlier positional arguments would otherwise never be called, or fail
    mid-run."""
    for old, new in renamed.items():
        if any(old in vars(k) for k in cls.__mro__ if issubclass(k, base) and k is not base):
            raise RegistrationError(f"{register}: {cls.__name__}.{old} is not part of the interface any more: {new}")
    for name, n in hooks.items():
        fn = inspect.getattr_static(cls, name, None)
        if fn is None or isinstance(fn, (classmethod, staticmethod, property)) or not callable(fn):
            continue
        params = list(inspect.signature(fn).parameters.values())[1:]  # after self
        if any(p.kind in (p.VAR_POSITIONAL,) for p in params):
            continue
        required = [p for p in params if p.default is p.empty and p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)]
        positional = [p for p in params if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)]
        if len(required) > n or len(positional) < n:
            args = ", ".join(p.name for p in params)
            raise RegistrationError(f"{register}: {cls.__name__}.{name}({args}) must take the step's context"
                            f"{' and ' + str(n - 1) + ' more' if n > 1 else ''}: "
                            f"def {name}(self, ctx{', ...' if n > 1 else ''}) (ctx: stdr.context.StepContext, "
                            "with step, phase, t, camera, params, cond, deformed and render)")
