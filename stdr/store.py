"""Hydra's side of the config: the ConfigStore kept in step with the registries, the derived
experiments, the resolvers, and `compose_config`.

`register()` stores the run and stdr-eval schemas (stdr.config), one option per registered
baseline (`baseline=<name>`), densification strategy (`densify=<name>`) and plug-in
(`<plug-in>=on|off`), and the experiments derived for every data option; a component registered
later becomes an option at once (the registries call back). The resolvers are `stdr_schedule`
(the derived `schedule` node), `stdr_experiments` (sweep lists) and `stdr_scene_path`.
"""
from __future__ import annotations

import dataclasses
import functools
from dataclasses import field
from pathlib import Path
from typing import Any, List

from hydra.core.config_store import ConfigStore
from omegaconf import OmegaConf

from .baselines import BASELINES
from .baselines.registry import capabilities, discover_baselines, get_baseline
from .config import CONFIG_DIR, _schemas, root_schema
from .densify.prune import prune_steps
from .densify.strategy import STRATEGIES, get_strategy
from .errors import ConfigError
from .io.files import read_yaml
from .plugins import PLUGINS, enabled_plugins, plugin_node, registered_plugins
from .registries import entry_point_name
from .schedule import Schedule, build_schedule

#: the top-level entry of a run's config.yaml that records resumes with changed keys (stdr.train.resume)
CHANGES_KEY = "config_changes"


# ----------------------------------------------------------------- a saved config, read back
# keys of other baselines that configs written before per-baseline config classes carried under
# `baseline` (every run had baseline.scgs, .spgs and .hexplane); dropped when such a config is read
_LEGACY_BASELINE_KEYS = ("scgs", "spgs", "hexplane")


def typed_schema(raw: dict, where: str = "config"):
    """The typed schema a saved config `raw` (a plain dict) is read with: the root schema with its
    baseline's and densification strategy's dataclasses. Drops from `raw`, in place, the keys of
    earlier versions (other baselines' nodes, plug-ins' removed keys). Unknown sections, baselines
    and strategies are a ConfigError naming `where`."""
    b = dict(raw.get("baseline") or {})
    name = b.get("name", "deform")
    try:
        spec = get_baseline(name)
    except ValueError as e:
        raise ConfigError(f"{where}: {e}") from None
    fields = set(spec.config.__dataclass_fields__)
    for k in _LEGACY_BASELINE_KEYS:
        if k in b and k not in fields:
            del b[k]
    raw["baseline"] = b
    root = root_schema()
    for p in registered_plugins():  # keys a plug-in's earlier versions wrote
        if isinstance(raw.get(p.name), dict) and p.removed_keys:
            raw[p.name] = {k: v for k, v in raw[p.name].items() if k not in p.removed_keys}
    unknown = sorted(set(raw) - set(root.__dataclass_fields__))
    for k in [k for k in unknown if isinstance(raw.get(k), dict) and raw[k].get("enabled") is False]:
        del raw[k]  # a plug-in that was off in this run, not installed now: nothing of the run depends on it
        unknown.remove(k)
    if unknown:
        raise ConfigError(f"{where}: unknown config section(s) {unknown}: a plug-in's keys need the plug-in registered "
                          f"(registered: {sorted(PLUGINS)}; stdr.plugins.register_plugin, or an installed package "
                          "with a 'stdr.plugins' entry point)")
    d = dict(raw.get("densify") or {})
    try:
        strategy = get_strategy(d.get("name"))
    except ValueError as e:
        raise ConfigError(f"{where}: {e}") from None
    return OmegaConf.merge(OmegaConf.structured(root), {"baseline": OmegaConf.structured(spec.config),
                                                         "densify": OmegaConf.structured(strategy)})


def load_config(raw: Any, where: str = "config"):
    """A saved config (a run's config.yaml, a checkpoint's config: a dict, DictConfig or path)
    merged onto the typed defaults of its baseline. Unknown keys are an error naming `where`."""
    if isinstance(raw, (str, Path)):
        where = str(raw)
        raw = read_yaml(raw)
        if not isinstance(raw, dict):
            raise ConfigError(f"{where}: holds a {type(raw).__name__}, not a run's config (a mapping of keys)")
    raw = OmegaConf.to_container(raw) if OmegaConf.is_config(raw) else dict(raw)
    raw.pop(CHANGES_KEY, None)  # the record of resumes with changed keys (stdr.train.resume), not a key
    schema = typed_schema(raw, where)
    try:
        return OmegaConf.merge(schema, raw)
    except Exception as e:  # omegaconf's errors name the key; say which file
        raise ConfigError(f"{where}: {e}") from None


