"""The plug-in registry (stdr.plugins): checks at registration, what registering gives a plug-in
(config group, typed keys, experiments, sweep list, schedule, row label, evaluation-time keys),
and a core that names no plug-in. Training a registered plug-in end to end: tests/test_model.py
(in-process) and tests/test_entry_points.py (from another distribution)."""
import re
from dataclasses import dataclass
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from stdr.eval.table import method_suffix
from stdr.plugins import PLUGINS, Plugin, enabled_plugins, register_plugin, unregister_plugin
from stdr.schedule import Event
from stdr.store import resolve_schedule
from stdr.testing import make_cfg

ROOT = Path(__file__).resolve().parents[1]


@dataclass
class PulseConfig:
    enabled: bool = False
    start: int = 100
    strength: float = 1.0


class Pulse(Plugin):
    name = "pulse"

    @classmethod
    def from_config(cls, pcfg, cfg, schedule, train_times, device):
        return cls()

    @classmethod
    def stages(cls, pcfg, cfg, schedule):
        schedule.events.append(Event(int(pcfg.start), "pulse.start", "pulse on"))
        if int(pcfg.start) >= schedule.iterations:
            schedule.never_trains(f"pulse.start={pcfg.start} is at or after the run's end")
        return {"start": int(pcfg.start)}


def pulse_tags(pcfg):
    return ["strong"] if pcfg["strength"] > 1 else []


@pytest.fixture
def pulse():
    spec = register_plugin("pulse", Pulse, PulseConfig, label="+P", row_tags=pulse_tags)
    yield spec
    unregister_plugin("pulse")


def test_registration_is_checked():
    class NoFactory(Plugin):
        name = "nofactory"

    class Named(Pulse):
        name = "other"

    @dataclass
    class NoSwitch:
        strength: float = 1.0

    @dataclass
    class OnByDefault:
        enabled: bool = True

    with pytest.raises(ValueError, match="lower-case letters"):
        register_plugin("Pulse", Pulse, PulseConfig)
    with pytest.raises(ValueError, match="'render' is a config section of its own"):
        register_plugin("render", Pulse, PulseConfig)
    with pytest.raises(TypeError, match="must be a Plugin subclass"):
        register_plugin("pulse", object, PulseConfig)
    with pytest.raises(TypeError, match="must implement the classmethod from_config"):
        register_plugin("nofactory", NoFactory, PulseConfig)
    with pytest.raises(ValueError, match=r"Named.name is 'other'; set `name = 'pulse'`"):
        register_plugin("pulse", Named, PulseConfig)
    for bad in (NoSwitch, OnByDefault):
        with pytest.raises(TypeError, match="`enabled: bool = False`"):
            register_plugin("pulse", Pulse, bad)
    with pytest.raises(ValueError, match="'stdr' is already registered"):
        register_plugin("stdr", type("Stdr2", (Pulse,), {"name": "stdr"}), PulseConfig)
    # where it applies: known capabilities, baseline names, a boolean for the grids
    with pytest.raises(ValueError, match=r"requires must give a tuple of capabilities from \('conditioning'"):
        register_plugin("pulse", Pulse, PulseConfig, requires=("wings",))
    with pytest.raises(ValueError, match="requires must give a tuple"):
        register_plugin("pulse", Pulse, PulseConfig, requires=lambda node: "conditioning")
    with pytest.raises(TypeError, match="baselines must be a tuple of baseline names"):
        register_plugin("pulse", Pulse, PulseConfig, baselines="deform")
    with pytest.raises(TypeError, match="in_grids must be True or False"):
        register_plugin("pulse", Pulse, PulseConfig, in_grids="yes")
    assert "pulse" not in PLUGINS and "nofactory" not in PLUGINS


def test_a_plugin_joins_the_grids_and_baselines_only_where_it_says():
    from stdr.store import experiment_names, experiments_on
    from stdr.validate import check_run_config
    grid = experiments_on("dnerf")
    # by default a new plug-in stays out of the default grid, which stays plain + STDR on every baseline
    register_plugin("pulse", Pulse, PulseConfig)
    try:
        assert experiments_on("dnerf") == grid
        assert grid.split(",") == [f"dnerf_{b}{s}" for b in ("4dgs", "deform", "scgs", "spgs") for s in ("", "_stdr")]
        assert "dnerf_scgs_pulse" in experiment_names() and "dnerf_scgs_pulse" in experiments_on("dnerf", "pulse")
    finally:
        unregister_plugin("pulse")
    # limited to one baseline, in the grids: derived, listed and allowed there only
    register_plugin("pulse", Pulse, PulseConfig, baselines=("deform",), in_grids=True)
    try:
        assert [e for e in experiment_names() if e.startswith("dnerf_") and e.endswith("_pulse")] == ["dnerf_deform_pulse"]
        assert experiments_on("dnerf", "pulse") == "dnerf_deform_pulse"
        assert "dnerf_deform_pulse" in experiments_on("dnerf").split(",")
        with pytest.raises(Exception, match=r"pulse=on with baseline=scgs \(ControlNodeDeformation\): pulse applies to "
                                            r"the baselines deform only; set pulse=off, or train it with another baseline"):
            check_run_config(make_cfg(["experiment=dnerf_scgs", "pulse=on", "data.path=/x"]))
    finally:
        unregister_plugin("pulse")
    # a requirement every built-in baseline lacks (none changes opacity): no experiment, and refused
    register_plugin("pulse", Pulse, PulseConfig, requires=("opacity_deltas",), in_grids=True)
    try:
        assert not any(e.endswith("_pulse") for e in experiment_names())
        assert experiments_on("dnerf") == grid and experiments_on("dnerf", "pulse") == ""
        with pytest.raises(Exception, match="pulse needs a baseline with the capability 'opacity_deltas'"):
            check_run_config(make_cfg(["experiment=dnerf_deform", "pulse=on", "data.path=/x"]))
    finally:
        unregister_plugin("pulse")


