"""The deformation interface shared by all baselines.

A deformation module maps canonical Gaussians, a time t in [0, 1] and an optional per-Gaussian
conditioning tensor (STDR supplies one) to `Deltas`, and says how those deltas are applied.
The baselines differ in that rule, so it is explicit, never unified silently:

- Deformable 3DGS (`deform`): added *after* activation - means + dx, exp(log s) + ds,
  normalize(q) + dq (the rasterizer normalizes again).
- 4DGaussians (`4dgs`): added *before* activation - log s + ds, q + dq, then activations.
- SC-GS blends control-node transforms and SP-GS applies a rigid SO(3) + translation per
  superpoint into translations and rotations, then the post-activation rule.
"""
from __future__ import annotations

import inspect
from dataclasses import dataclass, field
from typing import Any, List, Optional

import numpy as np
import torch
from omegaconf import II, OmegaConf
from torch import Tensor, nn

from ..errors import ConfigError
from .. import device as devices  # module attribute: cpu_bf16_flags is looked up at call time
from ..ops import RowView, rows_of, sigmoid
from ..gaussians import Gaussians
from ..context import StepContext


#: the static warm-up's share of the run when no budget file sets baseline.warmup: Deformable
#: 3DGS's published 3 000 of 40 000 iterations, so the paper length gives the published value
WARMUP_SHARE = 0.075


def flag_value(module: nn.Module, name: str):
    """A 0-d buffer of `module` (a stage or readiness flag kept as a buffer so checkpoints carry
    it) as a Python number. The value is remembered with the buffer's identity and version: it is
    read from the device only after something else changed it (a checkpoint load, `.to()`), so
    an ordinary training step does not wait for the device to test a flag."""
    buf = getattr(module, name)
    key = (id(buf), buf._version)
    memo = module.__dict__.setdefault("_flag_values", {})
    hit = memo.get(name)
    if hit is not None and hit[0] == key:
        return hit[1]
    v = buf.item()
    memo[name] = (key, v, buf)  # (the buffer kept alive: its id stays its own)
    return v


def set_flag(module: nn.Module, name: str, value) -> None:
    """Fill a 0-d buffer and remember its new value (see flag_value)."""
    buf = getattr(module, name)
    buf.fill_(value)
    v = bool(value) if buf.dtype == torch.bool else float(value) if buf.is_floating_point() else int(value)
    module.__dict__.setdefault("_flag_values", {})[name] = ((id(buf), buf._version), v, buf)


def _share(iterations, share) -> int:
    return int(round(int(iterations) * float(share)))


if not OmegaConf.has_resolver("stdr_share"):  # at import: saved configs may hold the interpolation
    OmegaConf.register_new_resolver("stdr_share", _share)


@dataclass
class BaselineConfig:
    """Keys every baseline has (`baseline.*`). A baseline's own config subclasses this with its
    defaults (the published values) and its own sub-config (`baseline.scgs.*`, ...); it is
    registered with the module (stdr.baselines.registry.register_baseline) and becomes the Hydra
    option `baseline=<name>`. Budget files (stdr/configs/budget_baseline/<name>_<budget>.yaml) are
    optional deltas on top. The schedule keys scale with the run unless a budget file sets them:
    `warmup` = WARMUP_SHARE x optim.iterations, `lr_max_steps` = optim.iterations (a baseline
    without budget files trains its deformation under every budget)."""

    name: str = "deform"
    # static iterations before the deformation is applied (default: 7.5 % of the run)
    warmup: int = II(f"stdr_share:${{optim.iterations}},{WARMUP_SHARE}")
    depth: int = 8
    width: int = 256
    skips: List[int] = field(default_factory=lambda: [4])
    xyz_freqs: int = 10
    t_freqs: int = 6
    time_net: bool = True
    time_out: int = 30
    head_init_std: Optional[float] = None  # None: PyTorch default (published); 1e-5: start at identity
    lr_init: float = 8e-4
    lr_final: float = 1.6e-6
    lr_max_steps: int = II("optim.iterations")  # the network's lr decays over the whole run
    lr_from_warmup: bool = False    # the network's lr schedule starts at the warm-up's end (4DGS restarts it)
    # the network's arithmetic: "fp32"; "bf16" (autocast: matrix products in bfloat16 with fp32
    # accumulation, deltas returned in fp32); or "auto": bf16 on a CPU with AVX512-BF16 or AMX for a
    # baseline whose bf16 training passed its speed and val checks (register_baseline(..., bf16_default=True)),
    # fp32 elsewhere (CUDA included, until bf16 is verified on a GPU). A run records the precision
    # it chose in config.yaml and metrics.json; docs/performance.md has the rule and measurements
    precision: str = "auto"
    # the deformation MLP (deform's network; scgs's and spgs's trunk) through torch.compile
    # (inductor, dynamic shapes). Off: on the CPU it is no faster at budget=cpu sizes and costs
    # seconds of compilation a process (docs/performance.md); not measured on a GPU yet. 4dgs has no
    # compiled form of its network (its HexPlane sampling is a kernel: baseline.hexplane.compiled)
    compile: bool = False
    # the direct nearest-neighbour search (`baseline.scgs.knn=direct`, `baseline.spgs.knn=direct`)
    # as a compiled kernel (stdr.knn.knn_direct): null = where it has been checked
    # (stdr.verified.VERIFIED: the CPU), false = its torch twin; both give the same bits
    knn_compiled: Optional[bool] = None


