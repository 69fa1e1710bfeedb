"""Plug-ins: components that attach to any baseline (STDR is one).

A plug-in may add per-Gaussian parameters (kept aligned by densification because they live in
the model's parameter dict), networks with their own parameter groups and learning-rate
schedules, a conditioning input for the deformation network, a factor on opacity, loss terms,
and its own say in the densification's opacity reset and pruning. The interface is
`stdr.plugins.interface`: `Plugin` and the optional roles `Conditioner`, `Densifying` and
`Reporting`; the model and the training loop call the hooks on every plug-in in order, each with
the step's one context (stdr.context.StepContext); every default does nothing, so a plug-in
implements only what it changes.

A plug-in is registered like a baseline (`register_plugin`, below): its config dataclass
becomes the typed node `cfg.<name>` with the options `<name>=on|off`, every baseline it applies
to (PluginSpec.missing: the capabilities it requires, its own list of baselines) gets the
experiments `<data>_<baseline>_<name>`, its phase boundaries join the run's one schedule
(`Plugin.stages`), its label follows the baseline's name in tables and charts, and `stdr-eval`
accepts `<name>.<key>=...` to change a run's plug-in keys at evaluation time. The built-in
plug-ins register on first use of the registry; other distributions add theirs through the
entry-point group `stdr.plugins` (docs/extending.md).

Several plug-ins combine as follows: their conditionings are concatenated in order (the
deformation network is built for the sum of their `cond_dim`), delta scales and opacity factors
multiply, loss terms are summed (logged as `loss/<plug-in>_<term>`), and the first plug-in whose
`reset_opacity` returns True handles the densification's opacity reset.
"""
from __future__ import annotations

import dataclasses
import re
from dataclasses import dataclass, field
from typing import Any, Callable, Optional

from ..errors import RegistrationError
from ..registries import CAPABILITY_NAMES, Registry
from .interface import Conditioner, Densifying, Plugin, Reporting, check_plugin_class  # noqa: F401  (the interface)


# ==================================================================== the registry
@dataclass(frozen=True)
class PluginSpec:
    name: str      # config node and group (cfg.<name>, <name>=on|off), experiments <data>_<baseline>_<name>
    plugin: type   # a Plugin subclass whose `name` is `name`
    config: type   # a dataclass with `enabled: bool = False`
    label: str     # after the baseline's name in tables and charts (e.g. "+STDR")
    #: tags after the label in table rows (stdr.eval.table.method_suffix) for the plug-in's
    #: switches that differ from their defaults (e.g. ['w/o spatial_reg']), so ablation rows never
    #: merge: a function of the plug-in's config node as a plain dict
    row_tags: Callable[[dict], list[str]] = field(default=lambda pcfg: [], compare=False)
    #: the baseline capabilities it needs (stdr.registries.CAPABILITY_NAMES), a function of its
    #: config node (its registered dataclass's defaults for the derived experiments and grids)
    requires: Callable[[Any], tuple] = field(default=lambda pcfg: (), compare=False)
    #: the baselines it applies to, by name (None: every baseline with the capabilities it requires)
    baselines: Optional[tuple[str, ...]] = None
    #: whether it joins the default grids (`${stdr_experiments:<data>}`, the dnerf_grid sweeps)
    in_grids: bool = False
    #: keys that earlier versions wrote under its config node: a saved config that carries them
    #: still loads (they are dropped)
    removed_keys: tuple[str, ...] = ()

    def missing(self, baseline: str, capabilities: frozenset, node: Any = None) -> list[str]:
        """Why it cannot run with `baseline` (whose capabilities are given): the capabilities it
        lacks, or that the plug-in names other baselines; [] when it applies. `node`: the
        plug-in's config node (default: its dataclass's defaults)."""
        if self.baselines is not None and baseline not in self.baselines:
            return [f"{self.name} applies to the baselines {', '.join(self.baselines)} only"]
        need = self.requires(self.config() if node is None else node)
        return [f"{self.name} needs a baseline with the capability {c!r}" for c in need if c not in capabilities]


#: the names a plug-in may not take: the run config's own sections (stdr.config.Config), stdr-eval's
#: keys (stdr.config.EvalAppConfig) and the config groups of stdr-train (tests/test_plugin_registry.py
#: checks that it covers both schemas)
RESERVED_KEYS = frozenset({
    "baseline", "budget", "compact", "data", "densify", "device", "eval", "model", "name", "optim", "pack", "prune",
    "render", "schedule", "seed", "train",
    "experiment", "experiment_data", "budget_baseline", "stress", "sweep", "hydra", "defaults",
    "runs", "split", "out", "reevaluate", "remeasure", "unfinished", "allow_mixed", "base_config", "base_eval"})
#: every plug-in by name (stdr.registries.Registry; the entry-point group `stdr.plugins`); the
#: built-in ones are registered by importing stdr.plugins.stdr
PLUGINS: Registry[PluginSpec] = Registry(
    "plug-in", "plug-in", "stdr.plugins", "stdr.plugins.register_plugin", builtin=("stdr.plugins.stdr",),
    owner=lambda spec: spec.plugin)


