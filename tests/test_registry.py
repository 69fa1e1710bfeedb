"""The baseline registry: one module and one config make a baseline that every entry point,
experiment and test sees. Densification strategies are registered the same way
(stdr.densify.strategy): a second one, written here, becomes `densify=<name>` with typed keys,
joins the schedule and trains through the one loop; the default is unchanged."""
from __future__ import annotations

from dataclasses import dataclass, field

import re

import pytest
import torch
from omegaconf import OmegaConf
from torch import nn

from stdr.store import load_config, resolve_schedule
from stdr.store import data_options, experiment_names
from stdr.baselines import BASELINES, BaselineConfig, Deformation, Deltas, get_baseline, register_baseline
from stdr.baselines.registry import unregister_baseline
from stdr.densify.strategy import STRATEGIES, DensifyStrategy, get_strategy, register_strategy, unregister_strategy
from stdr.testing import applicable, make_cfg, tiny_config


@pytest.mark.parametrize("name", sorted(BASELINES))
def test_every_registered_baseline_is_an_option_with_derived_experiments(name):
    spec = get_baseline(name)
    cfg = make_cfg([f"baseline={name}"])
    assert cfg.baseline.name == name and OmegaConf.get_type(cfg.baseline) is spec.config
    names = set(experiment_names())
    assert {f"{d}_{name}{s}" for d in data_options() for s in ("", "_stdr")} <= names
    for exp, on in ((f"dnerf_{name}", False), (f"dnerf_{name}_stdr", True)):
        c = make_cfg([f"experiment={exp}", "data.path=/x"])
        assert (c.name, c.data.format, c.baseline.name, c.stdr.enabled) == (exp, "dnerf", name, on)
    # what every experiment on a dataset adds comes with it (stdr/configs/experiment_data)
    assert make_cfg([f"experiment=embedded_{name}"]).budget == "demo"
    assert make_cfg([f"experiment=nerfds_{name}", "data.path=/x"]).model.init == "points"
    assert make_cfg([f"experiment=dnerf_{name}", "data.path=/x"]).model.init == "random"


def test_another_baselines_key_is_rejected_not_ignored():
    with pytest.raises(Exception, match="scgs"):
        make_cfg(["experiment=dnerf_deform", "data.path=/x", "baseline.scgs.num_nodes=64"])
    assert applicable(["baseline.scgs.num_nodes=64", "baseline.depth=2"], "deform") == ["baseline.depth=2"]
    assert applicable(["baseline.scgs.num_nodes=64"], "scgs") == ["baseline.scgs.num_nodes=64"]


# ------------------------------------------------------------------ a baseline added in a test
@dataclass
class DriftOptions:
    speed: float = 0.0


@dataclass
class DriftConfig(BaselineConfig):
    """A toy baseline: every Gaussian drifts along x with a learned speed times t."""

    name: str = "drift"
    drift: DriftOptions = field(default_factory=DriftOptions)


class Drift(Deformation):
    capabilities = frozenset({"conditioning"})  # its cond_head reads STDR's conditioning

    def __init__(self, speed: float = 0.0, cond_dim: int = 0):
        super().__init__()
        self.cond_dim = cond_dim
        self.speed = nn.Parameter(torch.tensor([speed, 0.0, 0.0]))
        self.cond_head = nn.Linear(cond_dim, 3) if cond_dim else None
        if self.cond_head is not None:
            nn.init.zeros_(self.cond_head.weight)
            nn.init.zeros_(self.cond_head.bias)

    @classmethod
    def config_kwargs(cls, b, cond_dim=0, train_times=None, seed=0, schedule=None):
        return {"speed": b.drift.speed, "cond_dim": cond_dim}

    def forward(self, params, t, cond=None):
        dx = (self.speed * t).expand_as(params["means"])
        if self.cond_head is not None:
            dx = dx + self.cond_head(cond)
        return Deltas(means=dx)


@pytest.fixture
def drift():
    spec = register_baseline("drift", Drift, DriftConfig)
    yield spec
    unregister_baseline("drift")
    assert "drift" not in BASELINES and not any("drift" in e for e in experiment_names())


