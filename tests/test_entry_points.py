"""A baseline and a plug-in from another distribution: a throw-away package with
`stdr.baselines`, `stdr.plugins` and `stdr.strategies` entry points, on the path of a fresh process, trains through
stdr-train (the plug-in beside STDR), shows in stdr-eval's table and reloads from its checkpoint,
with no edit to stdr."""
import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

TOY = '''
from dataclasses import dataclass, field

import torch
from torch import nn

from stdr.baselines import BaselineConfig, Deformation, Deltas, register_baseline


@dataclass
class WobbleOptions:
    amplitude: float = 0.01


@dataclass
class WobbleConfig(BaselineConfig):
    name: str = "wobble"
    wobble: WobbleOptions = field(default_factory=WobbleOptions)


class Wobble(Deformation):
    """Every Gaussian moves by a learned vector times sin(t)."""

    capabilities = frozenset({"conditioning"})  # it takes STDR's conditioning (cond_dim), and leaves it unused

    def __init__(self, amplitude=0.01, cond_dim=0):
        super().__init__()
        self.cond_dim = cond_dim
        self.direction = nn.Parameter(torch.full((3,), amplitude))

    @classmethod
    def config_kwargs(cls, b, cond_dim=0, train_times=None, seed=0, schedule=None):
        return {"amplitude": b.wobble.amplitude, "cond_dim": cond_dim}

    def forward(self, params, t, cond=None):
        return Deltas(means=(self.direction * torch.sin(torch.tensor(float(t)))).expand_as(params["means"]))


def register():
    register_baseline("wobble", Wobble, WobbleConfig)


from stdr.plugins import Plugin, Reporting, register_plugin


@dataclass
class GlowConfig:
    enabled: bool = False
    weight: float = 0.5


class Glow(Reporting, Plugin):
    """A loss term pulling every Gaussian's opacity logit up, weighted by `glow.weight`."""

    name = "glow"

    def __init__(self, weight):
        self.weight = weight

    @classmethod
    def from_config(cls, pcfg, cfg, schedule, train_times, device):
        return cls(pcfg.weight)

    def regularizers(self, ctx):
        return {"pull": -self.weight * ctx.params["opacities"].mean()}

    def stats(self, params):
        return {"weight": self.weight}


def register_glow():
    register_plugin("glow", Glow, GlowConfig, label="+glow")


from stdr.densify.strategy import DensifyStrategy, register_strategy


@dataclass
class Eager(DensifyStrategy):
    """The default strategy, growing from a lower gradient threshold."""
    name: str = "eager"
    grow_grad2d: float = 0.0001


def register_eager():
    register_strategy("eager", Eager)
'''


def _distribution(root: Path, entry: str, plugin_entry: str = "stdr_wobble:register_glow",
                  configs: dict[str, str] | None = None, toy: str = TOY) -> None:
    """configs: {path under the package's configs/ folder: YAML}, shipped through `stdr.configs`."""
    (root / "stdr_wobble").mkdir(parents=True)
    (root / "stdr_wobble" / "__init__.py").write_text(toy)
    info = root / "stdr_wobble-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: stdr-wobble\nVersion: 0.1\n")
    groups = (f"[stdr.baselines]\nwobble = {entry}\n\n[stdr.plugins]\nglow = {plugin_entry}\n\n"
              "[stdr.strategies]\neager = stdr_wobble:register_eager\n")
    if configs is not None:
        (root / "stdr_wobble" / "configs").mkdir()
        (root / "stdr_wobble" / "configs" / "__init__.py").write_text("")
        for rel, text in configs.items():
            (root / "stdr_wobble" / "configs" / rel).parent.mkdir(parents=True, exist_ok=True)
            (root / "stdr_wobble" / "configs" / rel).write_text(text)
        groups += "\n[stdr.configs]\nwobble = stdr_wobble.configs\n"
    (info / "entry_points.txt").write_text(groups)


def _run(args, env):
    return subprocess.run([sys.executable, *args], cwd=ROOT, env=env, capture_output=True, text=True, timeout=900)