def resolve_schedule(cfg) -> Schedule:
    """Every boundary of a run from its config (a Config or DictConfig): each component's stages,
    put together by stdr.schedule.build_schedule."""
    b = cfg.baseline
    total = int(cfg.optim.iterations)
    prune = getattr(cfg, "prune", None)  # configs saved before contribution pruning have no node
    return build_schedule(
        total, int(b.warmup), get_baseline(b.name).module.stages(b),
        get_strategy(getattr(cfg.densify, "name", None)).stages(cfg.densify),
        prune_steps(prune, total, int(cfg.densify.refine_stop)) if prune is not None else None,
        float(prune.share) if prune is not None else 0.0,
        [(spec.name, lambda sched, spec=spec: spec.plugin.stages(plugin_node(cfg, spec.name), cfg, sched))
         for spec in enabled_plugins(cfg)])


# ----------------------------------------------------------------- Hydra
def _schedule_resolver(*, _root_) -> dict:
    return resolve_schedule(_root_).as_dict()


def data_options() -> list[str]:
    """The options of the `data` group (stdr/configs/data/*.yaml)."""
    return sorted(p.stem for p in (CONFIG_DIR / "data").glob("*.yaml"))


def _experiment_files() -> set[str]:
    return {p.stem for p in (CONFIG_DIR / "experiment").glob("*.yaml")}


def plugin_applies(spec, baseline: str, node: Any = None) -> list[str]:
    """Why plug-in `spec` cannot run with the registered baseline `baseline` ([] when it can):
    the capabilities it requires that the baseline's module does not declare, or its own list of
    baselines (PluginSpec.missing). `node`: the plug-in's config node (default: its defaults)."""
    return spec.missing(baseline, capabilities(get_baseline(baseline).module), node)


def derived_experiments(name: str) -> dict[str, dict]:
    """The experiments baseline `name` gets, for every data option: `<data>_<name>` (every
    plug-in off) and `<data>_<name>_<plug-in>` for each registered plug-in that applies to it
    (plugin_applies; that one on), each selecting data, baseline and plug-ins, plus what every
    experiment on that data adds (stdr/configs/experiment_data/<data>.yaml, optional: e.g. init
    from the capture's points). A YAML file stdr/configs/experiment/<same name>.yaml, when
    present, is used instead."""
    files = _experiment_files()
    plugins = [s.name for s in registered_plugins()]
    applying = [s.name for s in registered_plugins() if not plugin_applies(s, name)]
    out = {}
    for d in data_options():
        for on in (None, *applying):
            exp = f"{d}_{name}" + (f"_{on}" if on else "")
            if exp not in files:
                out[exp] = {"defaults": [{"optional /experiment_data": d}, {"override /data": d},
                                         {"override /baseline": name},
                                         *({f"override /{p}": "on" if p == on else "off"} for p in plugins)],
                            "name": exp}
    return out


def run_name(cfg) -> str:
    """The experiment name a run is labelled with: `cfg.name`, unless it is a derived experiment's
    name (`<data>_<baseline>[_<plug-in>]`) whose baseline or plug-ins the command changed
    (`baseline=linear` without `experiment=`, `stdr=on`): then the name of the experiment the run
    really is, `<data>_<its baseline>[_<each plug-in on>]`."""
    name = str(cfg.name)
    data = next((d for d in sorted(data_options(), key=len, reverse=True) if name.startswith(d + "_")), None)
    if data is None or name in _experiment_files():
        return name
    derived = {e for b in BASELINES for e in derived_experiments(b)}
    if name not in derived:
        return name  # a name the user gave
    actual = f"{data}_{cfg.baseline.name}" + "".join(f"_{p.name}" for p in enabled_plugins(cfg))
    return actual


def experiment_names() -> list[str]:
    """Every experiment `stdr-train experiment=<name>` accepts."""
    return sorted(_experiment_files() | {e for b in BASELINES for e in derived_experiments(b)})