def test_composing_sees_a_registry_change_that_bypassed_the_listeners(monkeypatch):
    """compose_config re-stores Hydra's nodes only when the registries changed since the last
    time; a change made without register_baseline (no listener call) is still seen."""
    from hydra.errors import ConfigCompositionException

    from stdr.baselines.registry import BaselineSpec
    with pytest.raises(ConfigCompositionException, match="drift"):
        make_cfg(["baseline=drift"])
    monkeypatch.setattr(BASELINES, "_listeners", [])  # nobody is told of the changes below
    BASELINES.add("drift", BaselineSpec("drift", Drift, DriftConfig))
    assert make_cfg(["baseline=drift"]).baseline.drift.speed == 0.0
    BASELINES.remove("drift")
    with pytest.raises(ConfigCompositionException, match="drift"):
        make_cfg(["baseline=drift"])


@pytest.mark.slow
def test_a_baseline_is_one_module_and_one_config(tmp_path, drift):
    from stdr.model import load_model
    from stdr.train.trainer import Trainer

    # an option, derived experiments, typed keys, no budget file needed
    cfg = make_cfg(["experiment=dnerf_drift_stdr", "data.path=/x", "baseline.drift.speed=0.5"])
    assert cfg.baseline.drift.speed == 0.5 and cfg.stdr.enabled and cfg.baseline.depth == 8
    # the whole loop, with STDR's conditioning, trains it; the checkpoint rebuilds it
    sched = ["optim.iterations=40", "baseline.warmup=10", "densify.refine_start=5", "densify.refine_every=5",
             "train.checkpoint_every=0", "train.eval_at_warmup_end=false", "stdr.warmup_end=10",
             "stdr.freeze_at=20", "baseline.scgs.num_nodes=64"]  # another baseline's key: skipped by the helper
    t = Trainer(tiny_config(tmp_path, sched + ["experiment=embedded_drift_stdr"]), tmp_path / "run",
                splits=("train", "test"))
    assert isinstance(t.state.model.deform, Drift) and t.state.model.deform.cond_dim > 0
    before = t.state.model.deform.speed.detach().clone()
    t.train()
    assert not torch.equal(before, t.state.model.deform.speed.detach())  # it learned
    psnr = t.evaluate("test")["psnr"]
    m = load_model(tmp_path / "run" / "checkpoints" / "last.pt", device="cpu")
    assert isinstance(m.deform, Drift) and torch.equal(m.deform.speed, t.state.model.deform.speed)
    from stdr.eval.evaluate import evaluate_model
    assert evaluate_model(m, t.scene.frames("test"))["psnr"] == pytest.approx(psnr, abs=1e-4)


def test_budget_files_are_optional_deltas(drift):
    # no budget_baseline/drift_*.yaml: the budget's shared keys apply on the typed defaults, and the
    # schedule keys scale with the run: warm-up 7.5 % of it (3 000 of the paper's 40 000), the
    # network's lr over all of it
    for budget, iters, warm in (("demo", 1500, 112), ("cpu", 2000, 150), ("paper", 40000, 3000)):
        c = make_cfg(["baseline=drift", f"budget={budget}"])
        assert (c.optim.iterations, c.baseline.depth, c.baseline.warmup, c.baseline.lr_max_steps) == \
            (iters, 8, warm, iters), budget
    assert make_cfg(["baseline=drift", "budget=cpu", "optim.iterations=100"]).baseline.warmup == 8
    # a baseline's budget file, where there is one, still applies on top (deform_cpu.yaml: 6x128)
    assert (make_cfg(["baseline=deform", "budget=cpu"]).baseline.depth,
            make_cfg(["baseline=deform", "budget=paper"]).baseline.depth) == (6, 8)


