"""stdr-tool queue: a grid of runs, several at once, within a time budget, on the CPU at toy sizes
(the same code a lent GPU runs with device=cuda). And scripts/idle_run.py, which a timed run of a
study goes through: the command's CPU time against the whole machine's, its exit status, and the
machine's lock that makes timed runs take turns."""
import fcntl
import json
import subprocess
import sys
import tarfile
from pathlib import Path

import pytest

from helpers import load_script
from stdr.testing import TINY_SCENE
from stdr.tools import queue_tool
from stdr.tools import runqueue as qm


def _toy(tmp_path, iterations=20):
    return [*TINY_SCENE, f"data.cache_dir={tmp_path / 'cache'}", "device=cpu", "model.init_num=300", "eval.lpips=false",
            "eval.save_images=false", "train.image_every=0", f"optim.iterations={iterations}", "baseline.warmup=10",
            "eval.fps_repeats=1"]


def test_a_grid_runs_two_at_a_time_and_comes_back_in_one_archive(tmp_path):
    q = qm.plan(["embedded_deform", "embedded_4dgs"], [], [0, 1], _toy(tmp_path), est_s=5)
    assert [r.id for r in q.runs] == ["embedded_deform__default__s0", "embedded_4dgs__default__s0",
                                      "embedded_deform__default__s1", "embedded_4dgs__default__s1"]
    q.save(tmp_path / "q.json")
    proc = subprocess.run([sys.executable, "-m", "stdr.cli.tool", "queue", "run", str(tmp_path / "q.json"),
                           "--work", str(tmp_path / "work"), "--out", str(tmp_path / "out"), "--concurrent", "2",
                           "--budget", "600", "--cores", "2"], capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    state = qm.Queue.load(tmp_path / "out" / "queue.json")
    assert state.counts()["done"] == 4 and all(r.tries == 1 and r.seconds > 0 for r in state.runs)
    call = state.calls[-1]
    assert call["concurrent"] == 2 and call["threads_each"] == 1 and sorted(call["finished"]) == sorted(r.id for r in q.runs)
    assert call["sweep_exit"] == 0 and sorted(call["started"]) == sorted(r.id for r in q.runs)
    # each run is a stdr-train of its own, in WORK/<id>, with the call's threads and deadline
    first = [(tmp_path / "work" / r.id / "stdout.log").read_text().splitlines()[0] for r in q.runs]
    assert all("train.threads=1" in c and "train.deadline=" in c and f"hydra.run.dir={tmp_path / 'work' / r.id}" in c
               for c, r in zip(first, q.runs))
    with tarfile.open(tmp_path / "out" / "runs.tgz") as tar:
        names = set(tar.getnames())
        m = json.loads(tar.extractfile("embedded_4dgs__default__s1/metrics.json").read())
        tail = tar.extractfile("embedded_4dgs__default__s1/log_tail.txt").read().decode()
    assert {f"{r.id}/{f}" for r in q.runs for f in qm.FILES} <= names
    assert m["test"]["psnr"] > 5 and "[stdr] metrics:" in tail
    assert "sweep finished" in (tmp_path / "out" / "queue_log_tail.txt").read_text()
    # the GPU table takes the archive as it comes back: every member <run id>/<file>
    gpu_table = load_script(Path(__file__).resolve().parents[1] / "scripts" / "gpu_table.py", "gpu_table")
    assert sorted(gpu_table.add(tmp_path / "out" / "runs.tgz", tmp_path / "table")) != []
    assert len(list((tmp_path / "table" / "runs").glob("*/metrics.json"))) == 4
    # the next call finds nothing to do and packs the same runs again
    again = qm.Queue.load(tmp_path / "q.json")
    assert qm.execute(again, tmp_path / "work", 2, 60)["started"] == []


def test_the_deadline_starts_nothing_that_would_not_fit_and_stops_what_runs(tmp_path):
    # 60 s: the first run's start-up (a Python with torch, on a machine the other tests load) must
    # fit before its start-by of deadline - 1 s; 24 s did not always (a loaded 2-core CI machine)
    q = qm.plan(["embedded_deform"], [], [0, 1], _toy(tmp_path, iterations=100_000), est_s=1)
    q.runs[1].est_s = 10_000  # its estimate does not fit the budget: never started
    rec = qm.execute(q, tmp_path / "work", 2, budget_s=60, log=lambda m: None)
    assert rec["started"] == [q.runs[0].id] and rec["finished"] == [] and rec["sweep_exit"] == 0
    assert rec["wall_s"] < 60 + 20  # the run stopped itself at the deadline: the sweep was not killed
    assert [r.state for r in q.runs] == ["pending", "pending"] and q.runs[0].tries == 1 and q.runs[1].tries == 0
    run, skipped = (tmp_path / "work" / r.id for r in q.runs)
    assert not (run / "metrics.json").exists() and (run / "checkpoints" / "last.pt").is_file()
    assert "(train.deadline); the same command without train.deadline resumes" in (run / "stdout.log").read_text()
    assert "not started, train.start_by passed" in (skipped / "stdout.log").read_text()
    assert not (skipped / "config.yaml").exists()


def test_a_failing_run_is_marked_with_its_log_and_the_others_go_on(tmp_path):
    q = qm.plan(["embedded_deform"], [], [0], _toy(tmp_path), est_s=1)
    q.runs.insert(0, qm.Run("nested/broken", ["experiment=embedded_deform", "optim.no_such_key=1"], 1))
    q.runs.insert(1, qm.Run("no_data", ["experiment=embedded_deform", "data.format=dnerf",
                                        f"data.path={tmp_path / 'no_such_scene'}"], 1))
    rec = qm.execute(q, tmp_path / "work", 1, budget_s=300, log=lambda m: None)
    assert [r.state for r in q.runs] == ["failed", "failed", "done"] and rec["failed"] == ["nested/broken", "no_data"]
    assert "no_such_key" in q.runs[0].error  # its config does not compose: never launched
    assert "no_such_scene" in q.runs[1].error and "stdout.log" in q.runs[1].error
    assert "no_such_scene" in (tmp_path / "work" / "no_data" / "stdout.log").read_text()


def test_plan_never_overwrites_a_queue_and_ids_are_unique(tmp_path):
    (tmp_path / "q.json").write_text("{}")
    with pytest.raises(SystemExit, match="exists"):
        queue_tool.main(["plan", str(tmp_path / "q.json"), "--experiments", "embedded_deform", "--est-seconds", "1"])
    with pytest.raises(ValueError, match="share an id"):
        qm.plan(["embedded_deform"], [tmp_path / "a" / "x", tmp_path / "b" / "x"], [0], [], 1)


def test_variants_are_runs_of_their_own_side_by_side(tmp_path):
    v = [qm.parse_variant("torch:optim.fused_loss=false"), qm.parse_variant("fast:optim.fused_loss=true,train.guard.compiled=true")]
    q = qm.plan(["dnerf_deform"], [tmp_path / "jumpingjacks"], [0], ["budget=gpu"], 400, v)
    assert [r.id for r in q.runs] == ["dnerf_deform__jumpingjacks__s0__torch", "dnerf_deform__jumpingjacks__s0__fast"]
    assert q.runs[1].overrides[-3:] == ["budget=gpu", "optim.fused_loss=true", "train.guard.compiled=true"]
    with pytest.raises(ValueError, match="LABEL:KEY=VALUE"):
        qm.parse_variant("optim.fused_loss=true")


def test_plan_from_the_command_line_takes_the_overrides_after_the_dashes(tmp_path, capsys):
    queue_tool.main(["plan", str(tmp_path / "q.json"), "--experiments", "dnerf_deform", "--scenes", str(tmp_path / "s1"),
             "--seeds", "0", "1", "--est-seconds", "300", "--variants", "a:seed=0", "--", "budget=gpu", "device=cuda"])
    q = qm.Queue.load(tmp_path / "q.json")
    assert len(q.runs) == 2 and all(r.overrides[-3:-1] == ["budget=gpu", "device=cuda"] for r in q.runs)
    assert "2 runs planned" in capsys.readouterr().out


FAKE_APP = """
import json, os, time
from pathlib import Path
import hydra
from hydra.core.config_store import ConfigStore
from hydra.core.hydra_config import HydraConfig

ConfigStore.instance().store(name="fake", node={"experiment": "", "seed": 0, "stamps": "", "train": {
    "threads": 0, "progress": True, "deadline": None, "start_by": None}})


@hydra.main(version_base=None, config_path=None, config_name="fake")
def main(cfg):
    t0 = time.time()
    time.sleep(8)
    d = Path(HydraConfig.get().runtime.output_dir)
    (d / "config.yaml").write_text("{}")
    (d / "metrics.json").write_text("{}")
    Path(cfg.stamps, d.name).write_text(json.dumps([t0, time.time(), os.environ["OMP_NUM_THREADS"],
                                                    cfg.train.threads, os.getpid()]))


main()
"""


def test_sixteen_runs_at_once_one_thread_each(tmp_path, monkeypatch):
    """A lent GPU machine has 16 cores: `--concurrent 16` keeps 16 runs going at once, one thread
    each. The runs here are jobs of a stand-in Hydra app (it records when it ran and writes
    metrics.json) on the same sweeper and launcher, so the test measures the scheduling, not training."""
    stamp = tmp_path / "stamps"
    stamp.mkdir()
    (tmp_path / "fake_app.py").write_text(FAKE_APP)
    monkeypatch.setattr(qm, "APP", [sys.executable, str(tmp_path / "fake_app.py")])
    q = qm.plan(["embedded_deform"], [], list(range(20)), [f"stamps={stamp}"], est_s=1)
    rec = qm.execute(q, tmp_path / "work", 16, 120, cores=16, log=lambda m: None)
    assert rec["threads_each"] == 1 and len(rec["finished"]) == 20 and rec["failed"] == [], rec
    spans = [json.loads(p.read_text()) for p in stamp.iterdir()]
    assert all(s[2] == "1" and s[3] == 1 for s in spans)
    # the most runs alive at one moment: every start checked against every span
    overlap = max(sum(a[0] <= s[0] < a[1] for a in spans) for s in spans)
    assert overlap == 16, overlap


def test_a_plan_by_experiment_puts_the_first_experiments_on_every_scene_first(tmp_path):
    """--order experiment: the table's main rows (deform +- STDR) on all four scenes come before
    the next experiments; relative scene paths are kept as given (read where the queue runs)."""
    scenes = [f"build/gpucarry/{s}" for s in ("bouncingballs", "hellwarrior", "jumpingjacks", "standup")]
    exps = ["dnerf_deform", "dnerf_deform_stdr", "dnerf_scgs", "dnerf_scgs_stdr"]
    q = qm.plan(exps, scenes, [0], ["budget=gpu"], est_s=400, order="experiment")
    assert [r.id.split("__")[0] for r in q.runs[:8]] == ["dnerf_deform"] * 4 + ["dnerf_deform_stdr"] * 4
    assert [r.id.split("__")[1] for r in q.runs[:4]] == ["bouncingballs", "hellwarrior", "jumpingjacks", "standup"]
    assert "data.path=build/gpucarry/bouncingballs" in q.runs[0].overrides
    by_scene = qm.plan(exps, scenes, [0], [], est_s=400)
    assert [r.id.split("__")[0] for r in by_scene.runs[:4]] == exps  # the default: a scene's methods together
    with pytest.raises(ValueError, match="--order"):
        qm.plan(exps, scenes, [0], [], est_s=400, order="seed")


FAKE_RUN = """
import json, os, sys, time
from pathlib import Path
run = Path(next(a for a in sys.argv if a.startswith("hydra.run.dir=")).split("=", 1)[1])
run.mkdir(parents=True, exist_ok=True)
stamps = Path(sys.argv[1])
seen = stamps / (run.relative_to(run.parents[2]).as_posix().replace("/", "__"))
first = not seen.exists()
seen.write_text(seen.read_text() + "x" if seen.exists() else "x")
(run / "config.yaml").write_text("{}")
(run / "metrics.json").write_text(json.dumps({"test": {"psnr": 20.0, "code": {"commit": os.environ.get("FAKE_COMMIT", "")}}}))
# the first try of a run whose scene is 'b' shared the machine
(run / "load.json").write_text(json.dumps({"idle": not (first and run.parent.name == "b")}))
"""


def test_one_call_at_a_time_on_a_work_folder(tmp_path):
    """A second call on the same WORK would train the same runs into the same folders: refused."""
    import fcntl
    work = tmp_path / "work"
    work.mkdir()
    q = qm.plan(["embedded_deform"], [], [0], [], est_s=1)
    with open(work / ".queue.lock", "w") as held:  # a call running on WORK holds it
        fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)
        with pytest.raises(qm.QueueBusy, match="another queue call is running"):
            qm.execute(q, work, 1, 60, log=lambda m: None)
        q.save(tmp_path / "q.json")
        with pytest.raises(SystemExit, match="another queue call is running"):
            queue_tool.main(["run", str(tmp_path / "q.json"), "--work", str(work), "--out", str(tmp_path / "out")])
    assert q.runs[0].state == "pending" and q.runs[0].tries == 0


