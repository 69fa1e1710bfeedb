"""Sweeps on Hydra's multirun with real launchers (joblib, submitit_local, and slurm on a real
one-node cluster), failure reporting, skipping finished runs."""
import json
import os
import subprocess
import sys

import pytest
from omegaconf import OmegaConf

from stdr.baselines import BASELINES
from stdr.testing import make_cfg
import shutil
import time
from pathlib import Path
import torch
from stdr.io.checkpoint import load_checkpoint
from stdr.testing import TINY_SCENE


def _sweep(tmp_path, *overrides, timeout=900, rc=0):
    """The sweep's output; `rc`: its exit code (1 when a job failed)."""
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    cmd = [sys.executable, "-m", "stdr.cli.train", "-m", "+sweep=embedded_smoke", f"hydra.sweep.dir={tmp_path / 'sw'}",
           f"data.cache_dir={tmp_path / 'cache'}", "experiment=embedded_deform", *overrides]
    p = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=timeout, env=env)
    assert p.returncode == rc, p.stdout[-3000:] + p.stderr[-3000:]
    return p.stdout + p.stderr


@pytest.mark.slow
def test_joblib_sweep_runs_every_job_reports_failures_and_skips_finished_runs(tmp_path):
    sub = "hydra.sweep.subdir=${name}/${data.eval_split}/s${seed}"  # a run folder per job
    out = _sweep(tmp_path, "hydra/launcher=local", "seed=0,1", "data.eval_split=test,bogus", sub, rc=1)
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


# ---------------------------------------------------------------- a real Slurm cluster
# The slurm launcher on a real one-node Slurm cluster (scripts/slurm_cluster.py starts munged,
# slurmctld and slurmd in a temporary folder; with SLURM_CONF set, that cluster is used instead;
# STDR_SLURM_PARTITION names its partition). Through the project's own commands: a sweep and its
# table, a job requeued mid-run, a run longer than its job's time limit, and scancel of a sweep.
# Without slurm-wlm and munge (or root for the test cluster) the tests skip with the reason.
#
# The test cluster's job credentials expire after 15 s, so a requeued job starts again that
# soon (Slurm's default is two minutes).
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))
import slurm_cluster  # noqa: E402


BASE = [*TINY_SCENE, "device=cpu", "model.init_num=300", "eval.lpips=false", "train.progress=false",
        "eval.save_images=false", "train.image_every=0", "eval.fps_repeats=1", "eval.fps_warmup=0",
        "baseline.warmup=10", "train.eval_at_warmup_end=false", "train.threads=1", "train.log_every=100"]
#: a run of about half a minute of training on one core: longer than what a 1-minute job has
#: left after its start-up and before Slurm's warning signal
LONG = ["optim.iterations=2500", "train.checkpoint_every=100"]


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    """(environment with SLURM_CONF, partition)."""
    if os.environ.get("SLURM_CONF"):
        yield dict(os.environ), os.environ.get("STDR_SLURM_PARTITION", "debug")
        return
    why = slurm_cluster.missing()
    if why and os.environ.get("CI") == "true":
        pytest.fail(f"CI runs the Slurm tests, but: {why} (.ci/run installs slurm-wlm and munge)")
    if why:
        pytest.skip(f"no Slurm cluster: {why}")
    d = tmp_path_factory.mktemp("slurm")
    conf = slurm_cluster.start(d)
    try:
        yield {**os.environ, "SLURM_CONF": str(conf)}, "debug"
    finally:
        slurm_cluster.stop(d)


def launcher(partition: str, *extra: str) -> list[str]:
    return ["hydra/launcher=slurm", f"hydra.launcher.partition={partition}", "hydra.launcher.gpus_per_task=null",
            "hydra.launcher.cpus_per_task=1", "hydra.launcher.mem_gb=1", *extra]


def sweep_cmd(tmp: Path, sweep: Path, *overrides: str) -> list[str]:
    return [sys.executable, "-m", "stdr.cli.train", "-m", *BASE, f"data.cache_dir={tmp / 'cache'}",
            f"hydra.sweep.dir={sweep}", *overrides]