def test_registration_is_checked():
    with pytest.raises(ValueError, match="name defaults to 'drift'"):
        register_baseline("other", Drift, DriftConfig)
    with pytest.raises(TypeError, match="Deformation subclass"):
        register_baseline("drift", nn.Linear, DriftConfig)

    @dataclass
    class Loose:
        name: str = "loose"
    with pytest.raises(TypeError, match="BaselineConfig"):
        register_baseline("loose", Drift, Loose)
    with pytest.raises(ValueError, match="already registered"):
        register_baseline("deform", Drift, DriftConfig.__mro__[1])
    with pytest.raises(ValueError, match="not a registered baseline.*register_baseline"):
        get_baseline("nope")
    # capabilities are a set of known names, each backed by the hook it needs; conditioning needs a
    # config_kwargs that passes it on
    with pytest.raises(TypeError, match=r"Vague.capabilities must be a set of names from .*got 'conditioning'"):
        register_baseline("drift", type("Vague", (Drift,), {"capabilities": "conditioning"}), DriftConfig)
    with pytest.raises(TypeError, match=r"Typo.capabilities must be a set of names from .*'conditionning'"):
        register_baseline("drift", type("Typo", (Drift,), {"capabilities": frozenset({"conditionning"})}), DriftConfig)
    with pytest.raises(TypeError, match=r"Mixer declares 'mixes_rows' but does not override forward_rows"):
        register_baseline("drift", type("Mixer", (Drift,), {"capabilities": frozenset({"mixes_rows"})}), DriftConfig)
    with pytest.raises(TypeError, match=r"Blender overrides forward_rows but does not declare 'mixes_rows'"):
        register_baseline("drift", type("Blender", (Drift,), {"forward_rows": lambda self, p, t, c, r: None}),
                          DriftConfig)
    with pytest.raises(TypeError, match=r"bf16_default must be True or False, got 1"):
        register_baseline("drift", Drift, DriftConfig, bf16_default=1)

    class Deaf(Drift):
        @classmethod
        def config_kwargs(cls, b, train_times=None, seed=0, schedule=None):
            return {"speed": b.drift.speed}
    with pytest.raises(TypeError, match="Deaf declares 'conditioning' but its config_kwargs takes no cond_dim"):
        register_baseline("drift", Deaf, DriftConfig)
    assert "drift" not in BASELINES


def test_a_baseline_that_declares_no_conditioning_gets_no_stdr_experiment():
    """STDR's separated field needs a network that takes `cond`: a baseline without the capability
    gets its plain experiments only, and turning STDR on is refused before the run starts, unless
    STDR runs without its field (then it feeds no conditioning)."""
    from stdr.baselines.registry import capabilities
    from stdr.errors import ConfigError
    from stdr.store import experiments_on
    from stdr.validate import check_run_config
    assert all(capabilities(BASELINES[b].module) >= {"conditioning"} for b in ("deform", "scgs", "spgs", "4dgs"))
    assert "mixes_rows" in capabilities(BASELINES["scgs"].module) and "mixes_rows" not in capabilities(Drift)

    class Plain(Drift):
        capabilities = frozenset()
    register_baseline("drift", Plain, DriftConfig, in_grids=True)  # in the grids, to see what they hold of it
    try:
        assert capabilities(Plain) == frozenset()
        assert {e for e in experiment_names() if "drift" in e} == {f"{d}_drift" for d in data_options()}
        assert "dnerf_drift," in experiments_on("dnerf") + "," and "dnerf_drift_stdr" not in experiments_on("dnerf")
        with pytest.raises(ConfigError, match=r"^stdr=on with baseline=drift \(Plain\): stdr needs a baseline with "
                                              r"the capability 'conditioning'; set stdr=off, or add "
                                              r"'conditioning' to Plain.capabilities once its forward takes `cond`"):
            check_run_config(make_cfg(["baseline=drift", "stdr=on", "data.path=/x"]))
        check_run_config(make_cfg(["experiment=embedded_drift", "stdr=on", "stdr.separated_field=false"]))
    finally:
        unregister_baseline("drift")