def register_plugin(name: str, plugin: type, config: type, label: Optional[str] = None,
                    row_tags: Optional[Callable[[dict], list[str]]] = None,
                    requires: tuple | Callable[[Any], tuple] = (), baselines: Optional[tuple[str, ...]] = None,
                    in_grids: bool = False, removed_keys: tuple[str, ...] = ()) -> PluginSpec:
    """Add a plug-in: `plugin` a Plugin subclass with `name = name` that implements
    `from_config`; `config` a dataclass whose `enabled` defaults to False (its other fields are
    the plug-in's typed keys, `<name>.<key>`); `label` (default '+<name>') follows the baseline's
    name in table rows and chart legends, and `row_tags(node)` (default: none) gives the tags after
    it for a run's plug-in node (a plain dict).

    Where it applies: `requires` the baseline capabilities it needs
    (stdr.registries.CAPABILITY_NAMES; a tuple, or a function of its config node giving one),
    `baselines` the names it is limited to (None: any with those capabilities). Experiments
    `<data>_<baseline>_<name>` are derived only where it applies, and a run that turns it on where
    it does not is refused before it starts. `in_grids`: whether the default grids include it
    (default: no; a sweep names it with `${stdr_experiments:<data>,<name>}`). `removed_keys`: keys
    of its config node that earlier versions wrote and this one no longer has (a saved config with
    them still loads)."""
    PLUGINS.discover()  # the built-in and installed ones first, so a clash is seen either way
    if not re.fullmatch(r"[a-z][a-z0-9_]*", name or ""):
        raise RegistrationError(f"register_plugin({name!r}): the name must be lower-case letters, digits and '_' "
                         "(it is a config key and an experiment suffix)")
    if name in RESERVED_KEYS:
        raise RegistrationError(f"register_plugin({name!r}): {name!r} is a config section of its own; choose another name")
    if not (isinstance(plugin, type) and issubclass(plugin, Plugin)):
        raise RegistrationError(f"register_plugin({name!r}): plugin must be a Plugin subclass, got {plugin!r}")
    check_plugin_class(f"register_plugin({name!r})", plugin)
    if plugin.from_config.__func__ is Plugin.from_config.__func__:
        raise RegistrationError(f"register_plugin({name!r}): {plugin.__name__} must implement the classmethod from_config")
    if plugin.name != name:
        raise RegistrationError(f"register_plugin({name!r}): {plugin.__name__}.name is {plugin.name!r}; set `name = {name!r}`")
    if not dataclasses.is_dataclass(config) or "enabled" not in {f.name for f in dataclasses.fields(config)} \
            or config().enabled is not False:
        raise RegistrationError(f"register_plugin({name!r}): config must be a dataclass with `enabled: bool = False`, "
                        f"got {config!r}")
    if row_tags is not None and not callable(row_tags):
        raise RegistrationError(f"register_plugin({name!r}): row_tags must be a function of the plug-in's config node, got {row_tags!r}")
    need = requires if callable(requires) else (lambda pcfg, r=tuple(requires): r)
    check_requirements(name, need(config()))
    if baselines is not None and (isinstance(baselines, str) or not all(isinstance(b, str) for b in baselines)):
        raise RegistrationError(f"register_plugin({name!r}): baselines must be a tuple of baseline names or None, got {baselines!r}")
    if not isinstance(in_grids, bool):
        raise RegistrationError(f"register_plugin({name!r}): in_grids must be True or False, got {in_grids!r}")
    return PLUGINS.add(name, PluginSpec(name, plugin, config, label if label is not None else f"+{name}",
                                        **({"row_tags": row_tags} if row_tags is not None else {}), requires=need,
                                        baselines=None if baselines is None else tuple(baselines), in_grids=in_grids,
                                        removed_keys=tuple(removed_keys)))


def check_requirements(name: str, need) -> None:
    """A plug-in's `requires` (evaluated): a tuple of known capability names."""
    if isinstance(need, str) or not isinstance(need, (tuple, list)) or any(c not in CAPABILITY_NAMES for c in need):
        raise RegistrationError(f"register_plugin({name!r}): requires must give a tuple of capabilities from "
                         f"{CAPABILITY_NAMES}, got {need!r}")


def unregister_plugin(name: str) -> None:
    """Remove a plug-in and its Hydra options (for tests that register a temporary one)."""
    PLUGINS.remove(name)


def registered_plugins() -> list[PluginSpec]:
    """Every registered plug-in, in registration order (built-in ones first)."""
    return PLUGINS.registered()


def get_plugin(name: str) -> PluginSpec:
    return PLUGINS.get(name)


def plugin_node(cfg, name: str):
    """cfg.<name> of a config (DictConfig, dataclass or plain dict), or None."""
    return cfg.get(name) if isinstance(cfg, dict) else getattr(cfg, name, None)


def enabled_plugins(cfg) -> list[PluginSpec]:
    """The registered plug-ins a config switches on (`<name>.enabled`), in registration order."""
    out = []
    for spec in registered_plugins():
        node = plugin_node(cfg, spec.name)
        if node is not None and bool(node.get("enabled") if isinstance(node, dict) else node.enabled):
            out.append(spec)
    return out
