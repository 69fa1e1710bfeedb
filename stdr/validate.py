"""A run's config checked before anything trains: every key known, every value in range, every
path of the right kind. Each failure is a ConfigError whose one line names the key, the value and
what is allowed (stdr-train prints it and exits with code 2).

`check_run_config(cfg, base)` is what stdr-train calls on the config Hydra composed. Keys are checked
against the typed schema that every tool reads a saved run with (`stdr.store.load_config`), so a
run folder that stdr-train writes can be read by stdr-eval, stdr-export, stdr-view and a resume. A
key a baseline, plug-in or densification strategy declares in its config dataclass is part of that
schema.
"""
from __future__ import annotations

import difflib
import math
from pathlib import Path
from typing import Any, Callable, Iterator, Optional

from omegaconf import DictConfig, OmegaConf

from .errors import ConfigError
from .config import root_schema
from .baselines.registry import get_baseline
from .plugins import enabled_plugins, plugin_node
from .store import plugin_applies, typed_schema, load_config, resolve_schedule
from .data.stress import check_stress
from .densify.prune import check_prune_config
from .data.load import resolve_data_path


# ------------------------------------------------------------------ keys
def schema_keys(node: Any, prefix: str = "") -> Iterator[str]:
    """Every dotted key of a typed config node (inside free-form dict fields: none)."""
    if not isinstance(node, DictConfig) or not _typed(node):
        return
    for k in node.keys():
        key = f"{prefix}{k}"
        yield key
        child = node._get_node(k)
        if isinstance(child, DictConfig):
            yield from schema_keys(child, key + ".")


def _typed(node: DictConfig) -> bool:
    """A node made from a dataclass (its keys are fixed), not a Dict[str, ...] field."""
    t = OmegaConf.get_type(node)
    return t is not None and t is not dict and hasattr(t, "__dataclass_fields__")


def unknown_keys(raw: dict, schema: DictConfig, prefix: str = "") -> list[str]:
    """The dotted keys of the plain dict `raw` that the typed `schema` lacks."""
    out = []
    if not _typed(schema):
        return out
    for k, v in raw.items():
        key = f"{prefix}{k}"
        if k not in schema:
            out.append(key)
        elif isinstance(v, dict) and isinstance(schema._get_node(k), DictConfig):
            out += unknown_keys(v, schema._get_node(k), key + ".")
    return out


def nearest_key(key: str, known: list[str]) -> Optional[str]:
    """The known key `key` was most likely meant to be (a typo), or None."""
    parent, _, leaf = key.rpartition(".")
    siblings = [k for k in known if k.rpartition(".")[0] == parent]
    hit = difflib.get_close_matches(leaf, [k.rpartition(".")[2] for k in siblings], n=1, cutoff=0.7)
    if hit:
        return f"{parent}.{hit[0]}" if parent else hit[0]
    leaves = {}
    for k in known:  # the same name in another section (optim.prune_opa -> densify.prune_opa)
        leaves.setdefault(k.rpartition(".")[2], k)
    hit = difflib.get_close_matches(leaf, list(leaves), n=1, cutoff=0.85)
    return leaves[hit[0]] if hit else None


def unknown_key_hint(key: str, known: list[str]) -> str:
    """What to say of the unknown dotted `key` among the `known` ones: the nearest valid key, else
    what its section holds (the sections themselves for a top-level name)."""
    near = nearest_key(key, known)
    if near:
        return f"did you mean {near}?"
    parent = key.rpartition(".")[0]
    siblings = [k.rpartition(".")[2] for k in known if k.rpartition(".")[0] == parent]
    if not parent or not siblings:
        sections = [k for k in known if "." not in k]
        return f"the sections are {', '.join(sections)}; a plug-in's keys need the plug-in installed and registered"
    listed = ", ".join(siblings[:12]) + (", ..." if len(siblings) > 12 else "")
    return f"{parent} has {listed}; a baseline's or plug-in's keys need it selected (e.g. baseline=scgs, stdr=on)"


def check_keys(cfg) -> None:
    """Refuse a key the run's schema does not have (a `+key` typo), naming the nearest valid one."""
    import copy

    raw = OmegaConf.to_container(cfg, resolve=False) if OmegaConf.is_config(cfg) else dict(cfg)
    sections = list(root_schema().__dataclass_fields__)
    top = [k for k in raw if k not in sections]
    if top:
        raise ConfigError(f"unknown config section {top[0]}: {unknown_key_hint(top[0], sections)}")
    schema = typed_schema(copy.deepcopy(raw), "config")  # (it drops saved configs' legacy keys; a new run has none)
    bad = unknown_keys(raw, schema)
    if bad:
        more = f" (and {len(bad) - 1} more: {', '.join(bad[1:4])})" if len(bad) > 1 else ""
        raise ConfigError(f"unknown config key {bad[0]}{more}: {unknown_key_hint(bad[0], list(schema_keys(schema)))}")


