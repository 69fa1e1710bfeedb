"""The one list of baselines: a name, its deformation module and its config dataclass.

Adding a baseline is one module and one config (docs/baselines.md, "Adding a baseline"):

    @dataclass
    class MyConfig(BaselineConfig):      # typed defaults of `baseline.*` for baseline=mine
        name: str = "mine"
        ...

    class MyDeformation(Deformation):
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
from .base import BaselineConfig, Deformation


@dataclass(frozen=True)
class BaselineSpec:
    name: str
    module: type       # a Deformation subclass
    config: type       # a BaselineConfig subclass whose `name` default is `name`
    in_grids: bool = False  # whether the default grids (${stdr_experiments:<data>}) include it


#: every baseline by name (stdr.registries.Registry; the entry-point group `stdr.baselines`)
BASELINES: Registry[BaselineSpec] = Registry(
    "baseline", "baseline.name", "stdr.baselines", "stdr.baselines.registry.register_baseline",
    owner=lambda spec: spec.module)


#: what a baseline can do, by the names a plug-in's `requires` uses, each read from the module class:
#: "conditioning" - it takes a plug-in's per-Gaussian conditioning (Deformation.takes_conditioning);
#: "opacity_deltas" - its deltas change opacity (Deformation.canonical_opacity is False);
#: "mixes_rows" - a Gaussian's deltas depend on other Gaussians (it overrides forward_rows)
CAPABILITIES = {
    "conditioning": lambda m: m.takes_conditioning,
    "opacity_deltas": lambda m: not m.canonical_opacity,
    "mixes_rows": lambda m: m.forward_rows is not Deformation.forward_rows,
}
assert tuple(CAPABILITIES) == CAPABILITY_NAMES  # the names plug-ins require (stdr.registries)
#: the class attributes that declare capabilities (booleans, checked at registration)
DECLARED = ("takes_conditioning", "canonical_opacity")


def capabilities(module: type) -> frozenset[str]:
    """The capabilities (CAPABILITIES) a Deformation subclass declares."""
    return frozenset(c for c, has in CAPABILITIES.items() if has(module))


def register_baseline(name: str, module: type, config: type, in_grids: bool = False) -> BaselineSpec:
    """Add a baseline. `config` must subclass BaselineConfig and default `name` to `name`;
    `module` must subclass Deformation and implement `config_kwargs`; its capabilities
    (CAPABILITIES) are declared by class attributes (DECLARED) that must be booleans.
    `in_grids`: whether the default grids (`${stdr_experiments:<data>}`: the dnerf_grid and
    stability sweeps) include it; the built-ins do, and a baseline from another package does not
    unless it says so, so installing one changes no grid a study has run."""
    if not isinstance(in_grids, bool):
        raise TypeError(f"register_baseline({name!r}): in_grids must be True or False, got {in_grids!r}")
    if not (isinstance(module, type) and issubclass(module, Deformation)):
        raise TypeError(f"register_baseline({name!r}): module must be a Deformation subclass, got {module!r}")
    for attr in DECLARED:
        if not isinstance(getattr(module, attr), bool):
            raise TypeError(f"register_baseline({name!r}): {module.__name__}.{attr} must be True or False, got "
                            f"{getattr(module, attr)!r} (docs/baselines.md, \"Capabilities\")")
    if module.takes_conditioning and "cond_dim" not in inspect.signature(module.config_kwargs).parameters:
        raise TypeError(f"register_baseline({name!r}): {module.__name__}.takes_conditioning is True but its "
                        "config_kwargs takes no cond_dim to pass on: implement config_kwargs(b, cond_dim, ...)")
    if not (dataclasses.is_dataclass(config) and issubclass(config, BaselineConfig)):
        raise TypeError(f"register_baseline({name!r}): config must be a dataclass subclassing BaselineConfig, "
                        f"got {config!r}")
    if config().name != name:
        raise ValueError(f"register_baseline({name!r}): {config.__name__}.name defaults to {config().name!r}; "
                         f"set `name: str = {name!r}`")
    return BASELINES.add(name, BaselineSpec(name, module, config, in_grids))


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
