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
from dataclasses import dataclass
from typing import Any, Callable, Optional

import numpy as np

from .base import BaselineConfig, Deformation


@dataclass(frozen=True)
class BaselineSpec:
    name: str
    module: type       # a Deformation subclass
    config: type       # a BaselineConfig subclass whose `name` default is `name`


BASELINES: dict[str, BaselineSpec] = {}
# called with (spec, added) on every (un)registration; stdr.config.register() adds the one that
# keeps Hydra's ConfigStore in step, so a baseline registered later still becomes an option
_LISTENERS: list[Callable[[BaselineSpec, bool], None]] = []


def add_listener(fn: Callable[[BaselineSpec, bool], None]) -> None:
    if fn not in _LISTENERS:
        _LISTENERS.append(fn)


def register_baseline(name: str, module: type, config: type) -> BaselineSpec:
    """Add a baseline. `config` must subclass BaselineConfig and default `name` to `name`;
    `module` must subclass Deformation and implement `config_kwargs`."""
    if not (isinstance(module, type) and issubclass(module, Deformation)):
        raise TypeError(f"register_baseline({name!r}): module must be a Deformation subclass, got {module!r}")
    if not (dataclasses.is_dataclass(config) and issubclass(config, BaselineConfig)):
        raise TypeError(f"register_baseline({name!r}): config must be a dataclass subclassing BaselineConfig, "
                        f"got {config!r}")
    if config().name != name:
        raise ValueError(f"register_baseline({name!r}): {config.__name__}.name defaults to {config().name!r}; "
                         f"set `name: str = {name!r}`")
    if name in BASELINES and BASELINES[name].module is not module:
        raise ValueError(f"baseline {name!r} is already registered (by {BASELINES[name].module.__name__})")
    spec = BaselineSpec(name, module, config)
    BASELINES[name] = spec
    for fn in _LISTENERS:
        fn(spec, True)
    return spec


def unregister_baseline(name: str) -> None:
    """Remove a baseline and its Hydra options (for tests that register a temporary one)."""
    spec = BASELINES.pop(name, None)
    if spec is not None:
        for fn in _LISTENERS:
            fn(spec, False)


#: entry-point group through which another distribution adds baselines: in its pyproject.toml,
#:   [project.entry-points."stdr.baselines"]
#:   mine = "my_package.mine:register"     # a function that calls register_baseline (or a module
#:                                         # whose import does)
ENTRY_POINT_GROUP = "stdr.baselines"
_discovered = False


def discover_baselines() -> list[str]:
    """Register the baselines that installed distributions provide through ENTRY_POINT_GROUP
    (once per process; the CLIs' config registration and get_baseline call it). Returns the
    names added. An entry point that fails, or registers nothing, is an error naming it."""
    global _discovered
    if _discovered:
        return []
    _discovered = True
    from ..entry_points import load_group
    return load_group(ENTRY_POINT_GROUP, lambda: BASELINES, "stdr.baselines.register_baseline")


def get_baseline(name: str) -> BaselineSpec:
    if name not in BASELINES:
        discover_baselines()
    if name not in BASELINES:
        raise ValueError(f"baseline.name={name!r} is not a registered baseline; choose one of {sorted(BASELINES)} "
                         "(stdr.baselines.registry.register_baseline adds one)")
    return BASELINES[name]


def build_deformation(b: Any, cond_dim: int = 0, train_times: Optional[np.ndarray] = None, seed: int = 0,
                      schedule=None) -> Deformation:
    """The deformation module of baseline config `b` (its `name` picks the registered module)."""
    return get_baseline(b.name).module.from_config(b, cond_dim, train_times, seed, schedule)