def experiment_table() -> list[dict[str, Any]]:
    """Every experiment with what it composes: {name, data, baseline, plugins (those on), source}.
    source: `derived` (made here for each data option x baseline x plug-in: derived_experiments),
    or the YAML file under stdr/configs/experiment/ that defines it (and overrides a derived one
    of the same name); data / baseline / plugins are None for a file (its defaults say)."""
    rows = []
    for b in BASELINES:
        for name, node in derived_experiments(b).items():
            picks = {k.split("/")[-1]: v for d in node["defaults"] for k, v in d.items() if k.startswith("override /")}
            rows.append({"name": name, "data": picks["data"], "baseline": picks["baseline"],
                         "plugins": [p for p, v in picks.items() if v == "on"], "source": "derived"})
    for f in sorted(_experiment_files()):
        rows.append({"name": f, "data": None, "baseline": None, "plugins": None,
                     "source": f"stdr/configs/experiment/{f}.yaml"})
    return sorted(rows, key=lambda r: r["name"])


_STORED: dict[str, set[str]] = {"baseline": set(), "experiment": set(), "plugin": set(), "densify": set()}
_SYNCED: list = [None]  # the registries' contents at the last _sync_store


def _registries() -> tuple:
    """What the stored configs are made from: the registered baselines, plug-ins and densification
    strategies (specs compare by name and class)."""
    return tuple(BASELINES.values()), tuple(registered_plugins()), tuple(STRATEGIES.items())


def _sync_store(*_) -> None:
    """Keep Hydra's ConfigStore in step with the registries of baselines and plug-ins: the
    schemas (base_config with a default `<plug-in>: off` for each plug-in, base_eval), the
    options baseline=<name> (the registered dataclass: typed defaults) and <plug-in>=on|off, and
    the derived experiments. Called on every (un)registration."""
    cs = ConfigStore.instance()
    run, ev = _schemas()
    plugins = [s.name for s in registered_plugins()]
    # the strategy's and the plug-ins' groups are selected by this defaults list (after the
    # schema's own values)
    stored = dataclasses.make_dataclass("BaseConfig", [("defaults", List[Any], field(
        default_factory=lambda: ["_self_", {"densify": "default"}, *({p: "off"} for p in plugins)]))], bases=(run,))
    cs.store(name="base_config", node=stored)
    cs.store(name="base_eval", node=ev)
    for name in _STORED["densify"] - set(STRATEGIES):
        cs.repo.get("densify", {}).pop(f"{name}.yaml", None)
    for name, cls in STRATEGIES.items():
        cs.store(group="densify", name=name, node=cls)
    _STORED["densify"] = set(STRATEGIES)
    for group in _STORED["plugin"] - set(plugins):
        cs.repo.pop(group, None)
    for p in plugins:
        cs.store(group=p, name="on", node={"enabled": True})
        cs.store(group=p, name="off", node={"enabled": False})
    _STORED["plugin"] = set(plugins)
    for b in _STORED["baseline"] - set(BASELINES):
        cs.repo.get("baseline", {}).pop(f"{b}.yaml", None)
    for spec in BASELINES.values():
        cs.store(group="baseline", name=spec.name, node=spec.config)
    _STORED["baseline"] = set(BASELINES)
    exps = {}
    for b in BASELINES:
        exps.update(derived_experiments(b))
    for e in _STORED["experiment"] - set(exps):
        cs.repo.get("experiment", {}).pop(f"{e}.yaml", None)
    for e, node in exps.items():
        cs.store(group="experiment", name=e, node=node, package="_global_")
    _STORED["experiment"] = set(exps)
    _SYNCED[0] = _registries()


def experiments_on(data: str, *which: str) -> str:
    """`${stdr_experiments:dnerf}`: the default grid on data option `data` as a comma-separated
    sweep list: each baseline that joins the grids (BaselineSpec.in_grids: the built-ins), plain
    and with each plug-in that joins them (PluginSpec.in_grids: STDR) and applies to it;
    `${stdr_experiments:dnerf,<plug-in>}` (or `plain`) only those, a named plug-in on every
    baseline it applies to (those of other packages included)."""
    plugins = [s.name for s in registered_plugins()]
    for w in which:
        if w != "plain" and w not in plugins:
            raise ValueError(f"stdr_experiments:{data},{w}: {w!r} is neither 'plain' nor a registered plug-in "
                             f"({plugins})")
    picked = [s for s in registered_plugins() if (s.name in which if which else s.in_grids)]
    out = []
    for b in sorted(BASELINES):
        in_grid = BASELINES[b].in_grids
        if in_grid and (not which or "plain" in which):
            out.append(f"{data}_{b}")
        out += [f"{data}_{b}_{s.name}" for s in picked if not plugin_applies(s, b) and (in_grid or s.name in which)]
    return ",".join(out)


