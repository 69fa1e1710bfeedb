"""examples/stdr_linear, the outside package docs/extending.md walks through: installed with pip
(into a folder of its own, put on the path of fresh processes), its baseline trains plain and
+STDR with its plug-in through stdr-train, the conformance kit passes on both, and installing it
changes no built-in grid."""
import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from stdr.testing import TINY_SCENE

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "examples" / "stdr_linear"

GRIDS = textwrap.dedent("""
    import json
    from stdr.store import compose_config, experiment_names
    grid = compose_config(["+sweep=dnerf_grid"], return_hydra_config=True).hydra.sweeper.params
    stab = compose_config(["+sweep=stability"], return_hydra_config=True).hydra.sweeper.params
    print(json.dumps({"dnerf_grid": dict(grid), "stability": dict(stab), "experiments": experiment_names()}))
""")


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> dict:
    site = tmp_path_factory.mktemp("site")
    r = subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation",
                        "--target", str(site), str(EXAMPLE)], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    return {**os.environ, "PYTHONPATH": os.pathsep.join([str(site), str(ROOT)])}


def _run(args, env, timeout=900):
    return subprocess.run([sys.executable, *args], cwd=ROOT, env=env, capture_output=True, text=True, timeout=timeout)


def test_installing_the_example_changes_no_built_in_grid(installed):
    without = _run(["-c", GRIDS], {**os.environ, "PYTHONPATH": str(ROOT)})
    with_it = _run(["-c", GRIDS], installed)
    assert without.returncode == 0 and with_it.returncode == 0, without.stderr[-2000:] + with_it.stderr[-2000:]
    a, b = json.loads(without.stdout), json.loads(with_it.stdout)
    assert a["dnerf_grid"] == b["dnerf_grid"] and a["stability"] == b["stability"]
    added = sorted(set(b["experiments"]) - set(a["experiments"]))
    # the baseline on every data option, plain and +STDR; its plug-in only on it
    assert "embedded_linear" in added and "embedded_linear_stdr" in added and "embedded_linear_velocity_l1" in added
    assert all("linear" in e for e in added) and not [e for e in b["experiments"] if e.endswith("deform_velocity_l1")]


@pytest.mark.slow
def test_the_example_trains_plain_and_with_stdr_and_its_budget_file_applies(installed, tmp_path):
    tiny = [*TINY_SCENE, f"data.cache_dir={tmp_path / 'cache'}", "device=cpu", "model.init_num=1500",
            "eval.lpips=false", "train.progress=false", "eval.save_images=false", "train.image_every=0",
            "optim.iterations=60", "baseline.warmup=20"]
    for exp, more in (("embedded_linear", ["velocity_l1=on"]), ("embedded_linear_stdr", ["stdr.warmup_end=30",
                                                                                         "stdr.freeze_at=40"])):
        p = _run(["-m", "stdr.cli.train", f"experiment={exp}", *more, *tiny, f"hydra.run.dir={tmp_path / exp}"], installed)
        assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-2000:]
        m = json.loads((tmp_path / exp / "metrics.json").read_text())["test"]
        assert m["psnr"] > 9.0  # the untrained start renders about 7 dB on this scene
    assert "mean_speed" in json.loads((tmp_path / "embedded_linear" / "metrics.json").read_text())["test"]["velocity_l1"]
    demo = _run(["-c", "from stdr.store import compose_config; "
                       "print(compose_config(['experiment=embedded_linear', 'budget=demo']).baseline.warmup)"], installed)
    assert demo.stdout.split() == ["400"], demo.stderr[-2000:]  # the package's budget_baseline/linear_demo.yaml


@pytest.mark.slow
@pytest.mark.parametrize("kit", [["check-baseline", "linear", "--plugin", "stdr"],
                                 ["check-plugin", "velocity_l1", "--baseline", "linear"]])
def test_the_conformance_kit_passes_on_the_example(installed, kit):
    p = _run(["-m", "stdr.cli.tool", *kit, "--quick"], installed)
    assert p.returncode == 0 and "6 of 6 checks passed" in p.stdout, p.stdout[-3000:] + p.stderr[-3000:]