def test_saved_configs_load_onto_their_baselines_typed_defaults(tmp_path):
    cfg = OmegaConf.to_container(make_cfg(["experiment=dnerf_scgs", "data.path=/x"]), resolve=True)
    back = load_config(cfg)
    assert OmegaConf.get_type(back.baseline) is get_baseline("scgs").config and back.baseline.scgs.num_nodes == 512
    # a config.yaml from before per-baseline configs carried every baseline's sub-config
    old = OmegaConf.to_container(make_cfg(["experiment=dnerf_deform", "data.path=/x"]), resolve=True)
    old["baseline"].update(scgs={"num_nodes": 512}, spgs={"num_superpoints": 300}, hexplane={"base_res": 64})
    p = tmp_path / "config.yaml"
    p.write_text(OmegaConf.to_yaml(old))
    assert "scgs" not in load_config(p).baseline
    # a config.yaml from before static skipping was removed carried stdr.static_skip
    old["stdr"]["static_skip"] = 0.0
    p.write_text(OmegaConf.to_yaml(old))
    assert "static_skip" not in load_config(p).stdr
    # anything else unknown is an error that names the file
    old["baseline"]["nodes"] = 3
    p.write_text(OmegaConf.to_yaml(old))
    with pytest.raises(ValueError, match=f"{p}.*nodes"):
        load_config(p)
    old["baseline"] = {"name": "nope"}
    p.write_text(OmegaConf.to_yaml(old))
    with pytest.raises(ValueError, match=f"{p}.*'nope'"):
        load_config(p)


@pytest.mark.parametrize("name", sorted(BASELINES))
@pytest.mark.parametrize("stdr", ["", "_stdr"])
def test_longer_cpu_preset_is_the_cpu_preset_on_the_paper_schedule_scaled_to_10k(name, stdr):
    """budget=cpu_long (docs/budgets.md): budget=cpu's sizes (resolution, initial points, cap,
    networks, thresholds) and every schedule milestone of the baseline's paper run scaled by
    10k / its paper iterations (to within rounding to 100 steps), the rule budget=gpu follows
    for 20k; SC-GS's ARAP steps scale with it."""
    from stdr.eval.table import flatten
    exp = [f"experiment=dnerf_{name}{stdr}", "data.path=/x"]
    cfgs = {b: flatten(OmegaConf.to_container(make_cfg(exp + [f"budget={b}"]), resolve=True))
            for b in ("cpu", "cpu_long", "paper")}
    cpu, long, paper = cfgs["cpu"], cfgs["cpu_long"], cfgs["paper"]
    assert long["optim.iterations"] == 10000
    f = 10000 / paper["optim.iterations"]
    for k in MILESTONES - {"optim.iterations"}:
        if paper.get(k):
            assert abs(long[k] - paper[k] * f) <= 50, (k, long[k], paper[k] * f)
    assert long["densify.reset_white_at_start"] == paper["densify.reset_white_at_start"] is True
    scaled = MILESTONES | {"budget", "densify.reset_white_at_start", "baseline.scgs.arap_steps"}
    changed = {k for k in cpu.keys() | long.keys() if cpu.get(k) != long.get(k) and not k.startswith("schedule.")}
    assert changed <= scaled, changed - scaled  # sizes, networks and thresholds stay budget=cpu's
    if name == "scgs":
        arap = long["baseline.scgs.arap_steps"]
        assert all(abs(a - b * f) <= 1 for a, b in zip(arap, paper["baseline.scgs.arap_steps"])), arap
    if stdr:  # STDR's phases follow the baseline's static warm-up: the paper's 3000 / 6000 of 40k, scaled
        from stdr.store import resolve_schedule
        sc = resolve_schedule(make_cfg(exp + ["budget=cpu_long"]))
        assert sc.plugins["stdr"]["warmup_end"] == long["baseline.warmup"]
        assert sc.plugins["stdr"]["freeze_at"] >= 2 * long["baseline.warmup"]


MILESTONES = {"optim.iterations", "optim.means_lr_max_steps", "model.sh_interval", "densify.refine_start",
              "densify.refine_stop", "densify.reset_every", "densify.prune_big_after", "baseline.warmup",
              "baseline.lr_max_steps", "baseline.scgs.node_stage_end", "baseline.scgs.main_warmup"}