def test_registering_gives_group_keys_experiments_sweep_schedule_and_label(pulse):
    from stdr.store import experiment_names
    cfg = make_cfg(["experiment=dnerf_deform_pulse", "data.path=/x", "pulse.strength=2.5"])
    assert cfg.pulse.enabled and cfg.pulse.strength == 2.5 and not cfg.stdr.enabled
    assert [s.name for s in enabled_plugins(cfg)] == ["pulse"]
    with pytest.raises(Exception, match="strength"):  # typed: a float key refuses text
        make_cfg(["pulse.strength=strong"])
    assert not make_cfg([]).pulse.enabled and make_cfg(["pulse=on"]).pulse.enabled
    # every baseline gets the experiment, on every data option; plain experiments switch it off
    assert {"dnerf_scgs_pulse", "embedded_4dgs_pulse", "nerfies_spgs_pulse"} <= set(experiment_names())
    assert not make_cfg(["experiment=dnerf_deform", "data.path=/x"]).pulse.enabled
    assert make_cfg(["experiment=dnerf_deform", "data.path=/x", "pulse=on"]).pulse.enabled  # the command line wins
    # both plug-ins at once
    both = make_cfg(["experiment=dnerf_deform_stdr", "data.path=/x", "pulse=on"])
    assert [s.name for s in enabled_plugins(both)] == ["stdr", "pulse"]
    # its phase joins the one schedule, and its values the derived node
    s = resolve_schedule(cfg)
    assert s.plugins == {"pulse": {"start": 100}} and "100  pulse on  [pulse.start]" in s.describe()
    node = OmegaConf.to_container(cfg, resolve=True)["schedule"]
    assert node["pulse_start"] == 100 and "stdr_freeze_at" not in node
    from stdr.schedule import NeverTrains
    with pytest.raises(NeverTrains, match="pulse.start=5000"):
        resolve_schedule(make_cfg(["pulse=on", "pulse.start=5000", "optim.iterations=2000"]))
    # the sweep list of the grids
    from stdr.store import experiments_on
    assert experiments_on("dnerf", "pulse").split(",") == [f"dnerf_{b}_pulse" for b in
                                                                   ("4dgs", "deform", "scgs", "spgs")]
    with pytest.raises(ValueError, match="'glow' is neither 'plain' nor a registered plug-in"):
        experiments_on("dnerf", "glow")
    # the row label: baseline, each enabled plug-in's label, its tags
    flat = OmegaConf.to_container(both, resolve=True)
    assert method_suffix(flat) == "+STDR+P"
    flat["pulse"]["strength"] = 3.0
    flat["stdr"]["spatial_reg"] = False
    assert method_suffix(flat) == "+STDR w/o spatial_reg+P strong"


def test_unregistering_removes_the_group_and_experiments(pulse):
    from stdr.store import experiment_names
    assert "dnerf_deform_pulse" in experiment_names()
    unregister_plugin("pulse")
    assert "dnerf_deform_pulse" not in experiment_names()
    with pytest.raises(Exception, match="pulse"):
        make_cfg(["pulse=on"])
    register_plugin("pulse", Pulse, PulseConfig, label="+P", row_tags=pulse_tags)  # for the fixture's teardown


def test_stdr_eval_takes_plugin_keys_but_not_the_switch():
    from stdr.store import compose_config
    e = compose_config(["runs=[a]", "stdr.mask_after_freeze=false"], config_name="eval")
    assert e.stdr.mask_after_freeze is False and e.stdr.lambda_temp is None  # null: the run's own
    with pytest.raises(Exception, match="enabled"):
        compose_config(["runs=[a]", "stdr.enabled=true"], config_name="eval")
    from stdr.cli.eval import apply_overrides
    run = make_cfg(["experiment=embedded_deform_stdr"])
    apply_overrides(run, "stdr", e.stdr)
    assert run.stdr.mask_after_freeze is False and run.stdr.lambda_temp == make_cfg([]).stdr.lambda_temp