# ------------------------------------------------------------------ values
def _num(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


#: what a kind of value allows: (test, the words that say so)
KINDS: dict[str, tuple[Callable[[Any], bool], str]] = {
    "count": (lambda v: _int(v) and v >= 1, "a whole number >= 1"),
    "steps": (lambda v: _int(v) and v >= 0, "a whole number >= 0 (0: never / off)"),
    "positive": (lambda v: _num(v) and math.isfinite(v) and v > 0, "a finite number > 0"),
    "nonneg": (lambda v: _num(v) and math.isfinite(v) and v >= 0, "a finite number >= 0"),
    "unit": (lambda v: _num(v) and 0 <= v <= 1, "a number in [0, 1]"),
    "open_unit": (lambda v: _num(v) and 0 < v < 1, "a number in (0, 1)"),
    "below_one": (lambda v: _num(v) and 0 <= v < 1, "a number in [0, 1)"),
    "opt_count": (lambda v: v is None or (_int(v) and v >= 1), "null (no limit) or a whole number >= 1"),
    "opt_positive": (lambda v: v is None or (_num(v) and math.isfinite(v) and v > 0), "null (off) or a finite number > 0"),
    "sh_degree": (lambda v: _int(v) and 0 <= v <= 3, "0, 1, 2 or 3"),
    "opt_sh_degree": (lambda v: v is None or (_int(v) and 0 <= v <= 3), "null (all bands) or 0, 1, 2 or 3"),
    "resume": (lambda v: isinstance(v, bool) or v == "override",
               "true (resume from the checkpoint), false (start over) or override (resume with changed keys)"),
}

#: key -> kind, for the keys every run has (a key absent from a run's config is skipped)
RULES: dict[str, str] = {
    "seed": "steps",
    "data.resolution_scale": "positive", "data.max_width": "opt_count", "data.image_scale": "opt_count",
    "model.init_num": "count", "model.init_extent": "positive", "model.init_opacity": "open_unit",
    "model.sh_degree": "sh_degree", "model.sh_interval": "count",
    "optim.iterations": "count", "optim.lambda_dssim": "unit", "optim.spatial_lr_scale": "positive",
    "optim.means_lr_init": "nonneg", "optim.means_lr_final": "nonneg", "optim.means_lr_max_steps": "count",
    "optim.scales_lr": "nonneg", "optim.quats_lr": "nonneg", "optim.opacities_lr": "nonneg",
    "optim.sh0_lr": "nonneg", "optim.shN_lr": "nonneg",
    "baseline.warmup": "steps",
    "baseline.lr_init": "nonneg", "baseline.lr_final": "nonneg", "baseline.lr_max_steps": "count",
    "densify.grow_grad2d": "nonneg", "densify.grow_scale3d": "positive", "densify.prune_opa": "below_one",
    "densify.prune_scale3d": "positive", "densify.prune_scale2d": "opt_positive", "densify.prune_big_after": "steps",
    "densify.refine_start": "steps", "densify.refine_stop": "steps", "densify.refine_every": "count",
    "densify.reset_every": "steps", "densify.reset_value": "open_unit", "densify.max_gaussians": "steps",
    "densify.target_gaussians": "steps",
    "render.tile_size": "steps", "render.eps2d": "nonneg", "render.near": "positive",
    "train.eval_every": "steps", "train.eval_frames": "steps", "train.checkpoint_every": "steps",
    "train.log_every": "count", "train.image_every": "steps", "train.stop_at": "opt_count", "train.threads": "steps",
    "train.deadline": "opt_positive", "train.start_by": "opt_positive", "train.resume": "resume",
    "eval.fps_warmup": "steps", "eval.fps_repeats": "count",
    "pack.finetune": "steps", "pack.sh_degree": "opt_sh_degree",
}

#: key -> the values it takes
CHOICES: dict[str, tuple] = {
    "data.format": ("procedural", "dnerf", "nerfies"),
    "data.eval_split": ("test", "val", "train"),
    "render.backend": ("auto", "cuda", "cpu", "reference"),
    "render.cull": ("off", "eval", "train"),
    "eval.lpips": ("auto", "true", "false"),
    "eval.lpips_net": ("vgg", "alex"),
}


def _get(cfg, key: str):
    """The value at dotted `key`, interpolations resolved (_MISSING: the key is absent, or its
    interpolation cannot be resolved here: the run resolves it and says so itself)."""
    node = cfg
    for part in key.split(".")[:-1]:
        if not isinstance(node, DictConfig) or part not in node:
            return _MISSING
        node = node._get_node(part)
    leaf = key.split(".")[-1]
    if not isinstance(node, DictConfig) or leaf not in node:
        return _MISSING
    try:
        return node[leaf]
    except Exception:  # noqa: BLE001 - an interpolation only the run can resolve
        return _MISSING


_MISSING = object()


def _nonfinite(node, prefix: str = "") -> Iterator[str]:
    """Dotted keys holding NaN or an infinity (a float key given 'nan' or 'inf')."""
    for k in node.keys():
        key = f"{prefix}{k}"
        child = node._get_node(k)
        if isinstance(child, DictConfig):
            yield from _nonfinite(child, key + ".")
        else:
            v = child._value()
            if isinstance(v, float) and not math.isfinite(v):
                yield key


def check_values(cfg) -> None:
    """Every value of RULES and CHOICES in range; no NaN or infinity anywhere; the sections' own
    checks (prune.*, train.guard.*, data.stress.*) as ConfigErrors."""
    if "schedule" in cfg:
        top = OmegaConf.masked_copy(cfg, [k for k in cfg.keys() if k != "schedule"])
    else:
        top = cfg
    for key in _nonfinite(top):
        raise ConfigError(f"{key}={_get(cfg, key)}: must be a finite number")
    for key, kind in RULES.items():
        v = _get(cfg, key)
        if v is _MISSING:
            continue
        test, allowed = KINDS[kind]
        if not test(v):
            raise ConfigError(f"{key}={v!r}: use {allowed}")
    for key, allowed in CHOICES.items():
        v = _get(cfg, key)
        if v is not _MISSING and str(v).lower() not in allowed:
            raise ConfigError(f"{key}={v!r}: use one of {', '.join(allowed)}")
    for fn, node in ((check_prune_config, "prune"), (check_guard_config, "train.guard"), (check_stress, "data.stress")):
        sub = _get(cfg, node)
        if sub is not _MISSING:
            _as_config_error(fn, sub)


def check_guard_config(g) -> None:
    """train.guard's values that cannot work (stdr.config.GuardConfig), as errors naming the key."""
    if g.snapshot_every < 1:
        raise ValueError(f"train.guard.snapshot_every={g.snapshot_every}: must be at least 1")
    if not 0.0 < g.lr_factor <= 1.0:
        raise ValueError(f"train.guard.lr_factor={g.lr_factor}: must be in (0, 1] (each recovery multiplies "
                         "every learning rate by it)")
    if g.max_recoveries < 0:
        raise ValueError(f"train.guard.max_recoveries={g.max_recoveries}: must be 0 or more")
    if g.divergence_db < 0:
        raise ValueError(f"train.guard.divergence_db={g.divergence_db}: must be 0 (off) or positive")
    if g.after_reset < 0:
        raise ValueError(f"train.guard.after_reset={g.after_reset}: must be 0 or more (steps after an opacity reset)")
    if g.monitor_frames < 0:
        raise ValueError(f"train.guard.monitor_frames={g.monitor_frames}: must be 0 (all frames) or positive")


def _as_config_error(fn, *args) -> None:
    """fn(*args), its ValueError (a section's own check names the key) raised as a ConfigError."""
    try:
        fn(*args)
    except ConfigError:
        raise
    except ValueError as e:
        raise ConfigError(str(e)) from None


# ------------------------------------------------------------------ paths
def check_data_path(data, base: str | Path | None = None) -> None:
    """data.path: a folder for a scene format, refused where the dataset does not read it."""
    fmt, path = data.format, data.path
    if fmt == "procedural":
        if path:
            raise ConfigError(f"data.path={path}: the procedural scene (data={data.name or 'embedded'}) does not read "
                              "it; to train on a scene folder choose its dataset too, e.g. experiment=dnerf_deform "
                              f"data.path={path}")
        return
    if not path:
        what = ("a D-NeRF scene folder (the one holding transforms_train.json)" if fmt == "dnerf"
                else "a Nerfies-format scene folder (the one holding dataset.json)")
        raise ConfigError(f"data.path is not set: point it at {what}")
    p = resolve_data_path(str(path), base)
    if not p.exists():
        raise ConfigError(f"data.path={path}: no such folder ({p})")
    if not p.is_dir():
        inside = "transforms_train.json" if fmt == "dnerf" else "dataset.json"
        raise ConfigError(f"data.path={path}: is a file, not a folder; point it at the scene folder (the one "
                          f"holding {inside})")


def check_plugins_apply(cfg) -> None:
    """Every plug-in the config turns on applies to its baseline (stdr.store.plugin_applies: the
    capabilities the plug-in requires, as its config node sets them, against those the baseline
    declares)."""
    name = str(cfg.baseline.name)
    module = get_baseline(name).module
    for spec in enabled_plugins(cfg):
        why = plugin_applies(spec, name, plugin_node(cfg, spec.name))
        if why:
            fix = (f"add 'conditioning' to {module.__name__}.capabilities once its forward takes `cond`"
                   if any("'conditioning'" in w for w in why) else "train it with another baseline")
            raise ConfigError(f"{spec.name}=on with baseline={name} ({module.__name__}): {'; '.join(why)}; "
                              f"set {spec.name}=off, or {fix} (docs/baselines.md, \"Capabilities\")")


def check_run_config(cfg, base: str | Path | None = None) -> None:
    """Everything above, in the order a user would fix it: keys, values, the data path; then the
    config must read back as every tool reads a saved run (stdr.store.load_config)."""
    check_keys(cfg)
    check_values(cfg)
    check_plugins_apply(cfg)
    check_data_path(cfg.data, base)
    _as_config_error(resolve_schedule, cfg)  # a phase that never trains (NeverTrains) is named here
    _as_config_error(load_config, cfg)