def test_a_pause_file_holds_the_next_run_and_a_command_replaces_stdr_train(tmp_path):
    """WORK/pause.<name> holds a job before it starts its run; `--command` runs another program in
    place of stdr-train (here one that only writes the run's files), with {run_dir} filled in."""
    import time
    (tmp_path / "fake_run.py").write_text(FAKE_RUN)
    stamps = tmp_path / "stamps"
    stamps.mkdir()
    work = tmp_path / "work"
    work.mkdir()
    (work / "pause.study").write_text("")
    q = qm.plan(["embedded_deform"], [tmp_path / "a"], [0], [], est_s=1)
    q.save(tmp_path / "q.json")
    cmd = f"{sys.executable} {tmp_path / 'fake_run.py'} {stamps} --marker {{run_dir}}/m"
    proc = subprocess.Popen([sys.executable, "-m", "stdr.cli.tool", "queue", "run", str(tmp_path / "q.json"), "--work",
                             str(work), "--out", str(tmp_path / "out"), "--budget", "300", "--command", cmd],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    log = work / "queue.log"
    deadline = time.time() + 120
    while "paused (pause.study)" not in (log.read_text(errors="replace") if log.exists() else ""):
        assert proc.poll() is None and time.time() < deadline, proc.communicate()[0]
        time.sleep(0.5)
    time.sleep(1.0)
    assert not any(stamps.iterdir())  # held: nothing ran
    (work / "pause.study").unlink()
    out = proc.communicate(timeout=120)[0]
    assert proc.returncode == 0, out
    state = qm.Queue.load(tmp_path / "q.json")
    assert [r.state for r in state.runs] == ["done"], out
    first = (work / q.runs[0].id / "stdout.log").read_text().splitlines()[0]
    assert f"--marker {work / q.runs[0].id}/m" in first and "experiment=embedded_deform" in first


def test_the_headline_study_records_idle_runs_and_runs_a_shared_one_again(tmp_path, monkeypatch):
    """studies/headline.py on the queue, with a stand-in for the timed stdr-train: every run of the
    seed is recorded; the one that shared the machine is run again in the next sweep and then recorded."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    import studies.headline as h
    (tmp_path / "fake_run.py").write_text(FAKE_RUN)
    stamps = tmp_path / "stamps"
    stamps.mkdir()
    root = tmp_path / "dnerf"
    for s in ("a", "b"):
        (root / s).mkdir(parents=True)
        (root / s / "transforms_train.json").write_text("{}")
    monkeypatch.setattr(h, "SCENES", ("a", "b"))
    monkeypatch.setattr(h, "EXPERIMENTS", ("dnerf_deform", "dnerf_deform_stdr"))
    monkeypatch.setattr(h, "command", lambda code: [sys.executable, str(tmp_path / "fake_run.py"), str(stamps)])
    monkeypatch.setenv("FAKE_COMMIT", h.checkout_commit(h.ROOT) or "")  # trained by the --code checkout (this one)
    records = tmp_path / "records"
    assert h.main([str(root), "--work", str(tmp_path / "work"), "--records", str(records), "--seeds", "7",
                   "--no-results"]) == 0
    assert sorted(p.parent.relative_to(records).as_posix() for p in records.rglob("metrics.json")) == sorted(
        f"{e}/{s}/s7" for s in ("a", "b") for e in ("dnerf_deform", "dnerf_deform_stdr"))
    tries = {p.name: len(p.read_text()) for p in stamps.iterdir()}
    assert tries == {f"{e}__{s}__s7": 1 if s == "a" else 2 for s in ("a", "b") for e in ("dnerf_deform", "dnerf_deform_stdr")}
    assert all(json.loads((p.parent / "load.json").read_text())["idle"] for p in records.rglob("metrics.json"))
    assert h.plan_seed(root, 7, records).runs == []  # resumable: nothing left to plan


def test_the_headline_study_records_no_run_trained_by_other_code_than_its_checkout(tmp_path, monkeypatch, capsys):
    """A run whose metrics.json names another commit than the --code checkout's (its stdr imported
    from elsewhere) is not recorded: it fails, named, and the call says so in its exit status."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    import studies.headline as h
    if h.checkout_commit(h.ROOT) is None:
        pytest.skip("this copy of the project is not a git checkout: no commit to check against")
    (tmp_path / "fake_run.py").write_text(FAKE_RUN)
    (tmp_path / "stamps").mkdir()
    root = tmp_path / "dnerf"
    (root / "a").mkdir(parents=True)
    (root / "a" / "transforms_train.json").write_text("{}")
    monkeypatch.setattr(h, "SCENES", ("a",))
    monkeypatch.setattr(h, "EXPERIMENTS", ("dnerf_deform",))
    monkeypatch.setattr(h, "command", lambda code: [sys.executable, str(tmp_path / "fake_run.py"), str(tmp_path / "stamps")])
    monkeypatch.setenv("FAKE_COMMIT", "0" * 40)
    records = tmp_path / "records"
    assert h.main([str(root), "--work", str(tmp_path / "work"), "--records", str(records), "--seeds", "7",
                   "--no-results"]) == 1
    assert not list(records.rglob("metrics.json"))
    assert "trained by code 0000000, not the --code checkout's" in capsys.readouterr().err