@pytest.mark.parametrize("name", sorted(BASELINES))
@pytest.mark.parametrize("stdr", ["", "_stdr"])
def test_gpu_preset_is_the_paper_preset_with_its_schedule_scaled_to_20k(name, stdr):
    """budget=gpu (docs/budgets.md): every schedule milestone of the baseline's paper run
    scaled by 20k / its paper iterations (to within rounding to 100 steps), 400 px wide, no
    screen-size prune (research/measurements/size_prune_val decided it on val), nothing else changed
    (networks, thresholds, the densification interval, STDR's own settings; its phases follow the
    warm-up)."""
    from stdr.eval.table import flatten
    exp = [f"experiment=dnerf_{name}{stdr}", "data.path=/x"]
    paper = flatten(OmegaConf.to_container(make_cfg(exp + ["budget=paper"]), resolve=True))
    gpu = flatten(OmegaConf.to_container(make_cfg(exp + ["budget=gpu"]), resolve=True))
    changed = {k for k in paper.keys() | gpu.keys() if paper.get(k) != gpu.get(k) and not k.startswith("schedule.")}
    assert changed == {"budget", "data.max_width", "densify.prune_scale2d"} | {k for k in MILESTONES if paper.get(k)}, \
        changed
    assert gpu["data.max_width"] == 400 and gpu["optim.iterations"] == 20000
    assert gpu["densify.prune_scale2d"] is None and paper["densify.prune_scale2d"] == 20.0
    f = 20000 / paper["optim.iterations"]
    for k in changed & MILESTONES:
        assert abs(gpu[k] - paper[k] * f) <= 50, (k, paper[k], gpu[k], f)


@pytest.mark.slow
@pytest.mark.parametrize("budget", ["demo", "cpu"])
def test_a_baseline_without_budget_files_trains_its_deformation_under_every_budget(tmp_path, drift, budget):
    """The warm-up trap: a fifth baseline with the typed defaults only used to keep a 3 000-step
    warm-up under budget=cpu (2 000 iterations) and budget=demo (1 500), and never deformed. Here
    the run is shortened to 60 steps (the warm-up scales with it: 4 or 5 steps) and the deformation's
    own parameter must have moved."""
    from stdr.train.trainer import Trainer
    t = Trainer(tiny_config(tmp_path, ["experiment=embedded_drift", f"budget={budget}", "optim.iterations=60",
                                       "train.checkpoint_every=0", "train.eval_at_warmup_end=false"]), tmp_path / "run")
    assert t.state.model.warmup == round(0.075 * 60) and t.state.model.warmup < 60
    before = t.state.model.deform.speed.detach().clone()
    t.train()
    assert not torch.equal(before, t.state.model.deform.speed.detach())


class DriftNoCond(Drift):
    """Drift whose config_kwargs forgets the plug-ins' conditioning width."""

    @classmethod
    def config_kwargs(cls, b, cond_dim=0, train_times=None, seed=0, schedule=None):
        return {"speed": b.drift.speed}


class DriftBadKwargs(Drift):
    @classmethod
    def config_kwargs(cls, b, cond_dim=0, train_times=None, seed=0, schedule=None):
        return {"speed": b.drift.speed, "cond_dim": cond_dim, "sped": 1.0}


@pytest.mark.parametrize("module, error, said", [
    (DriftNoCond, "ConfigError", "baseline drift (DriftNoCond) was built for per-Gaussian conditioning of width 0, "
                                 "but the plug-ins on feed 17"),
    (DriftBadKwargs, "TypeError", "DriftBadKwargs.config_kwargs returned arguments DriftBadKwargs.__init__ does not take"),
])
def test_a_baseline_that_cannot_be_built_as_configured_fails_at_construction_naming_the_hook(tmp_path, module, error,
                                                                                             said):
    """Before the first step (and before the run's record): a baseline that does not take STDR's
    conditioning, or whose config_kwargs does not fit its constructor, is named with the fix."""
    from stdr.baselines.registry import build_deformation
    from stdr.testing import make_cfg
    register_baseline("drift", module, DriftConfig)
    try:
        cfg = make_cfg(["experiment=embedded_drift_stdr"] if error == "ConfigError" else ["experiment=embedded_drift"])
        with pytest.raises(Exception, match=re.escape(said)) as e:
            build_deformation(cfg.baseline, 17 if error == "ConfigError" else 0)
        assert type(e.value).__name__ == error
    finally:
        unregister_baseline("drift")