def mlp_kwargs(b: Any, cond_dim: int) -> dict:
    """Constructor arguments of the shared MLP trunk (DeformMLP) from the common baseline keys."""
    return dict(depth=b.depth, width=b.width, skips=list(b.skips), xyz_freqs=b.xyz_freqs, t_freqs=b.t_freqs,
                cond_dim=cond_dim, head_init_std=b.head_init_std)


def stage_start(b: Any, schedule=None) -> int:
    """The step at which a module's own stages begin: the schedule's end of the static warm-up
    (baseline.warmup without a schedule)."""
    return int(b.warmup) if schedule is None else int(schedule.static_warmup_end)


@dataclass
class Deltas:
    means: Optional[Tensor] = None      # [N, 3]
    quats: Optional[Tensor] = None      # [N, 4]
    scales: Optional[Tensor] = None     # [N, 3]
    opacities: Optional[Tensor] = None  # [N]


def _add(x: Tensor, d: Optional[Tensor]) -> Tensor:
    return x if d is None else x + d


def apply_post_activation(params, d: Deltas) -> Gaussians:
    """Deformable-3DGS rule: deltas added to activated values."""
    q = params["quats"]
    return Gaussians(
        means=_add(params["means"], d.means),
        quats=_add(q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12), d.quats),
        scales=_add(torch.exp(params["scales"]), d.scales),
        opacities=sigmoid(params["opacities"]) if d.opacities is None
        else (sigmoid(params["opacities"]) + d.opacities).clamp(0.0, 1.0),
        sh=torch.cat([params["sh0"], params["shN"]], 1),
    )


def apply_pre_activation(params, d: Deltas) -> Gaussians:
    """4DGaussians rule: deltas added to stored (pre-activation) values, then activated."""
    return Gaussians(
        means=_add(params["means"], d.means),
        quats=_add(params["quats"], d.quats),
        scales=torch.exp(_add(params["scales"], d.scales)),
        opacities=sigmoid(_add(params["opacities"], d.opacities)),
        sh=torch.cat([params["sh0"], params["shN"]], 1),
    )