@pytest.mark.slow
def test_a_baseline_and_a_plugin_from_another_distribution_train_tabulate_and_reload(tmp_path):
    _distribution(tmp_path / "site", "stdr_wobble:register")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path / "site"), str(ROOT)])}
    run = tmp_path / "run"
    tiny = ["data.procedural.resolution=64", "data.procedural.n_train=40", "data.procedural.n_val=2",
            "data.procedural.n_test=4", f"data.cache_dir={tmp_path / 'cache'}", "device=cpu", "model.init_num=1500",
            "eval.lpips=false", "train.progress=false", "eval.save_images=false", "train.image_every=0"]
    p = _run(["-m", "stdr.cli.train", "experiment=embedded_wobble_stdr", "optim.iterations=60", "stdr.warmup_end=10",
              "stdr.freeze_at=20", "baseline.wobble.amplitude=0.02", "glow=on", "glow.weight=0.25", *tiny, f"hydra.run.dir={run}"], env)
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
    m = json.loads((run / "metrics.json").read_text())["test"]
    assert m["psnr"] > 5 and m["glow"] == {"weight": 0.25}
    cfg = (run / "config.yaml").read_text()
    assert "name: wobble" in cfg and "amplitude: 0.02" in cfg and "glow:\n  enabled: true\n  weight: 0.25" in cfg
    e = _run(["-m", "stdr.cli.eval", str(run), f"out={tmp_path / 'table'}"], env)
    assert e.returncode == 0, e.stdout[-3000:] + e.stderr[-3000:]
    assert "| wobble+STDR+glow |" in e.stdout
    code = textwrap.dedent(f"""
        import torch
        from stdr.model import load_model
        m = load_model({str(run / 'checkpoints' / 'last.pt')!r}, device="cpu")
        assert sorted(p.name for p in m.plugins) == ["glow", "stdr"] and m.plugin("glow").weight == 0.25
        print(type(m.deform).__module__, type(m.deform).__name__, m.deform.direction.tolist())
    """)
    r = _run(["-c", code], env)
    assert r.returncode == 0, r.stderr[-3000:]
    mod, cls, direction = r.stdout.split(" ", 2)
    assert (mod, cls) == ("stdr_wobble", "Wobble") and json.loads(direction) != [0.02, 0.02, 0.02]  # it trained


def test_a_broken_entry_point_is_an_error_that_names_it(tmp_path):
    _distribution(tmp_path / "site", "stdr_wobble:missing_function")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path / "site"), str(ROOT)])}
    p = _run(["-c", "from stdr.baselines.registry import discover_baselines; discover_baselines()"], env)
    assert p.returncode != 0
    assert ("entry point 'wobble' = 'stdr_wobble:missing_function' (group 'stdr.baselines', "
            "distribution stdr-wobble 0.1) failed") in p.stderr


def test_a_broken_plugin_entry_point_is_an_error_that_names_it(tmp_path):
    _distribution(tmp_path / "site", "stdr_wobble:register", plugin_entry="stdr_wobble:register")  # registers no plug-in
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path / "site"), str(ROOT)])}
    p = _run(["-c", "from stdr.plugins import PLUGINS; PLUGINS.discover()"], env)
    assert p.returncode != 0
    assert ("entry point 'glow' = 'stdr_wobble:register' (group 'stdr.plugins', distribution stdr-wobble 0.1) "
            "registered nothing; it must name a function (or module) that calls stdr.plugins.register_plugin") in p.stderr


def test_a_wrongly_declared_plugin_of_another_distribution_is_one_line_in_every_command(tmp_path):
    """A plug-in whose loss still takes the earlier (params, step): each command that loads the
    registries stops before it starts, with exit code 2 and one line naming the entry point, the
    hook and the fix; no traceback."""
    old = 'def regularizers(self, ctx):\n        return {"pull": -self.weight * ctx.params["opacities"].mean()}'
    assert old in TOY
    _distribution(tmp_path / "site", "stdr_wobble:register",
                  toy=TOY.replace(old, 'def regularizers(self, params, step):\n        return {"pull": params["opacities"].mean()}'))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path / "site"), str(ROOT)])}
    commands = {"stdr-train": ["-m", "stdr.cli.train", "experiment=embedded_deform", f"hydra.run.dir={tmp_path / 'run'}"],
                "stdr-eval": ["-m", "stdr.cli.eval", str(tmp_path / "run")],
                "stdr-tool": ["-m", "stdr.cli.tool", "check-plugin", "glow"],
                "stdr-export": ["-c", "import sys; from stdr.cli.view import export_main; export_main(sys.argv[1:])",
                                str(tmp_path / "run"), "--times", "0"]}
    for prog, args in commands.items():
        p = _run(args, env)
        assert p.returncode == 2, (prog, p.stderr[-3000:])
        lines = p.stderr.strip().splitlines()
        assert lines == [f"{prog}: error: entry point 'glow' = 'stdr_wobble:register_glow' (group 'stdr.plugins', "
                         "distribution stdr-wobble 0.1): register_plugin('glow'): Glow.regularizers(params, step) must "
                         "take the step's context: def regularizers(self, ctx) (ctx: stdr.context.StepContext, with "
                         "step, phase, t, camera, params, cond, deformed and render)"], (prog, p.stderr[-3000:])
    assert not (tmp_path / "run").exists()  # stopped before the run folder was made


