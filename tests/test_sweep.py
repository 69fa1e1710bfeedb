"""Sweeps on Hydra's multirun with real launchers (joblib, submitit_local), failure reporting,
skipping finished runs, and the SLURM config (composes only: no cluster here)."""
import json
import os
import subprocess
import sys

import pytest
from omegaconf import OmegaConf

from stdr.baselines import BASELINES
from stdr.testing import make_cfg


def _sweep(tmp_path, *overrides, timeout=900):
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    cmd = [sys.executable, "-m", "stdr.cli.train", "-m", "+sweep=embedded_smoke", f"hydra.sweep.dir={tmp_path / 'sw'}",
           f"data.cache_dir={tmp_path / 'cache'}", "experiment=embedded_deform", *overrides]
    p = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=timeout, env=env)
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
    return p.stdout + p.stderr


@pytest.mark.slow
def test_joblib_sweep_runs_every_job_reports_failures_and_skips_finished_runs(tmp_path):
    sub = "hydra.sweep.subdir=${name}/${data.eval_split}/s${seed}"  # a run folder per job
    out = _sweep(tmp_path, "hydra/launcher=local", "seed=0,1", "data.eval_split=test,bogus", sub)
    runs = {s: tmp_path / "sw" / "embedded_deform" / "test" / f"s{s}" for s in (0, 1)}
    # the two good jobs finished; the two with a bad split failed without stopping them
    assert all((d / "metrics.json").is_file() for d in runs.values())
    fails = [json.loads(x) for x in (tmp_path / "sw" / "failures.jsonl").read_text().splitlines()]
    assert len(fails) == 2 and all("data.eval_split=bogus" in f["overrides"] for f in fails)
    assert all(f["log"].endswith(".log") and "bogus" in f["error"] for f in fails)
    assert "2 failed job(s)" in out and "data.eval_split=bogus" in out
    # a rerun of the good jobs skips them; stdr-eval takes the sweep folder itself
    stamp = {s: (d / "metrics.json").stat().st_mtime_ns for s, d in runs.items()}
    out = _sweep(tmp_path, "hydra/launcher=local", "seed=0,1", "data.eval_split=test", sub)
    assert out.count("skipping finished run") == 2 and "no failed jobs" in out
    assert all((d / "metrics.json").stat().st_mtime_ns == stamp[s] for s, d in runs.items())
    p = subprocess.run([sys.executable, "-m", "stdr.cli.eval", str(tmp_path / "sw"), "reevaluate=false",
                        f"out={tmp_path / 'table'}"], capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert p.returncode == 0, p.stderr[-3000:]
    cell = json.loads((tmp_path / "table" / "table.json").read_text())["cells"]["deform"]["embedded"]
    assert cell["n_runs"] == 2  # the two seeds of the sweep, averaged


@pytest.mark.slow
def test_submitit_local_sweep_completes(tmp_path):
    _sweep(tmp_path, "hydra/launcher=submitit_local", "seed=0,1", "hydra.launcher.timeout_min=20")
    for s in (0, 1):
        m = json.loads((tmp_path / "sw" / "embedded_deform" / f"s{s}" / "metrics.json").read_text())
        assert m["test"]["iterations"] == 40


def test_launcher_and_sweep_configs_compose():
    slurm = make_cfg(["hydra/launcher=slurm"], return_hydra_config=True).hydra.launcher
    assert slurm._target_.endswith("SlurmLauncher") and slurm.gpus_per_task == 1 and slurm.timeout_min > 0
    local = make_cfg(["hydra/launcher=local"], return_hydra_config=True).hydra.launcher
    assert local._target_.endswith("JoblibLauncher") and local.n_jobs == 1
    grid = make_cfg(["+sweep=dnerf_grid", "data.root=/data/dnerf", "data.name=lego"], return_hydra_config=True)
    params = OmegaConf.to_container(grid.hydra.sweeper.params, resolve=True)
    # every registered baseline, plain and +STDR: a new baseline joins the grid by registering
    assert params["experiment"].split(",") == [f"dnerf_{b}{s}" for b in sorted(BASELINES) for s in ("", "_stdr")]
    assert grid.data.path == "/data/dnerf/lego" and params["seed"] == "0,1,2"
    # without data.root the scene path is an error naming the key, never a folder "None/lego"
    with pytest.raises(Exception, match="data.root is not set"):
        _ = make_cfg(["+sweep=dnerf_grid", "data.name=lego"]).data.path


def test_parallel_jobs_generate_the_embedded_scene_once_without_clobbering(tmp_path):
    """Sweep jobs started together all need the procedural scene: each generates into its own
    folder and the first complete one is renamed into place (found by the submitit sweep test)."""
    from concurrent.futures import ThreadPoolExecutor

    from stdr.data.procedural import SceneOptions, embedded_scene
    opt = SceneOptions(resolution=16, n_train=6, n_val=1, n_test=2)
    with ThreadPoolExecutor(4) as ex:
        paths = list(ex.map(lambda _: embedded_scene(tmp_path, opt), range(4)))
    assert len(set(paths)) == 1 and (paths[0] / "generator.json").is_file()
    assert len(list((paths[0] / "train").glob("*.png"))) == 6
    assert [p.name for p in tmp_path.iterdir()] == [paths[0].name]  # no temporary folders left