class Deformation(nn.Module):
    """Base class. A minimal baseline implements `config_kwargs` and `forward` (and its
    constructor); everything else is optional, with defaults.

    Declared (class attributes, checked at registration):
    - `capabilities`: what the module can do, by the names a plug-in's `requires` uses
      (stdr.registries.CAPABILITY_NAMES): "conditioning" (its forward takes a plug-in's
      per-Gaussian `cond`: config_kwargs passes cond_dim to it and it sets self.cond_dim),
      "opacity_deltas" (its deltas change opacity: temporal culling is then off for it),
      "mixes_rows" (a Gaussian's deltas depend on other Gaussians: it overrides `forward_rows`).
    - `apply_rule`: how deltas are applied (apply_post_activation or apply_pre_activation).

    Hooks the one training loop calls (all optional; the defaults do nothing), each training
    hook with the step's one context (stdr.context.StepContext: step, phase, time, camera, params,
    the conditioning `cond` the render uses, the deformed Gaussians and the render):
    - `init_gaussians(params)`: once the Gaussians exist, per-Gaussian tensors the module adds to
      the parameter dict (SC-GS's hyper-coordinates, SP-GS's association logits: densification
      keeps them aligned) and what it derives from them (4DGS's bounds).
    - `param_groups()`: network parameter groups with an lr multiplier each (4DGS's grid), and
      the learning rate of each per-Gaussian tensor it added ({"key": ..., "lr": ...}).
    - `before_step(ctx)`: every training step (SP-GS refreshes superpoint centres, SC-GS
      switches from its node stage to skinning).
    - `regularizers(ctx)`: named loss terms, already weighted, added after the static warm-up.
    - `stages(b)` (a classmethod, from the baseline config alone): the module's own events
      [(step, config key, what happens)] and switch windows [(name, first, last)] in which it
      changes its structure (SC-GS: node resampling and the detached steps after it); they go
      into the run's one schedule (stdr.schedule), which keeps STDR's freeze out of a window.
    - `forward_rows(params, t, cond, rows)`: the deltas of some rows alone (temporal culling).
    - `compile_network()`: baseline.compile=true.

    A built module has `cond_dim` (the conditioning width it was built for, 0 = none) and
    `precision` ("fp32" or "bf16": the arithmetic of its deltas, set by `from_config`).
    """

    capabilities: frozenset = frozenset()
    apply_rule = staticmethod(apply_post_activation)

    def __init__(self):
        super().__init__()
        self.cond_dim = 0  # a module built for a conditioning sets its width after this
        self.precision = "fp32"

    @classmethod
    def config_kwargs(cls, b: Any, cond_dim: int = 0, train_times: Optional[np.ndarray] = None, seed: int = 0,
                      schedule=None) -> dict:
        """Constructor arguments from the baseline config `b` (the baseline's registered
        dataclass), the plug-ins' conditioning width, the training times, the run's seed and its
        schedule. Every registered module implements it."""
        raise NotImplementedError(f"{cls.__name__} must implement config_kwargs(b, cond_dim, train_times, seed, "
                                  "schedule) to be built from a config")

    @classmethod
    def from_config(cls, b: Any, cond_dim: int = 0, train_times: Optional[np.ndarray] = None, seed: int = 0,
                    schedule=None) -> "Deformation":
        """The module of a baseline config (see `config_kwargs`)."""
        kwargs = cls.config_kwargs(b, cond_dim, train_times, seed, schedule)
        try:
            inspect.signature(cls).bind(**kwargs)
        except TypeError as e:
            raise TypeError(f"{cls.__name__}.config_kwargs returned arguments {cls.__name__}.__init__ does not take "
                            f"({e}): make config_kwargs return the constructor's keyword arguments") from None
        module = cls(**kwargs)
        if module.cond_dim != cond_dim:
            name = getattr(b, "name", cls.__name__)
            raise ConfigError(
                f"baseline {name} ({cls.__name__}) was built for per-Gaussian conditioning of width {module.cond_dim}, "
                f"but the plug-ins on feed {cond_dim} (STDR's separated field): its config_kwargs must pass cond_dim "
                "to the module, which sets self.cond_dim and takes `cond` in forward (the capability "
                f"'conditioning' in {cls.__name__}.capabilities declares); or train it without those plug-ins (stdr=off)")
        module.precision = check_precision(getattr(b, "precision", "fp32"))
        if getattr(b, "compile", False):
            module.compile_network()
        return module

    def compile_network(self) -> None:
        """baseline.compile=true: run this module's network through torch.compile. A module with
        a compiled form overrides this."""
        raise ValueError(f"baseline.compile=true: the {getattr(self, 'name', type(self).__name__)} deformation "
                         f"({type(self).__name__}) has no torch.compile form; set baseline.compile=false")

    def init_gaussians(self, params) -> None:
        """Once the Gaussians exist (`params` holds them): add the per-Gaussian tensors this module
        owns that are not in it yet, and set up what the module derives from the Gaussians."""

    def param_groups(self) -> list[dict]:
        """Network groups {"params", "name", "lr_mult"} (on the baseline's schedule times lr_mult),
        and one {"key", "lr"} per per-Gaussian tensor the module adds (a constant rate, not
        scaled by optim.spatial_lr_scale)."""
        return [{"params": list(self.parameters()), "name": "deform", "lr_mult": 1.0}]

    def before_step(self, ctx: StepContext) -> None:
        pass

    def regularizers(self, ctx: StepContext) -> dict[str, Tensor]:
        return {}

    @classmethod
    def stages(cls, b) -> tuple[list[tuple[int, str, str]], list[tuple[str, int, int]]]:
        return [], []

    def forward(self, params, t: float, cond: Optional[Tensor] = None) -> Deltas:  # pragma: no cover
        raise NotImplementedError

    def forward_rows(self, params, t: float, cond: Optional[Tensor], rows: Tensor) -> Deltas:
        """Deltas [M] of the Gaussians `rows` [M] alone (temporal culling). The default runs
        `forward` on those rows, right for modules whose deltas are per Gaussian (deform, 4dgs);
        modules with a part shared by all Gaussians (SC-GS's node conditioning, SP-GS's
        superpoints) compute that part from every row, so the kept rows' deltas are those of
        the full call, and declare "mixes_rows"."""
        return self.forward(RowView(params, rows), t, rows_of(cond, rows))


