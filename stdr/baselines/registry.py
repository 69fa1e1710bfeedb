"""The one list of baselines: a name, its deformation module and its config dataclass.

Adding a baseline is one module and one config (docs/baselines.md, "Adding a baseline"):

    @dataclass
    class MyConfig(BaselineConfig):      # typed defaults of `baseline.*` for baseline=mine
        name: str = "mine"
        ...

    class MyDeformation(Deformation):
        capabilities = frozenset({"conditioning"})  # optional: what it can do
        @classmethod
        def config_kwargs(cls, b, cond_dim=0, train_times=None, seed=0, schedule=None): ...
        def forward(self, params, t, cond=None): ...

    register_baseline("mine", MyDeformation, MyConfig)

Registering makes `baseline=mine` a Hydra option, derives the experiments `<data>_mine` and
`<data>_mine_stdr` for every data option, and lets tests iterate over it. A budget file
stdr/configs/budget_baseline/mine_<budget>.yaml is optional.
"""
from __future__ import annotations

import dataclasses
import inspect
from dataclasses import dataclass
from typing import Any, Optional

import numpy as np

from ..registries import CAPABILITY_NAMES, Registry
from ..context import check_hooks
from ..errors import RegistrationError
from .base import BaselineConfig, Deformation


@dataclass(frozen=True)
class BaselineSpec:
    name: str
    module: type       # a Deformation subclass
    config: type       # a BaselineConfig subclass whose `name` default is `name`
    in_grids: bool = False  # whether the default grids (${stdr_experiments:<data>}) include it
    #: whether baseline.precision=auto trains it in bf16 on a CPU with bf16 matrix instructions: set
    #: only where its bf16 training is faster and passed the val rule, plain and with each built-in
    #: plug-in (docs/performance.md, "bf16 by default")
    bf16_default: bool = False


#: every baseline by name (stdr.registries.Registry; the entry-point group `stdr.baselines`)
BASELINES: Registry[BaselineSpec] = Registry(
    "baseline", "baseline.name", "stdr.baselines", "stdr.baselines.registry.register_baseline",
    owner=lambda spec: spec.module)


#: names of the earlier Deformation interface, and what replaced each
RENAMED = {
    "setup": "init_gaussians(params) sets up what the module derives from the Gaussians",
    "gaussian_params": "init_gaussians(params) adds the module's per-Gaussian tensors to the parameter dict",
    "gaussian_lr": "give a per-Gaussian tensor's rate as an entry {'key': ..., 'lr': ...} of param_groups()",
    "takes_conditioning": "declare capabilities = frozenset({'conditioning'})",
    "canonical_opacity": "declare 'opacity_deltas' in capabilities when the deltas change opacity",
    "bf16_default": "pass bf16_default=True to register_baseline",
    "apply": "name the delta rule apply_rule",
    "deform": "the model renders through stdr.baselines.base.deform_gaussians(module, ...)",
    "deform_rows": "the model renders through stdr.baselines.base.deform_gaussians(module, ..., rows=rows)",
    "deltas": "stdr.baselines.base.network_deltas(module, ...) runs the network in its precision",
}


def capabilities(module: type) -> frozenset[str]:
    """The capabilities a Deformation subclass declares."""
    return frozenset(module.capabilities)


def check_capabilities(name: str, module: type) -> None:
    """A module's `capabilities`: a set of known names, each backed by what it needs (a
    TypeError naming the class and the hook to fix)."""
    caps = module.capabilities
    if isinstance(caps, str) or not isinstance(caps, (frozenset, set, tuple, list)) \
            or any(c not in CAPABILITY_NAMES for c in caps):
        raise RegistrationError(f"register_baseline({name!r}): {module.__name__}.capabilities must be a set of names from "
                        f"{CAPABILITY_NAMES}, got {caps!r} (docs/baselines.md, \"Capabilities\")")
    if "conditioning" in caps and "cond_dim" not in inspect.signature(module.config_kwargs).parameters:
        raise RegistrationError(f"register_baseline({name!r}): {module.__name__} declares 'conditioning' but its "
                        "config_kwargs takes no cond_dim to pass on: implement config_kwargs(b, cond_dim, ...)")
    overrides = module.forward_rows is not Deformation.forward_rows
    if overrides != ("mixes_rows" in caps):
        raise RegistrationError(f"register_baseline({name!r}): {module.__name__} " + (
            "overrides forward_rows but does not declare 'mixes_rows' in its capabilities: add it (a Gaussian's "
            "deltas depend on other rows)" if overrides else
            "declares 'mixes_rows' but does not override forward_rows: implement forward_rows(params, t, cond, rows)"))


def register_baseline(name: str, module: type, config: type, in_grids: bool = False,
                      bf16_default: bool = False) -> BaselineSpec:
    """Add a baseline. `config` must subclass BaselineConfig and default `name` to `name`;
    `module` must subclass Deformation and implement `config_kwargs`; its `capabilities`
    (CAPABILITY_NAMES) are checked here. `in_grids`: whether the default grids
    (`${stdr_experiments:<data>}`: the dnerf_grid and stability sweeps) include it; the built-ins
    do, and a baseline from another package does not unless it says so, so installing one changes
    no grid a study has run. `bf16_default`: baseline.precision=auto trains it in bf16 on a CPU
    with bf16 matrix instructions (only where that was verified: docs/performance.md)."""
    for key, v in (("in_grids", in_grids), ("bf16_default", bf16_default)):
        if not isinstance(v, bool):
            raise RegistrationError(f"register_baseline({name!r}): {key} must be True or False, got {v!r}")
    if not (isinstance(module, type) and issubclass(module, Deformation)):
        raise RegistrationError(f"register_baseline({name!r}): module must be a Deformation subclass, got {module!r}")
    check_capabilities(name, module)
    check_hooks(f"register_baseline({name!r})", module, Deformation, {"before_step": 1, "regularizers": 1}, RENAMED)
    if not (dataclasses.is_dataclass(config) and issubclass(config, BaselineConfig)):
        raise RegistrationError(f"register_baseline({name!r}): config must be a dataclass subclassing BaselineConfig, "
                        f"got {config!r}")
    if config().name != name:
        raise RegistrationError(f"register_baseline({name!r}): {config.__name__}.name defaults to {config().name!r}; "
                         f"set `name: str = {name!r}`")
    return BASELINES.add(name, BaselineSpec(name, module, config, in_grids, bf16_default))


def unregister_baseline(name: str) -> None:
    """Remove a baseline and its Hydra options (for tests that register a temporary one)."""
    BASELINES.remove(name)


def discover_baselines() -> list[str]:
    """Register the baselines that installed distributions provide through the entry-point
    group `stdr.baselines` (once per process). Returns the names added."""
    return BASELINES.discover()


def get_baseline(name: str) -> BaselineSpec:
    return BASELINES.get(name)


def build_deformation(b: Any, cond_dim: int = 0, train_times: Optional[np.ndarray] = None, seed: int = 0,
                      schedule=None) -> Deformation:
    """The deformation module of baseline config `b` (its `name` picks the registered module)."""
    return get_baseline(b.name).module.from_config(b, cond_dim, train_times, seed, schedule)