def test_a_strategy_from_another_distribution_is_an_option_of_stdr_train(tmp_path):
    """The `stdr.strategies` group: densify=eager composes with its own keys, found by name."""
    _distribution(tmp_path / "site", "stdr_wobble:register")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path / "site"), str(ROOT)])}
    code = textwrap.dedent("""
        from stdr.densify.strategy import get_strategy
        from stdr.store import compose_config
        cfg = compose_config(["densify=eager"])
        print(get_strategy("eager").__module__, cfg.densify.name, get_strategy("eager")().grow_grad2d)
    """)
    p = _run(["-c", code], env)
    assert p.returncode == 0, p.stderr[-3000:]
    assert p.stdout.split() == ["stdr_wobble", "eager", "0.0001"]


WOBBLE_DEMO = "# @package _global_\nbaseline:\n  warmup: 30\n  wobble:\n    amplitude: 0.05\n"
WOBBLE_SWEEP = ("# @package _global_\noptim:\n  iterations: 40\nhydra:\n  sweeper:\n    params:\n"
                "      experiment: embedded_wobble,embedded_wobble_stdr\n")


def test_budget_and_sweep_files_from_another_distribution_are_found_by_name(tmp_path):
    """The `stdr.configs` group: a package's budget_baseline/wobble_demo.yaml applies to
    budget=demo as stdr's own files do to its baselines, and its sweep file is a `+sweep=` option."""
    _distribution(tmp_path / "site", "stdr_wobble:register",
                  configs={"budget_baseline/wobble_demo.yaml": WOBBLE_DEMO, "sweep/wobble_pair.yaml": WOBBLE_SWEEP})
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path / "site"), str(ROOT)])}
    code = textwrap.dedent("""
        from stdr.store import compose_config
        demo = compose_config(["experiment=embedded_wobble", "budget=demo"])
        cpu = compose_config(["experiment=embedded_wobble", "budget=cpu"])
        deform = compose_config(["experiment=embedded_deform", "budget=demo"])
        swept = compose_config(["+sweep=wobble_pair"], return_hydra_config=True)
        print(demo.baseline.warmup, demo.baseline.wobble.amplitude, cpu.baseline.wobble.amplitude,
              deform.baseline.warmup, swept.optim.iterations, swept.hydra.sweeper.params.experiment)
    """)
    p = _run(["-c", code], env)
    assert p.returncode == 0, p.stderr[-3000:]
    assert p.stdout.split() == ["30", "0.05", "0.01", "400", "40", "embedded_wobble,embedded_wobble_stdr"]


def test_a_config_file_at_the_path_of_one_stdr_ships_is_refused_in_one_line(tmp_path):
    """A package's budget_baseline/deform_demo.yaml would lose to stdr's own without a word: it is
    refused before anything runs, naming the entry point, the distribution and the file."""
    _distribution(tmp_path / "site", "stdr_wobble:register", configs={"budget_baseline/deform_demo.yaml": WOBBLE_DEMO})
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path / "site"), str(ROOT)])}
    p = _run(["-m", "stdr.cli.train", "budget=demo", f"hydra.run.dir={tmp_path / 'run'}"], env)
    assert p.returncode == 2 and "Traceback" not in p.stderr, p.stderr[-3000:]
    lines = [ln for ln in p.stderr.splitlines() if ln.startswith("stdr-train: error:")]
    assert len(lines) == 1 and "entry point 'wobble' = 'stdr_wobble.configs' (group 'stdr.configs', distribution " \
        "stdr-wobble 0.1)" in lines[0] and "budget_baseline/deform_demo.yaml of a config file stdr ships" in lines[0]
    assert not (tmp_path / "run").exists()


def test_the_search_path_plugin_leaves_another_stdr_alone(monkeypatch):
    """Hydra loads the plugin from any `hydra_plugins` folder on the path: in a process that runs
    another stdr (an older checkout on PYTHONPATH beside this editable install), whose stdr.store
    has no config_packages, it adds nothing and raises nothing."""
    import stdr.store
    from hydra.core.config_search_path import ConfigSearchPath
    from hydra._internal.config_search_path_impl import ConfigSearchPathImpl
    from hydra_plugins.stdr_configs import StdrConfigPackages

    path: ConfigSearchPath = ConfigSearchPathImpl()
    monkeypatch.setattr(stdr.store, "config_packages", lambda: (("mine", "my_package.configs"),))
    StdrConfigPackages().manipulate_search_path(path)
    assert [e.path for e in path.get_path()] == ["pkg://my_package.configs"]
    monkeypatch.delattr(stdr.store, "config_packages")
    older: ConfigSearchPath = ConfigSearchPathImpl()
    StdrConfigPackages().manipulate_search_path(older)
    assert older.get_path() == []