def canonical_opacity(module: Deformation) -> bool:
    """Whether the module leaves the activated opacity at sigmoid(params["opacities"]) (no
    "opacity_deltas"): then a Gaussian's opacity at time t is known before the network runs, and
    temporal culling (render.cull) may skip rows that cannot reach 1/255."""
    return "opacity_deltas" not in module.capabilities


def network_deltas(module: Deformation, params, t: float, cond: Optional[Tensor] = None,
                   rows: Optional[Tensor] = None) -> Deltas:
    """Deltas [N] (or [M] of `rows`) in fp32, computed in the module's `precision`: every render
    path (`deform_gaussians`, the model's static rows) calls the network through this."""
    def run() -> Deltas:
        return module.forward(params, t, cond) if rows is None else module.forward_rows(params, t, cond, rows)
    if module.precision != "bf16":
        return run()
    with torch.autocast(device_type=params["means"].device.type, dtype=torch.bfloat16):
        d = run()
    return Deltas(**{k: None if v is None else v.float() for k, v in vars(d).items()})


def deform_gaussians(module: Deformation, params, t: float, cond: Optional[Tensor] = None,
                     delta_scale: Optional[Tensor] = None, rows: Optional[Tensor] = None) -> Gaussians:
    """Deformed, activated Gaussians at time t: all of them, or the rows `rows` [M] alone
    (Gaussians [M], equal to those rows of the full call up to float rounding of batched
    kernels; gradients reach only those rows).

    cond [N, cond_dim]: per-Gaussian conditioning (STDR's separated field).
    delta_scale [N, 1]: every delta is multiplied by it before it is applied (STDR's dynamic
    probability, when stdr.scale_deltas_by_dynamic is on).
    """
    n = params["means"].shape[0]
    if cond is not None and cond.shape != (n, module.cond_dim):
        raise ValueError(f"conditioning must be [N, {module.cond_dim}], got {tuple(cond.shape)}")
    d = network_deltas(module, params, t, cond, rows)
    if rows is None:
        return module.apply_rule(params, _scaled(d, delta_scale, n))
    return module.apply_rule(RowView(params, rows), _scaled(d, rows_of(delta_scale, rows), rows.shape[0]))


PRECISIONS = ("fp32", "bf16")


def check_precision(p: str) -> str:
    if p not in (*PRECISIONS, "auto"):
        raise ValueError(f"baseline.precision={p!r}: use one of {('auto', *PRECISIONS)}")
    return p


def choose_precision(requested: str, bf16_default: bool, device: torch.device, cpu_flags=None,
                     name: str = "this baseline") -> tuple[str, str]:
    """(precision, why) of a run: `requested` is baseline.precision, `bf16_default` the
    baseline's registration (BaselineSpec.bf16_default: its bf16 training was verified), `device`
    the run's. `auto` is bf16 on a CPU with bf16 matrix instructions (stdr.device.cpu_bf16_flags,
    or `cpu_flags`) for a baseline with `bf16_default`, fp32 otherwise; `why` is one line that says
    which and why (empty for an explicit fp32)."""
    check_precision(requested)
    flags = devices.cpu_bf16_flags() if cpu_flags is None and device.type == "cpu" else tuple(cpu_flags or ())
    if requested == "fp32":
        return "fp32", ""
    if requested == "bf16":
        if device.type == "cpu" and not flags:
            return "bf16", (devices.emulated_bf16_note("baseline.precision")
                            + " (baseline.precision=auto picks fp32 on this CPU)")
        return "bf16", ""
    if device.type != "cpu":
        return "fp32", (f"baseline.precision=auto: fp32 (bf16 is not yet verified on {device.type}; "
                        "baseline.precision=bf16 to try it)")
    if not flags:
        return "fp32", "baseline.precision=auto: fp32 (this CPU has no AVX512-BF16 or AMX)"
    if not bf16_default:
        return "fp32", (f"baseline.precision=auto: fp32 ({name} is not among the baselines whose bf16 training is "
                        "faster and passed the val check; docs/performance.md, 'bf16 by default')")
    return "bf16", f"baseline.precision=auto: bf16 (this CPU has {', '.join(flags).upper()}; {name} verified in bf16)"


def _scaled(d: Deltas, delta_scale: Optional[Tensor], n: int) -> Deltas:
    """Every delta times delta_scale [n, 1] (STDR's dynamic probability), or d unchanged."""
    if delta_scale is None:
        return d
    if delta_scale.shape != (n, 1):
        raise ValueError(f"delta_scale must be [N, 1], got {tuple(delta_scale.shape)}")
    return Deltas(**{k: None if v is None else v * (delta_scale if v.dim() == 2 else delta_scale[:, 0])
                     for k, v in vars(d).items()})