def test_the_headline_study_runs_the_code_checkouts_stdr_whatever_the_working_directory(tmp_path):
    """The command imports stdr from --code even when started from another checkout's folder
    (`python -m` would put that folder first on the module path)."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    import studies.headline as h
    code = tmp_path / "frozen"
    (code / "stdr" / "cli").mkdir(parents=True)
    (code / "scripts").mkdir()
    (code / "scripts" / "run.sh").write_text('#!/usr/bin/env bash\nexec "$@"\n')
    (code / "scripts" / "run.sh").chmod(0o755)
    for f in ("stdr/__init__.py", "stdr/cli/__init__.py"):
        (code / f).write_text("")
    (code / "stdr" / "cli" / "train.py").write_text("import stdr, sys; print('FROM', stdr.__file__)")
    cmd = [a.replace(sys.executable, sys.executable) for a in h.command(code)]
    cmd = cmd[cmd.index("--") + 1:]  # the training command, without the idle check around it
    cmd[cmd.index("python")] = sys.executable
    out = subprocess.run(cmd, cwd=Path(__file__).resolve().parents[1], capture_output=True, text=True, check=True).stdout
    assert f"FROM {code / 'stdr' / '__init__.py'}" in out


def test_run_one_trains_legs_in_one_folder_and_raises_on_failure(tmp_path):
    """A study's trunk and branch legs: run_one to train.stop_at (pending, with a checkpoint), then
    on to the end in the same folder (done, resumed there); a run that fails raises with its error."""
    run = tmp_path / "work" / "trunk"
    first = qm.run_one([*_toy(tmp_path, iterations=30), "experiment=embedded_deform", "train.stop_at=12"], run,
                       log=lambda m: None)
    assert first.state == "pending" and (run / "checkpoints" / "last.pt").is_file() and not (run / "metrics.json").exists()
    done = qm.run_one([*_toy(tmp_path, iterations=30), "experiment=embedded_deform"], run, log=lambda m: None)
    out = (run / "stdout.log").read_text()
    assert done.state == "done" and "resumed from" in out and "at iteration 12" in out
    with pytest.raises(RuntimeError, match="no_such_key"):
        qm.run_one(["experiment=embedded_deform", "optim.no_such_key=1"], tmp_path / "work" / "bad", log=lambda m: None)


def test_stopping_the_queue_stops_its_runs(tmp_path):
    """SIGTERM to `stdr-tool queue run` (a job's time limit, Ctrl-C) ends the sweep and the runs it
    started: none goes on orphaned, writing into WORK after the call has ended."""
    import signal
    import time
    q = qm.plan(["embedded_deform"], [], [0], [], est_s=1)
    q.save(tmp_path / "q.json")
    work = tmp_path / "work"
    started = work / q.runs[0].id / "started"  # the run's own command line names it (the queue's has {run_dir})
    cmd = (f"{sys.executable} -c 'import pathlib, sys, time; pathlib.Path(sys.argv[1]).touch(); time.sleep(120)' "
           "{run_dir}/started")
    proc = subprocess.Popen([sys.executable, "-m", "stdr.cli.tool", "queue", "run", str(tmp_path / "q.json"), "--work",
                             str(work), "--out", str(tmp_path / "out"), "--budget", "300", "--command", cmd],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)

    def alive():
        return subprocess.run(["pgrep", "-f", str(started)], capture_output=True).returncode == 0
    deadline = time.time() + 120
    while not started.exists():
        assert proc.poll() is None and time.time() < deadline, proc.communicate()[0]
        time.sleep(0.5)
    assert alive()
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(timeout=60) == 128 + signal.SIGTERM
    time.sleep(1)
    assert not alive()


def test_the_calibration_chooses_the_level_that_finishes_the_most_runs_in_the_time_left():
    """Made-up slices: a run alone takes 100 s; 4 at once make each 2x slower, 8 at once 5x, 16 at
    once 12.5x. With the 10 % margin a run takes 110, 220, 550 and 1375 s. In 600 s: 1 at once
    finishes 5 runs, 4 at once 8 (two waves), 8 at once 8 (one wave), 16 at once none. A tie goes
    to the larger level."""
    from stdr.tools.concurrency import choose

    def levels(**extra):
        rates = {1: 10.0, 4: 5.0, 8: 2.0, 16: 0.8}
        return [{"n": n, "per_run_steps_per_s": r, "steps_per_s": r * n, "failed": 0, **extra.get(str(n), {})}
                for n, r in rates.items()]

    lv = levels()
    pick = choose(lv, left_s=600, alone_s=100, pending=32)
    assert pick["chosen"] == 8 and pick["est_run_s"] == pytest.approx(550)
    assert [x["runs_in_time"] for x in lv] == [5, 8, 8, 0]
    assert [x["slowdown"] for x in lv] == pytest.approx([1.0, 2.0, 5.0, 12.5])
    # fewer runs pending than the waves would take: 1 at once runs them all as well as 8 at once would
    assert choose(levels(), left_s=600, alone_s=100, pending=3)["chosen"] == 8
    # 300 s left: only 1 at once (2 waves) and 4 at once (1 wave) finish anything; 4 > 2
    assert choose(levels(), left_s=300, alone_s=100, pending=32)["chosen"] == 4
    # nothing fits: no chunk, and the record says why
    none = choose(levels(), left_s=100, alone_s=100, pending=32)
    assert none["chosen"] is None and "no level finishes a run in the 100 s left" in none["why"]
    # a level where a copy failed (e.g. out of memory) is never chosen, however fast the others were
    failed = levels(**{"8": {"failed": 1}})
    assert choose(failed, left_s=600, alone_s=100, pending=32)["chosen"] == 4 and failed[2]["runs_in_time"] == 0
    with pytest.raises(ValueError, match="needs level 1"):
        choose([lv[1]], left_s=600, alone_s=100, pending=32)
    # level 1 measured but its copy reached no step within the slice (a cold start): named, with the fix
    with pytest.raises(ValueError, match="reached no training step within --slice: give a longer slice"):
        choose(levels(**{"1": {"per_run_steps_per_s": None, "steps_per_s": None}}), left_s=600, alone_s=100, pending=32)


def test_a_calibrated_call_measures_each_level_then_runs_the_chunk_at_the_chosen_one(tmp_path, capsys):
    """`queue run --calibrate 1 2`: copies of the next run train at each level in WORK/calibrate
    (gone after), their steps/s and the choice go into the call's entry of the queue file, and the
    chunk runs at the chosen level. A run alone is said to take 2 s, so both levels finish both
    runs in the budget and the tie goes to 2 at once."""
    q = qm.plan(["embedded_deform"], [], [0, 1], _toy(tmp_path), est_s=5)
    q.save(tmp_path / "q.json")
    base = ["run", str(tmp_path / "q.json"), "--work", str(tmp_path / "work"), "--out", str(tmp_path / "out")]
    with pytest.raises(SystemExit, match="not both"):
        queue_tool.main([*base, "--concurrent", "4", "--calibrate", "1", "2"])
    with pytest.raises(SystemExit, match="1 among them"):
        queue_tool.main([*base, "--calibrate", "2", "4"])
    assert not (tmp_path / "work" / "calibrate").exists() and qm.Queue.load(tmp_path / "q.json").calls == []
    # a long slice: the copies end at their 20 steps anyway, and a first run that builds the extension still fits
    queue_tool.main([*base, "--calibrate", "1", "2", "--slice", "300", "--alone-seconds", "2", "--budget", "900",
                     "--cores", "2"])
    state = qm.Queue.load(tmp_path / "out" / "queue.json")
    assert state.counts()["done"] == 2 and [r.est_s for r in state.runs] == [5, 5]  # the plan's estimates kept
    call = state.calls[-1]
    cal = call["calibration"]
    assert [(lv["n"], lv["copies"], lv["failed"]) for lv in cal["levels"]] == [(1, 1, 0), (2, 2, 0)]
    assert all(lv["steps_per_s"] > 0 for lv in cal["levels"]) and cal["levels"][0]["slowdown"] == 1.0
    assert cal["chosen"] == 2 and call["concurrent"] == 2 and call["threads_each"] == 1 and sorted(call["finished"]) == \
        sorted(r.id for r in q.runs)
    assert call["wall_s"] >= call["chunk_wall_s"] + cal["wall_s"] - 1
    assert not (tmp_path / "work" / "calibrate").exists()
    capsys.readouterr()
    queue_tool.main(["status", str(tmp_path / "out" / "queue.json")])
    out = capsys.readouterr().out
    assert "calibration   2 at once:" in out and "chosen: 2 (2 runs in the" in out and "chunk: 2 runs of one try" in out


@pytest.mark.slow
def test_a_call_runs_one_per_core_by_default_and_gives_the_bits_of_one_at_a_time(tmp_path):
    """Without --concurrent a call on 2 cores trains 2 runs at once, one thread each, and every run
    ends with the checkpoint the same runs reach one at a time on 2 threads (no timing is recorded
    by such a call; a timing study passes --concurrent 1)."""
    import torch
    from stdr.io.checkpoint import load_checkpoint

    assert queue_tool.default_concurrency(2) == 2 and queue_tool.default_concurrency(None) >= 1
    toy = _toy(tmp_path, iterations=30) + ["train.checkpoint_every=0"]
    q = qm.plan(["embedded_deform", "embedded_deform_stdr"], [], [0], toy, est_s=5)
    for mode, extra in (("alone", ["--concurrent", "1"]), ("cores", [])):
        q.save(tmp_path / f"{mode}.json")
        proc = subprocess.run([sys.executable, "-m", "stdr.cli.tool", "queue", "run", str(tmp_path / f"{mode}.json"),
                               "--work", str(tmp_path / mode), "--out", str(tmp_path / f"out_{mode}"), "--budget", "600",
                               "--cores", "2", *extra], capture_output=True, text=True, timeout=900)
        assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    alone, cores = (qm.Queue.load(tmp_path / f"{m}.json").calls[-1] for m in ("alone", "cores"))
    assert (alone["concurrent"], alone["threads_each"]) == (1, 2)
    assert (cores["concurrent"], cores["threads_each"]) == (2, 1) and len(cores["finished"]) == 2
    for r in q.runs:
        a, b = (load_checkpoint(tmp_path / m / r.id / "checkpoints" / "last.pt")["model"] for m in ("alone", "cores"))
        assert a["step"] == b["step"] == 30
        for k, v in a["params"].items():
            assert torch.equal(v, b["params"][k]), (r.id, k)
        for k, v in a["deform"].items():
            assert torch.equal(v, b["deform"][k]), (r.id, k)


def test_a_plan_with_an_unknown_experiment_is_one_line_and_writes_nothing(tmp_path):
    r = subprocess.run([sys.executable, "-m", "stdr.cli.tool", "queue", "plan", str(tmp_path / "q.json"),
                        "--experiments", "dnerf_defrom", "dnerf_deform", "--est-seconds", "5"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr[-2000:]
    assert "no such experiment: dnerf_defrom (did you mean dnerf_deform?)" in r.stderr
    assert not (tmp_path / "q.json").exists()


# ----------------------------------------------------------------- scripts/idle_run.py
IDLE_RUN = Path(__file__).resolve().parents[1] / "scripts" / "idle_run.py"


def test_records_the_commands_cpu_and_the_machines_and_passes_the_exit_status(tmp_path):
    out = tmp_path / "load.json"
    busy = "import time\nt = time.process_time()\nwhile time.process_time() - t < 0.3: pass\nraise SystemExit(3)"
    rc = subprocess.run([sys.executable, str(IDLE_RUN), "--out", str(out), "--lock", str(tmp_path / "lock"), "--",
                         sys.executable, "-c", busy]).returncode
    assert rc == 3
    rec = json.loads(out.read_text())
    assert rec["returncode"] == 3 and rec["child_cpu_s"] >= 0.3  # the command's own CPU time
    assert rec["machine_busy_cpu_s"] >= rec["child_cpu_s"] - 0.05  # the machine's includes it (tick rounding)
    assert rec["foreign_cpu_s"] >= 0 and rec["foreign_share"] == rec["foreign_cpu_s"] / (rec["wall_s"] * rec["cpus"])
    assert rec["idle"] == (rec["foreign_share"] <= rec["max_foreign"])
    assert 0 <= rec["lock_wait_s"] < 5


def test_timed_commands_on_one_machine_take_turns(tmp_path):
    """Two timed commands sharing the machine's lock run one after the other (the second waits,
    and its wait is outside its measurement); `--lock none` does not wait."""
    stamp = "import sys, time\nt0 = time.time()\ntime.sleep(2.0)\nopen(sys.argv[1], 'w').write(f'{t0} {time.time()}')"
    lock = str(tmp_path / "machine.lock")
    procs = [subprocess.Popen([sys.executable, str(IDLE_RUN), "--out", str(tmp_path / f"load{i}.json"), "--lock", lock,
                               "--", sys.executable, "-c", stamp, str(tmp_path / f"span{i}")]) for i in range(2)]
    assert [p.wait(timeout=60) for p in procs] == [0, 0]
    (a0, a1), (b0, b1) = (map(float, (tmp_path / f"span{i}").read_text().split()) for i in range(2))
    assert a1 <= b0 or b1 <= a0  # no overlap
    recs = [json.loads((tmp_path / f"load{i}.json").read_text()) for i in range(2)]
    waiter = max(recs, key=lambda r: r["lock_wait_s"])
    # 2 s each: a Python's start-up on a loaded machine (up to a second or so) stays well under it
    assert waiter["lock_wait_s"] >= 1.0  # it waited for (most of) the other's 2 s
    # and its own time is its command's alone (>= 2 s): with the wait in it, it would be >= wait + 2 s
    assert 2.0 <= waiter["wall_s"] < waiter["lock_wait_s"] + 2.0
    with open(lock, "a") as held:  # a queue holds the machine: `--lock none` still runs at once
        fcntl.flock(held, fcntl.LOCK_EX)
        rc = subprocess.run([sys.executable, str(IDLE_RUN), "--out", str(tmp_path / "free.json"), "--lock", "none", "--",
                             sys.executable, "-c", "pass"], timeout=30).returncode
    assert rc == 0 and json.loads((tmp_path / "free.json").read_text())["lock_wait_s"] == 0


def test_a_missing_command_is_an_error(tmp_path):
    proc = subprocess.run([sys.executable, str(IDLE_RUN), "--out", str(tmp_path / "x.json")], capture_output=True,
                          text=True)
    assert proc.returncode != 0 and "no command" in proc.stderr
