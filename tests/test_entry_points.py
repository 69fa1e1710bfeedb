"""A baseline from another distribution: a throw-away package with a `stdr.baselines` entry
point, on the path of a fresh process, trains through stdr-train, shows in stdr-eval's table and
reloads from its checkpoint, with no edit to stdr."""
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

from stdr.deform import BaselineConfig, Deformation, Deltas, register_baseline


@dataclass
class WobbleOptions:
    amplitude: float = 0.01


@dataclass
class WobbleConfig(BaselineConfig):
    name: str = "wobble"
    wobble: WobbleOptions = field(default_factory=WobbleOptions)


class Wobble(Deformation):
    """Every Gaussian moves by a learned vector times sin(t)."""

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
'''


def _distribution(root: Path, entry: str) -> None:
    (root / "stdr_wobble").mkdir(parents=True)
    (root / "stdr_wobble" / "__init__.py").write_text(TOY)
    info = root / "stdr_wobble-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: stdr-wobble\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(f"[stdr.baselines]\nwobble = {entry}\n")


def _run(args, env):
    return subprocess.run([sys.executable, *args], cwd=ROOT, env=env, capture_output=True, text=True, timeout=900)


@pytest.mark.slow
def test_a_baseline_from_another_distribution_trains_tabulates_and_reloads(tmp_path):
    _distribution(tmp_path / "site", "stdr_wobble:register")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path / "site"), str(ROOT)])}
    run = tmp_path / "run"
    tiny = ["data.procedural.resolution=64", "data.procedural.n_train=40", "data.procedural.n_val=2",
            "data.procedural.n_test=4", f"data.cache_dir={tmp_path / 'cache'}", "device=cpu", "model.init_num=1500",
            "eval.lpips=false", "train.progress=false", "eval.save_images=false", "train.image_every=0"]
    p = _run(["-m", "stdr.cli.train", "experiment=embedded_wobble_stdr", "optim.iterations=60", "stdr.warmup_end=10",
              "stdr.freeze_at=20", "baseline.wobble.amplitude=0.02", *tiny, f"hydra.run.dir={run}"], env)
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
    m = json.loads((run / "metrics.json").read_text())["test"]
    assert m["psnr"] > 5
    cfg = (run / "config.yaml").read_text()
    assert "name: wobble" in cfg and "amplitude: 0.02" in cfg
    e = _run(["-m", "stdr.cli.eval", str(run), f"out={tmp_path / 'table'}"], env)
    assert e.returncode == 0, e.stdout[-3000:] + e.stderr[-3000:]
    assert "| wobble+STDR |" in e.stdout
    code = textwrap.dedent(f"""
        import torch
        from stdr.model import load_model
        m = load_model({str(run / 'checkpoints' / 'last.pt')!r}, device="cpu")
        print(type(m.deform).__module__, type(m.deform).__name__, m.deform.direction.tolist())
    """)
    r = _run(["-c", code], env)
    assert r.returncode == 0, r.stderr[-3000:]
    mod, cls, direction = r.stdout.split(" ", 2)
    assert (mod, cls) == ("stdr_wobble", "Wobble") and json.loads(direction) != [0.02, 0.02, 0.02]  # it trained


def test_a_broken_entry_point_is_an_error_that_names_it(tmp_path):
    _distribution(tmp_path / "site", "stdr_wobble:missing_function")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path / "site"), str(ROOT)])}
    p = _run(["-c", "from stdr.deform.registry import discover_baselines; discover_baselines()"], env)
    assert p.returncode != 0
    assert ("entry point 'wobble' = 'stdr_wobble:missing_function' (group 'stdr.baselines', "
            "distribution stdr-wobble 0.1) failed") in p.stderr