def test_a_saved_config_with_an_unregistered_plugin_is_refused_by_name(tmp_path):
    from stdr.store import load_config
    raw = OmegaConf.to_container(make_cfg([]), resolve=True)
    raw["sparkle"] = {"enabled": True}
    with pytest.raises(ValueError, match=r"run.yaml: unknown config section\(s\) \['sparkle'\]: a plug-in's keys "
                                         r"need the plug-in registered"):
        load_config(raw, "run.yaml")


# the core modules: outside stdr/plugins/stdr/ and the registries, no module names the plug-in
CORE = ["stdr/config.py", "stdr/model.py", "stdr/schedule.py", "stdr/cli/eval.py", "stdr/eval", "stdr/train"]
# what "stdr" may be there: the package (its module paths but the plug-in's, CLIs, log prefix, resolvers, cache folder,
# environment variables, file formats, prose naming the package)
_MODULES = "|".join(sorted(p.stem for p in (ROOT / "stdr").iterdir()
                           if (p.suffix == ".py" or (p / "__init__.py").is_file()) and p.stem != "decouple"))
ALLOWED = re.compile(rf"(?<![\w.])stdr\.({_MODULES})\b|stdr-[a-z0-9-]+|\[stdr\]|stdr_(schedule|experiments|scene_path|share)"
                     r"|\bstdr/[\w/.]+|/stdr\b|STDR_[A-Z_]+|\bstdr (run|checkpoint|package)\b|stdr/configs|\$\{stdr_|docs/stdr\.md|\.stdrc\b")


def test_the_core_names_no_plugin():
    files = [p for c in CORE for p in ((ROOT / c).rglob("*.py") if (ROOT / c).is_dir() else [ROOT / c])]
    assert len(files) >= 10
    found = []
    for f in files:
        for i, line in enumerate(f.read_text().splitlines(), 1):
            rest = ALLOWED.sub("", line)
            if re.search(r"stdr", rest, re.IGNORECASE):
                found.append(f"{f.relative_to(ROOT)}:{i}: {line.strip()}")
    assert found == []


def test_a_plugins_frozen_keys_lose_their_optimizer_whatever_their_dtype(tmp_path, monkeypatch):
    """Frozen parameters are an interface (Plugin.frozen_keys), not a dtype: a float key a plug-in
    declares frozen gets no optimizer from that step on and keeps its values."""
    import torch
    from stdr.plugins.stdr.plugin import STDR as STDRPlugin
    from stdr.testing import tiny_config
    from stdr.train.trainer import Trainer

    monkeypatch.setattr(STDRPlugin, "frozen_keys", lambda self, params: {"sh0"} if self._frozen_now else set())
    STDRPlugin._frozen_now = False
    t = Trainer(tiny_config(tmp_path, ["experiment=embedded_deform_stdr", "optim.iterations=20", "baseline.warmup=5",
                                       "stdr.warmup_end=5", "stdr.freeze_at=10", "train.stop_at=12"]), tmp_path / "r")
    assert "sh0" in t.state.optimizers
    t.train()
    STDRPlugin._frozen_now = True
    before = t.state.model.params["sh0"].detach().clone()
    t.cfg.train.stop_at = 16
    t.train()
    assert "sh0" not in t.state.optimizers and "means" in t.state.optimizers
    assert torch.equal(t.state.model.params["sh0"], before) and t.step == 16


def test_the_reserved_names_cover_the_run_and_eval_schemas():
    """No plug-in may take a name the run config or stdr-eval already uses: RESERVED_KEYS, a constant
    of the registry (no module sets it at import), holds every section of both schemas."""
    from stdr.config import Config, EvalAppConfig
    from stdr.plugins import RESERVED_KEYS
    assert set(Config.__dataclass_fields__) | set(EvalAppConfig.__dataclass_fields__) <= RESERVED_KEYS



def test_a_run_with_a_disabled_plugin_that_is_not_installed_now_still_reads(tmp_path):
    """A section of a plug-in that was off in the run (enabled: false) is dropped when the plug-in
    is not registered; an enabled one is still an error naming it (the run depends on it)."""
    import yaml

    from stdr.errors import ConfigError
    from stdr.store import load_config
    from stdr.testing import make_cfg
    from omegaconf import OmegaConf
    raw = OmegaConf.to_container(make_cfg([]), resolve=True)
    for enabled in (False, True):
        raw["vel"] = {"enabled": enabled, "weight": 1.0}
        (tmp_path / "config.yaml").write_text(yaml.safe_dump(raw))
        if enabled:
            with pytest.raises(ConfigError, match=r"unknown config section\(s\) \['vel'\]"):
                load_config(tmp_path / "config.yaml")
        else:
            assert "vel" not in load_config(tmp_path / "config.yaml")
