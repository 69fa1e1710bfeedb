"""Densification, kept separate from the model (the gsplat pattern), as registered strategies.

A strategy is a dataclass whose fields are the `densify.*` keys, selected with `densify=<name>`
(default: `default`, 3DGS's adaptive density control, `DensifyStrategy`). The loop calls it
through a small protocol: `initialize_state` (its per-Gaussian statistics), `step_post_backward`
after each optimizer step (accumulate, refine, reset; it edits rows with `duplicate`, `split`,
`remove` below, which keep every tensor aligned) and, before any run exists, the classmethod
`stages(d)` (its boundaries for the run's one schedule). A second strategy subclasses
`DensifyStrategy` (so the budgets' shared `densify.*` keys stay valid; it may ignore the ones it
does not use), overrides what differs and calls `register_strategy(name, cls)`.

The strategy never names Gaussian attributes except where the method needs them (means and
scales when splitting, opacities when pruning/resetting). Every row operation is applied to
*every* tensor in the parameter dict, to the matching Adam moments, and to the strategy's own
per-Gaussian state, so an attribute added later (STDR's N x K mask) stays aligned for free.
Children of a clone or split inherit the parent's row.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Any, Callable, Optional

import torch
from torch import Tensor, nn

from ..gaussians import inverse_sigmoid
from ..ops import sigmoid
from ..render.projection import quat_to_rotmat
from ..errors import RegistrationError
from ..registries import Registry
from ..render.reference import ALPHA_MIN


def _edit_rows(params: nn.ParameterDict, optimizers: dict[str, torch.optim.Optimizer],
               fn: Callable[[str, Tensor], Tensor]) -> None:
    """Replace every per-Gaussian parameter p by fn(key, p) and its Adam moments likewise.

    fn for moments gets the moment tensor; rows created by fn are copies of their parent rows
    for parameters and zeros for moments (see `_moment_fn`).
    """
    for key in list(params.keys()):
        old = params[key]
        new = nn.Parameter(fn(key, old.detach()), requires_grad=old.requires_grad)
        opt = optimizers.get(key)
        if opt is not None:
            state = opt.state.pop(old, None)
            for group in opt.param_groups:
                group["params"] = [new if p is old else p for p in group["params"]]
            if state is not None:
                for sk, sv in state.items():
                    if torch.is_tensor(sv) and sv.dim() > 0 and sv.shape[0] == old.shape[0]:
                        state[sk] = fn("__moment__", sv)
                opt.state[new] = state
        params[key] = new


def duplicate(params, optimizers, state: dict, mask: Tensor) -> None:
    """Append a copy of every row where mask [N] is True (moments of the copies start at 0)."""
    idx = torch.nonzero(mask).squeeze(1)

    def fn(key, x):
        return torch.cat([x, torch.zeros_like(x[idx]) if key == "__moment__" else x[idx]])
    _edit_rows(params, optimizers, fn)
    for k, v in state.items():
        if torch.is_tensor(v) and v.dim() > 0:
            state[k] = torch.cat([v, torch.zeros_like(v[idx])])


def split(params, optimizers, state: dict, mask: Tensor, n_split: int = 2,
          scale_div: float = 1.6, generator: torch.Generator | None = None) -> None:
    """Replace every row where mask is True by n_split children sampled from the parent Gaussian.

    Children get positions drawn from the parent's distribution and scales / scale_div; every
    other attribute (SH, opacity, rotation, any extra per-Gaussian tensor) is the parent's.
    Order: the kept rows, then the children (as gsplat does).
    """
    sel = torch.nonzero(mask).squeeze(1)
    rest = torch.nonzero(~mask).squeeze(1)
    scales = torch.exp(params["scales"].detach()[sel])  # [S, 3]
    rot = quat_to_rotmat(params["quats"].detach()[sel])  # [S, 3, 3]
    noise = torch.randn(n_split, sel.numel(), 3, generator=generator, device=scales.device)
    offsets = torch.einsum("sij,nsj->nsi", rot, noise * scales[None])  # [n_split, S, 3]

    def fn(key, x):
        if key == "__moment__":
            return torch.cat([x[rest], torch.zeros_like(x[sel]).repeat(n_split, *[1] * (x.dim() - 1))])
        if key == "means":
            child = (x[sel][None] + offsets).reshape(-1, 3)
        elif key == "scales":
            child = torch.log(torch.exp(x[sel]) / scale_div).repeat(n_split, 1)
        else:
            child = x[sel].repeat(n_split, *[1] * (x.dim() - 1))
        return torch.cat([x[rest], child])
    _edit_rows(params, optimizers, fn)
    for k, v in state.items():
        if torch.is_tensor(v) and v.dim() > 0:
            state[k] = torch.cat([v[rest], torch.zeros_like(v[sel]).repeat(n_split, *[1] * (v.dim() - 1))])


def remove(params, optimizers, state: dict, mask: Tensor) -> None:
    """Delete every row where mask is True."""
    keep = torch.nonzero(~mask).squeeze(1)
    _edit_rows(params, optimizers, lambda key, x: x[keep])
    for k, v in state.items():
        if torch.is_tensor(v) and v.dim() > 0:
            state[k] = v[keep]


def reset_opacity(params, optimizers, value: float) -> None:
    """Clamp every opacity to at most `value` and zero its Adam moments."""
    cap = float(inverse_sigmoid(torch.tensor(value, device="cpu")))
    p = params["opacities"]
    with torch.no_grad():
        p.clamp_(max=cap)
    opt = optimizers.get("opacities")
    if opt is not None and p in opt.state:
        for sv in opt.state[p].values():
            if torch.is_tensor(sv) and sv.dim() > 0:
                sv.zero_()


@dataclass
class DensifyStrategy:
    """3DGS adaptive density control, with a cap on the Gaussian count.

    Every `refine_every` steps in [refine_start, refine_stop): Gaussians whose average
    screen-space mean gradient (3DGS NDC units) exceeds `grow_grad2d` are cloned if small
    (max scale <= grow_scale3d x extent) or split if large; then Gaussians with opacity <
    `prune_opa` are removed, and after `prune_big_after` also those larger than prune_scale3d x
    extent in the world or (unless prune_scale2d is null) prune_scale2d px on screen. Opacity is reset
    every `reset_every`.
    With `reset_white_at_start` and a white background it is also reset once at refine_start
    (3DGS and the peers built on it: Deformable 3DGS, SC-GS, SP-GS, 4DGaussians). `max_gaussians` caps growth: when exceeded, the candidates with the largest gradients win.

    `target_gaussians` (lean densification, a budget as in Taming 3DGS) replaces the gradient
    threshold by a count schedule: at each refinement the model grows to
    n0 + (target - n0) * p Gaussians, n0 the initial count and p the fraction of the refinement
    steps done (1 at the last one), by densifying the seen Gaussians with the largest average
    gradients; pruning is unchanged, so the count ends at or just below the target. A model
    already above the schedule does not grow (the target is never met by pruning).
    """

    name: str = "default"  # the registered strategy (densify=<name>)
    grow_grad2d: float = 2e-4
    grow_scale3d: float = 0.01
    prune_opa: float = 0.005
    prune_scale3d: float = 0.1
    # px on screen (the largest radius since the last refinement); null: no screen-size prune. The
    # reference implementations (3DGS, Deformable 3DGS) read a radius buffer that their
    # densification has just zeroed, so their screen-size prune never removes anything; gsplat
    # leaves it off by default for that reason. budget=paper and budget=gpu follow them.
    prune_scale2d: Optional[float] = 20.0
    prune_big_after: int = 3000
    refine_start: int = 500
    refine_stop: int = 15000
    refine_every: int = 100
    reset_every: int = 3000
    reset_value: float = 0.01
    reset_white_at_start: bool = False  # also reset at refine_start on a white background (3DGS)
    max_gaussians: int = 0  # 0 = no cap
    # true (3DGS and the peers): a Gaussian whose footprint is on screen counts as seen in the
    # gradient average, even when its opacity is below 1/255 and it changes no pixel; false: it
    # does not (what temporal culling in training, render.cull=train, implies for culled rows)
    count_invisible: bool = True
    target_gaussians: int = 0  # 0 = off; else grow towards this count on the schedule above

    def __post_init__(self) -> None:
        if self.target_gaussians < 0:
            raise ValueError(f"densify.target_gaussians={self.target_gaussians}: use 0 (off) or a count")
        if self.target_gaussians and self.max_gaussians and self.target_gaussians > self.max_gaussians:
            raise ValueError(f"densify.target_gaussians={self.target_gaussians} is above densify.max_gaussians="
                             f"{self.max_gaussians}: raise the cap or lower the target")

    @classmethod
    def stages(cls, d) -> tuple[list[tuple[int, str, str]], list[str]]:
        """(events (step, key, what), notes) of config node `d` for the run's schedule."""
        events = [(int(d.refine_start), "densify.refine_start", "densification starts (clone, split, prune)"),
                  (int(d.refine_stop), "densify.refine_stop", "densification stops")]
        notes = [f"opacity reset every {int(d.reset_every)} steps while densifying (densify.reset_every)"
                 ] if int(d.reset_every) > 0 else []
        return events, notes

    def initialize_state(self, n: int, scene_extent: float, white_background: bool = False,
                         device: torch.device | str | None = None) -> dict[str, Any]:
        return {"grad2d": torch.zeros(n, device=device), "count": torch.zeros(n, device=device),
                "max_radii": torch.zeros(n, device=device), "scene_extent": float(scene_extent),
                "white_background": bool(white_background), "initial_count": int(n)}

    def target_at(self, step: int, initial_count: int) -> int:
        """The count the model grows to at refinement step `step` (target_gaussians set)."""
        last = ((self.refine_stop - 1) // self.refine_every) * self.refine_every  # the last refinement
        p = 1.0 if last <= self.refine_start else min(max((step - self.refine_start) / (last - self.refine_start),
                                                          0.0), 1.0)
        return int(round(initial_count + (self.target_gaussians - initial_count) * p))

    def reset_due(self, step: int, state: dict[str, Any]) -> bool:
        """Whether the opacity reset fires after completed step `step` (counted from 1)."""
        if self.reset_every > 0 and step % self.reset_every == 0:
            return True
        return self.reset_white_at_start and bool(state.get("white_background")) and step == self.refine_start

    def last_reset(self, step: int, white_background: bool = False) -> Optional[int]:
        """The last step <= `step` (counted from 1) at which this schedule resets the opacities
        (reset_due's steps; resets happen only while densifying); None before the first."""
        out = []
        end = min(step, self.refine_stop - 1)
        if self.reset_every > 0 and end >= self.reset_every:
            out.append(end // self.reset_every * self.reset_every)
        if self.reset_white_at_start and white_background and self.refine_start <= end:
            out.append(self.refine_start)
        return max(out) if out else None

    def step_post_backward(self, params, optimizers, state, step: int, means2d: Tensor,
                           radii: Tensor, width: int, height: int,
                           generator: torch.Generator | None = None,
                           opacity_fn: Callable[[Any], Tensor] | None = None,
                           reset_fn: Callable[[Any, float], bool] | None = None,
                           rows: Tensor | None = None, opacities: Tensor | None = None) -> dict[str, int]:
        """Accumulate statistics from this step's render and refine when due.

        `step` counts from 1 (the number of completed optimizer steps after this one).
        means2d [M, 2] (with .grad), radii [M] and opacities [M] (what the rasterizer got; needed
        with count_invisible=false) are of the rendered rows `rows` [M] of the N Gaussians (all
        when None: temporal culling renders a subset).
        `opacity_fn(params) -> [N]`: the opacity pruning compares with prune_opa (default
        sigmoid of the opacity logits; STDR passes the largest masked opacity over time).
        `reset_fn(params, value) -> bool`: a plug-in's own reset; when it returns True the
        opacities are left alone (STDR caps its mask while opacity is frozen).
        Returns counts of what was done (for logging).
        """
        if step >= self.refine_stop:
            return {}
        with torch.no_grad():
            vis = radii > 0
            if not self.count_invisible:
                if opacities is None:
                    raise ValueError("densify.count_invisible=false needs the rendered opacities")
                vis &= opacities.detach() >= ALPHA_MIN  # the rasterizer's cut-off
            # by masks over the rendered rows, not by the indices of the visible ones: the same
            # sums (an invisible row adds 0) without a host sync (nonzero waits for the device)
            if means2d.grad is not None:
                g = means2d.grad.detach().clone()
                g[:, 0] *= 0.5 * width  # pixels -> 3DGS NDC units
                g[:, 1] *= 0.5 * height
                add = torch.where(vis, g.norm(dim=-1), 0.0)
                if rows is None:
                    state["grad2d"] += add
                    state["count"] += vis
                else:
                    state["grad2d"].index_add_(0, rows, add)
                    state["count"].index_add_(0, rows, vis.to(state["count"].dtype))
            mr = state["max_radii"] if rows is None else state["max_radii"][rows]
            mr = torch.where(vis, torch.maximum(mr, radii.float()), mr)
            if rows is None:
                state["max_radii"].copy_(mr)
            else:
                state["max_radii"][rows] = mr
        out: dict[str, int] = {}
        if step > self.refine_start and step % self.refine_every == 0:
            out = self._refine(params, optimizers, state, step, generator, opacity_fn)
        if self.reset_due(step, state):
            if reset_fn is None or not reset_fn(params, self.reset_value):
                reset_opacity(params, optimizers, self.reset_value)
            out["reset"] = 1
        return out

    @torch.no_grad()
    def _refine(self, params, optimizers, state, step, generator, opacity_fn=None) -> dict[str, int]:
        extent = state["scene_extent"]
        avg = state["grad2d"] / state["count"].clamp_min(1)
        n = params["means"].shape[0]
        if self.target_gaussians > 0:  # the schedule sets how many grow: the seen rows, largest gradients first
            cand = state["count"] > 0
            room = max(self.target_at(step, state.get("initial_count", n)) - n, 0)
        else:
            cand = avg > self.grow_grad2d
            room = max(self.max_gaussians - n, 0) if self.max_gaussians > 0 else None  # None: no cap
        if room is not None and int(cand.sum()) > room:  # keep the `room` largest gradients (each adds one)
            top = torch.topk(torch.where(cand, avg, torch.full_like(avg, -1.0)), room).indices
            cand = torch.zeros_like(cand)
            cand[top] = True
        is_small = torch.exp(params["scales"]).amax(-1) <= self.grow_scale3d * extent
        dup, spl = cand & is_small, cand & ~is_small
        n_dup, n_split = int(dup.sum()), int(spl.sum())
        duplicate(params, optimizers, state, dup)
        spl = torch.cat([spl, torch.zeros(n_dup, dtype=torch.bool, device=spl.device)])
        split(params, optimizers, state, spl, generator=generator)

        opa = sigmoid(params["opacities"]) if opacity_fn is None else opacity_fn(params)
        prune = opa < self.prune_opa
        if step > self.prune_big_after:
            big = torch.exp(params["scales"]).amax(-1) > self.prune_scale3d * extent
            screen = "" if self.prune_scale2d is None else f" or {self.prune_scale2d} px on screen"
            if self.prune_scale2d is not None:
                big |= state["max_radii"] > self.prune_scale2d
            n_big = int((big & ~prune).sum())
            if n_big > 0.5 * prune.numel():  # measured: a short schedule can lose its whole model here
                fix = ("densify.prune_scale2d=null (the reference's rule: no screen-size prune), "
                       if self.prune_scale2d is not None else "")
                warnings.warn(
                    f"densification at step {step}: the size prune removes {n_big} of {prune.numel()} Gaussians "
                    f"(larger than {self.prune_scale3d} x extent{screen}); the model "
                    f"has not split into small Gaussians by densify.prune_big_after={self.prune_big_after}. "
                    f"Set {fix}raise densify.prune_big_after, or lower densify.grow_grad2d",
                    RuntimeWarning, stacklevel=2)
            prune |= big
        if int(prune.sum()) >= prune.numel():  # never delete the whole model
            prune[:] = False
        n_prune = int(prune.sum())
        remove(params, optimizers, state, prune)
        for k in ("grad2d", "count", "max_radii"):
            state[k].zero_()
        return {"cloned": n_dup, "split": n_split, "pruned": n_prune}


# ==================================================================== the registry
#: every densification strategy by name (stdr.registries.Registry; the entry-point group
#: `stdr.strategies`); `default` is this module's and stays
STRATEGIES: Registry[type] = Registry(
    "densification strategy", "densify.name", "stdr.strategies", "stdr.densify.strategy.register_strategy",
    fixed=("default",), initial={"default": DensifyStrategy})


def register_strategy(name: str, cls: type) -> type:
    """Add a densification strategy: `cls` a dataclass subclassing DensifyStrategy whose `name`
    defaults to `name` (its fields are the `densify.*` keys of `densify=<name>`)."""
    import dataclasses
    if not (isinstance(cls, type) and issubclass(cls, DensifyStrategy) and dataclasses.is_dataclass(cls)):
        raise RegistrationError(f"register_strategy({name!r}): the strategy must be a dataclass subclassing "
                        f"stdr.densify.strategy.DensifyStrategy, got {cls!r}")
    if cls().name != name:
        raise RegistrationError(f"register_strategy({name!r}): {cls.__name__}.name defaults to {cls().name!r}; "
                         f"set `name: str = {name!r}`")
    return STRATEGIES.add(name, cls)


def unregister_strategy(name: str) -> None:
    STRATEGIES.remove(name)


def get_strategy(name: Optional[str]) -> type:
    return STRATEGIES.get(name or "default")


def build_strategy(d) -> DensifyStrategy:
    """The strategy of config node `d` (a DictConfig or dict of `densify.*`)."""
    from omegaconf import OmegaConf
    kw = OmegaConf.to_container(d) if OmegaConf.is_config(d) else dict(d)
    return get_strategy(kw.get("name"))(**kw)