def job_ids(sweep: Path) -> list[str]:
    """The Slurm job ids of a sweep: <id> for a single job, <array id>_<task> for an array."""
    return sorted(p.name for p in (sweep / ".submitit").iterdir() if p.is_dir() and p.name.replace("_", "").isdigit())


def _squeue(env) -> list[list[str]]:
    r = subprocess.run(["squeue", "-h", "-o", "%i %T %r"], capture_output=True, text=True, env=env)
    return [ln.split() for ln in r.stdout.splitlines() if ln.strip()]


def _tensors(ck: dict) -> dict[str, torch.Tensor]:
    out = {}

    def walk(node, prefix):
        if torch.is_tensor(node):
            out[prefix] = node
        elif isinstance(node, dict):
            for k, v in node.items():
                walk(v, f"{prefix}.{k}")
    walk(ck["model"], "model")
    return out


def assert_bit_identical(run: Path, reference: Path) -> None:
    a, b = load_checkpoint(run / "checkpoints" / "last.pt"), load_checkpoint(reference / "checkpoints" / "last.pt")
    assert a["model"]["step"] == b["model"]["step"]
    ta, tb = _tensors(a), _tensors(b)
    assert ta.keys() == tb.keys() and ta
    for k in ta:
        assert torch.equal(ta[k], tb[k]), k


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """The LONG run trained without interruption, in this process's machine, one thread."""
    tmp = tmp_path_factory.mktemp("ref")
    r = subprocess.run([sys.executable, "-m", "stdr.cli.train", *BASE, *LONG, f"data.cache_dir={tmp / 'cache'}",
                        f"hydra.run.dir={tmp / 'run'}"], capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-3000:]
    return tmp / "run"


@pytest.mark.slurm
def test_a_sweep_through_the_slurm_launcher_and_its_table(cluster, tmp_path):
    env, part = cluster
    sweep = tmp_path / "sweep"
    t0 = time.time()
    r = subprocess.run(sweep_cmd(tmp_path, sweep, "optim.iterations=20", "seed=0,1", *launcher(part)),
                       capture_output=True, text=True, timeout=600, env=env)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    assert "sweep finished, no failed jobs" in r.stdout
    print(f"[slurm] sweep jobs {job_ids(sweep)}: {time.time() - t0:.0f} s")
    for i in (0, 1):
        assert json.loads((sweep / str(i) / "metrics.json").read_text())["test"]["iterations"] == 20
    e = subprocess.run([sys.executable, "-m", "stdr.cli.eval", str(sweep), "reevaluate=false", f"out={tmp_path / 't'}"],
                       capture_output=True, text=True, timeout=300, env=env)
    assert e.returncode == 0, e.stderr[-3000:]
    table = json.loads((tmp_path / "t" / "table.json").read_text())
    assert table["cells"]["deform"]["embedded"]["n_runs"] == 2


def _wait_for(cond, timeout: float, what: str, proc=None) -> None:
    t0 = time.time()
    while not cond():
        if proc is not None and proc.poll() is not None:
            out, err = proc.communicate()
            pytest.fail(f"the sweep ended before {what}: {out[-2000:]} {err[-2000:]}")
        if time.time() - t0 > timeout:
            pytest.fail(f"no {what} in {timeout:.0f} s")
        time.sleep(0.5)


def _finish(proc, env, timeout: float = 900) -> tuple[str, str]:
    """The sweep's output once it ends. The test cluster keeps no accounting, so submitit waits
    for a job that died at its start forever: when the queue has been empty for 30 s, the sweep is
    stopped and the test fails with the controller's log."""
    t0, empty_since = time.time(), None
    while proc.poll() is None:
        if _squeue(env):
            empty_since = None
        elif empty_since is None:
            empty_since = time.time()
        if (empty_since is not None and time.time() - empty_since > 30) or time.time() - t0 > timeout:
            proc.kill()
            log = Path(env["SLURM_CONF"]).with_name("slurmctld.log")
            tail = log.read_text(errors="replace")[-3000:] if log.is_file() else ""
            pytest.fail(f"the sweep waits on jobs the cluster no longer has; slurmctld.log: {tail}")
        time.sleep(1)
    return proc.communicate()