def test_a_baseline_joins_the_default_grids_only_when_it_says_so():
    """register_baseline(in_grids=False), the default (a baseline from another package): its
    experiments exist, the default grids stay as they were; a plug-in named in the list still
    reaches it."""
    from stdr.store import experiments_on
    before = experiments_on("dnerf")
    register_baseline("drift", Drift, DriftConfig)
    try:
        assert "dnerf_drift" in experiment_names() and "dnerf_drift_stdr" in experiment_names()
        assert experiments_on("dnerf") == before and "drift" not in experiments_on("dnerf", "plain")
        assert "dnerf_drift_stdr" in experiments_on("dnerf", "stdr").split(",")
        with pytest.raises(TypeError, match="in_grids must be True or False"):
            register_baseline("drift2", Drift, DriftConfig, in_grids="yes")
    finally:
        unregister_baseline("drift")


# ----------------------------------------------------------------- densification strategies
@dataclass
class Thinning(DensifyStrategy):
    """Never grows; every `every` steps removes the `share` of the Gaussians with the lowest opacity."""

    name: str = "thinning"
    every: int = 10
    share: float = 0.1

    @classmethod
    def stages(cls, d):
        return [(int(d.every), "densify.every", "first thinning")], ["thinning: no growth"]

    def step_post_backward(self, params, optimizers, state, step, means2d, radii, width, height, generator=None,
                           opacity_fn=None, reset_fn=None, rows=None, opacities=None):
        from stdr.densify.strategy import remove
        if step % self.every:
            return {}
        n = params["means"].shape[0]
        k = int(n * self.share)
        drop = torch.zeros(n, dtype=torch.bool, device=params["means"].device)
        drop[torch.topk(-params["opacities"].detach().squeeze(-1), k).indices] = True
        remove(params, optimizers, state, drop)
        return {"pruned": k}


@pytest.fixture
def thinning():
    register_strategy("thinning", Thinning)
    yield
    unregister_strategy("thinning")
    assert "thinning" not in STRATEGIES


def test_strategy_registration_is_checked():
    @dataclass
    class Unnamed(DensifyStrategy):
        pass

    with pytest.raises(TypeError, match="dataclass subclassing"):
        register_strategy("loose", object)
    with pytest.raises(ValueError, match="Unnamed.name defaults to 'default'; set `name: str = 'x'`"):
        register_strategy("x", Unnamed)
    with pytest.raises(ValueError, match=r"densify.name='nope' is not a registered densification strategy.*default"):
        get_strategy("nope")
    with pytest.raises(Exception, match="nope"):
        make_cfg(["densify=nope"])


def test_a_second_strategy_is_an_option_with_typed_keys_and_stages(thinning):
    cfg = make_cfg(["experiment=dnerf_deform", "data.path=/x", "densify=thinning", "densify.share=0.25"])
    assert cfg.densify.name == "thinning" and cfg.densify.share == 0.25
    assert cfg.densify.refine_stop == 1500  # the budget's shared keys still apply
    with pytest.raises(Exception, match="share"):
        make_cfg(["densify=thinning", "densify.share=lots"])
    with pytest.raises(Exception, match="share"):  # the default strategy has no such key
        make_cfg(["densify.share=0.5"])
    s = resolve_schedule(cfg)
    assert "10  first thinning  [densify.every]" in s.describe() and "thinning: no growth" in s.notes
    assert "densify.refine_start" not in s.describe()  # its stages replace the default's
    from stdr.store import load_config
    from omegaconf import OmegaConf
    assert load_config(OmegaConf.to_container(cfg, resolve=True)).densify.share == 0.25


@pytest.mark.slow
def test_a_second_strategy_trains_through_the_loop(tmp_path, thinning):
    from stdr.train.trainer import Trainer
    t = Trainer(tiny_config(tmp_path, ["experiment=embedded_deform", "densify=thinning", "densify.every=10",
                                       "densify.share=0.1", "optim.iterations=30", "baseline.warmup=10",
                                       "train.checkpoint_every=0", "train.eval_at_warmup_end=false"]),
                tmp_path / "run")
    assert isinstance(t.strategy, Thinning)
    n0 = t.state.model.num_gaussians
    t.train()
    n = n0
    for _ in range(3):  # at 10, 20, 30
        n -= int(n * 0.1)
    assert t.state.model.num_gaussians == n
    assert all(v.shape[0] == n for v in t.state.model.params.values())