def _scene_path_resolver(root, name) -> str:
    """`${stdr_scene_path:${data.root},${data.name}}` (the sweeps): root/name, or an error that
    names the missing key (a null root must not become a path 'None/<scene>')."""
    if root is None or root == "":
        raise ValueError("data.root is not set: a sweep over scenes needs the dataset folder, e.g. "
                         "data.root=/data/dnerf")
    if name is None or name == "":
        raise ValueError("data.name is not set: the scene folder under data.root")
    return f"{root}/{name}"


def register() -> None:
    """Register the structured configs, every baseline and plug-in (and the ones registered later) and the
    `stdr_schedule` / `stdr_experiments` resolvers with Hydra. Idempotent; the entry points call it."""
    if not OmegaConf.has_resolver("stdr_schedule"):
        OmegaConf.register_new_resolver("stdr_schedule", _schedule_resolver)
    if not OmegaConf.has_resolver("stdr_experiments"):
        OmegaConf.register_new_resolver("stdr_experiments", experiments_on)
    if not OmegaConf.has_resolver("stdr_scene_path"):
        OmegaConf.register_new_resolver("stdr_scene_path", _scene_path_resolver)
    discover_baselines()  # baselines of other installed distributions (entry points)
    registered_plugins()  # built-in plug-ins and those of other distributions
    STRATEGIES.discover()  # strategies of other distributions
    if _SYNCED[0] != _registries():  # (re-storing every node costs ~0.3 s; compose_config calls this each time)
        _sync_store()
    for registry in (BASELINES, PLUGINS, STRATEGIES):
        registry.add_listener(_sync_store)




# ----------------------------------------------------------------- config files of other distributions
#: the entry-point group through which another distribution ships config files: a package whose
#: folder holds config groups (budget_baseline/, budget/, sweep/, experiment_data/, ...)
CONFIG_GROUP = "stdr.configs"


@functools.lru_cache(maxsize=None)
def config_packages() -> tuple[tuple[str, str], ...]:
    """(entry-point name, package) of every installed `stdr.configs` entry point, e.g.

        [project.entry-points."stdr.configs"]
        mine = "my_package.configs"     # my_package/configs/budget_baseline/mine_demo.yaml, ...

    Hydra searches them after stdr's own folder (hydra_plugins/stdr_configs). A package that does
    not import, or a file at the path of one stdr ships or another package ships (the first would
    win unseen), is a ConfigError naming the entry point, its distribution and the file."""
    import importlib
    from importlib.metadata import entry_points
    seen = {str(p.relative_to(CONFIG_DIR)): "stdr" for p in CONFIG_DIR.rglob("*.yaml")}
    found = []
    for ep in entry_points(group=CONFIG_GROUP):
        where = entry_point_name(ep, CONFIG_GROUP)
        try:
            folder = Path(importlib.import_module(ep.module).__file__).parent
        except (ImportError, TypeError) as e:
            raise ConfigError(f"{where}: cannot import the package {ep.module!r} ({e}); it must name a package "
                              "(a folder with __init__.py) holding config groups") from None
        for f in sorted(folder.rglob("*.yaml")):
            rel = str(f.relative_to(folder))
            if rel in seen:
                raise ConfigError(f"{where}: {f} has the path {rel} of a config file {seen[rel]} ships, which "
                                  "would be used instead; rename it (e.g. after your baseline)")
            seen[rel] = where
        found.append((ep.name, ep.module))
    return tuple(found)


def compose_config(overrides=(), config_name: str = "train", return_hydra_config: bool = False):
    """The config `stdr-train` (config_name="train") or `stdr-eval` ("eval") would run with these
    command-line overrides, composed with Hydra's compose API: for scripts, notebooks and tests
    (return_hydra_config: with the `hydra` node, e.g. a launcher's or a sweep's settings)."""
    from hydra import compose, initialize_config_dir

    register()
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base=None):
        return compose(config_name, overrides=list(overrides), return_hydra_config=return_hydra_config)