def _job_logs(proc, out: str, err: str, sweep: Path) -> str:
    """The sweep ended with exit 0: its jobs' stdout logs, requeues appended, as one text."""
    assert proc.returncode == 0, out[-3000:] + err[-3000:]
    return "".join(p.read_text(errors="replace") for p in (sweep / ".submitit").rglob("*_log.out"))


def _step(run: Path) -> int:
    try:
        return int(load_checkpoint(run / "checkpoints" / "last.pt")["model"]["step"])
    except Exception:  # noqa: BLE001 - not there yet
        return -1


@pytest.mark.slurm
def test_a_job_requeued_mid_run_resumes_and_ends_bit_identical(cluster, reference, tmp_path):
    env, part = cluster
    sweep = tmp_path / "sweep"
    proc = subprocess.Popen(sweep_cmd(tmp_path, sweep, *LONG, "seed=0", *launcher(part, "hydra.launcher.timeout_min=30")),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    t0 = time.time()
    try:
        _wait_for(lambda: _step(sweep / "0") >= 300, 600, "checkpoint at step 300", proc)
        jid = job_ids(sweep)[0].split("_")[0]
        at = _step(sweep / "0")
        subprocess.run(["scontrol", "requeue", jid], check=True, env=env)
        out, err = _finish(proc, env)
    finally:
        if proc.poll() is None:
            proc.kill()
    logs = _job_logs(proc, out, err, sweep)
    resumed = [int(ln.split("at iteration ")[1].split()[0]) for ln in logs.splitlines() if "resumed from" in ln]
    print(f"[slurm] requeue: job {jid} requeued at checkpoint {at}, resumed at {resumed}, {time.time() - t0:.0f} s")
    assert resumed and resumed[0] >= at, "the job was not requeued, or resumed before its checkpoint"
    assert json.loads((sweep / "0" / "metrics.json").read_text())["test"]["iterations"] == 2500
    assert_bit_identical(sweep / "0", reference)


@pytest.mark.slurm
def test_a_run_longer_than_its_time_limit_checkpoints_at_the_signal_and_finishes_bit_identical(
        cluster, reference, tmp_path):
    env, part = cluster
    sweep = tmp_path / "sweep"
    t0 = time.time()
    proc = subprocess.Popen(sweep_cmd(tmp_path, sweep, *LONG, "seed=0", *launcher(
        part, "hydra.launcher.timeout_min=1", "hydra.launcher.signal_delay_s=20", "hydra.launcher.max_num_timeout=8")),
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    out, err = _finish(proc, env)  # kills the sweep itself when it fails
    logs = _job_logs(proc, out, err, sweep)
    stops = [ln for ln in logs.splitlines() if "stopped at iteration" in ln and "warning signal" in ln]
    resumes = [ln for ln in logs.splitlines() if "resumed from" in ln]
    print(f"[slurm] time limit: jobs {job_ids(sweep)}, {len(stops)} stop(s) at the signal ({stops}), "
          f"{len(resumes)} resume(s), {time.time() - t0:.0f} s")
    assert stops and len(resumes) >= len(stops)
    # each stop at the signal is resumed from the step it checkpointed: nothing is trained twice (a
    # signal that comes before the loop or after it is submitit's alone: it requeues from the last checkpoint)
    at_stop = [int(s.split("stopped at iteration ")[1].split()[0]) for s in stops]
    at_resume = [int(s.split("at iteration ")[1].split()[0]) for s in resumes]
    assert all(step in at_resume for step in at_stop), (at_stop, at_resume)
    assert json.loads((sweep / "0" / "metrics.json").read_text())["test"]["iterations"] == 2500
    assert_bit_identical(sweep / "0", reference)


@pytest.mark.slurm
def test_scancel_of_a_sweep_leaves_finished_runs_intact_and_the_others_resumable(cluster, tmp_path):
    env, part = cluster
    sweep = tmp_path / "sweep"
    proc = subprocess.Popen(sweep_cmd(tmp_path, sweep, "train.checkpoint_every=50", "optim.iterations=20,3000",
                                      *launcher(part, "hydra.launcher.array_parallelism=1")),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        _wait_for(lambda: (sweep / "0" / "metrics.json").is_file() and _step(sweep / "1") >= 100, 600,
                  "a finished first run and a checkpoint of the second", proc)
        finished = {p.name: p.read_bytes() for p in (sweep / "0").iterdir() if p.is_file()}
        array = job_ids(sweep)[0].split("_")[0]
        subprocess.run(["scancel", array], check=True, env=env)
        _wait_for(lambda: not _squeue(env), 120, "the cancelled jobs gone")
        # the test cluster keeps no accounting (sacct), so submitit cannot see the jobs' end and the
        # launching command waits on: stopped here as its user would (Ctrl-C)
        proc.terminate()
        proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    print(f"[slurm] scancel: array {array}, second run stopped at checkpoint {_step(sweep / '1')}")
    assert {p.name: p.read_bytes() for p in (sweep / "0").iterdir() if p.is_file()} == finished
    assert json.loads((sweep / "0" / "metrics.json").read_text())["test"]["iterations"] == 20
    step = _step(sweep / "1")
    assert 100 <= step < 3000 and not (sweep / "1" / "metrics.json").exists()
    assert not [p for p in (sweep / "1").rglob("*") if ".tmp" in p.name]
    # scancel's SIGTERM reached training beside submitit's handler: the step it stopped at is checkpointed
    logs = "".join(p.read_text(errors="replace") for p in (sweep / ".submitit").rglob("*_log.out"))
    assert f"[stdr] stopped at iteration {step} of 3000 (SIGTERM)" in logs, logs[-3000:]
    # the unfinished run resumes where it was cancelled (the same command on this machine)
    r = subprocess.run([sys.executable, "-m", "stdr.cli.train", *BASE, "train.checkpoint_every=50",
                        "optim.iterations=3000", f"data.cache_dir={tmp_path / 'cache'}", f"hydra.run.dir={sweep / '1'}",
                        f"train.stop_at={step + 10}"], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    assert f"resumed from {sweep / '1' / 'checkpoints' / 'last.pt'} at iteration {step}" in r.stdout


@pytest.mark.slurm
def test_the_test_cluster_script_needs_its_tools_and_says_so(monkeypatch):
    monkeypatch.setattr(shutil, "which", lambda name: None)
    monkeypatch.setattr(slurm_cluster, "TOOLS", ("no-such-slurm-tool",))
    assert "no-such-slurm-tool not installed (apt-get install slurm-wlm munge)" in slurm_cluster.missing()


def test_a_sweep_of_very_many_runs_is_announced_before_hydra_composes_them():
    from stdr.cli.train import BIG_SWEEP, sweep_size
    assert sweep_size(["-m", "seed=range(0,1000000)", "data.max_width=100,200", "train.stop_at=3"]) == (
        2_000_000, ["seed=range(0,1000000) (1,000,000)", "data.max_width=100,200 (2)"])
    assert sweep_size(["-m", "seed=0,1,2"])[0] == 3 <= BIG_SWEEP
    # the real command says it at once (then it is stopped: composing a million jobs takes minutes)
    p = subprocess.Popen([sys.executable, "-m", "stdr.cli.train", "-m", "seed=range(0,1000000)",
                          "hydra.sweep.dir=/nonexistent/never"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        first = p.stdout.readline()
    finally:
        p.kill()
        p.wait()
    assert first.startswith("[stdr] this sweep is 1,000,000 runs (seed=range(0,1000000) (1,000,000))"), first
