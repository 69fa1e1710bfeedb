"""stdr-tool queue: a grid of runs, several at once, within a time budget, on the CPU at toy sizes
(the same code a lent GPU runs with device=cuda)."""
import json
import subprocess
import sys
import tarfile

import pytest

from stdr.testing import TINY_SCENE
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
    assert state.counts()["done"] == 4 and all(r.tries == 1 for r in state.runs)
    call = state.calls[-1]
    assert call["concurrent"] == 2 and call["threads_each"] == 1 and sorted(call["finished"]) == sorted(r.id for r in q.runs)
    logs = [(tmp_path / "work" / f"{r.id}.log").read_text() for r in q.runs]
    assert all("train.threads=1" in lg.splitlines()[0] for lg in logs)
    with tarfile.open(tmp_path / "out" / "runs.tgz") as tar:
        names = set(tar.getnames())
        m = json.loads(tar.extractfile("embedded_4dgs__default__s1/metrics.json").read())
    assert {f"{r.id}/{f}" for r in q.runs for f in qm.FILES} <= names
    assert m["test"]["psnr"] > 5
    # the next call finds nothing to do and packs the same runs again
    again = qm.Queue.load(tmp_path / "q.json")
    assert qm.execute(again, tmp_path / "work", 2, 60)["started"] == []


def test_the_deadline_starts_nothing_that_would_not_fit_and_stops_what_runs(tmp_path):
    q = qm.plan(["embedded_deform"], [], [0, 1], _toy(tmp_path, iterations=5000), est_s=1)
    q.runs[1].est_s = 10_000  # its estimate does not fit the budget: never started
    rec = qm.execute(q, tmp_path / "work", 2, budget_s=8, log=lambda m: None)
    assert rec["started"] == [q.runs[0].id] and rec["finished"] == []
    assert [r.state for r in q.runs] == ["pending", "pending"] and q.runs[0].tries == 1 and q.runs[0].seconds >= 8
    assert not (tmp_path / "work" / q.runs[0].id / "metrics.json").exists()


def test_a_failing_run_is_marked_with_its_log_and_the_others_go_on(tmp_path):
    q = qm.plan(["embedded_deform"], [], [0], _toy(tmp_path), est_s=1)
    q.runs.insert(0, qm.Run("broken", ["experiment=embedded_deform", "optim.no_such_key=1"], 1))
    qm.execute(q, tmp_path / "work", 1, budget_s=300, log=lambda m: None)
    assert [r.state for r in q.runs] == ["failed", "done"]
    assert "broken.log" in q.runs[0].error and "no_such_key" in (tmp_path / "work" / "broken.log").read_text()


def test_plan_never_overwrites_a_queue_and_ids_are_unique(tmp_path):
    (tmp_path / "q.json").write_text("{}")
    with pytest.raises(SystemExit, match="exists"):
        qm.main(["plan", str(tmp_path / "q.json"), "--experiments", "embedded_deform", "--est-seconds", "1"])
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
    qm.main(["plan", str(tmp_path / "q.json"), "--experiments", "dnerf_deform", "--scenes", str(tmp_path / "s1"),
             "--seeds", "0", "1", "--est-seconds", "300", "--variants", "a:seed=0", "--", "budget=gpu", "device=cuda"])
    q = qm.Queue.load(tmp_path / "q.json")
    assert len(q.runs) == 2 and all(r.overrides[-3:-1] == ["budget=gpu", "device=cuda"] for r in q.runs)
    assert "2 runs planned" in capsys.readouterr().out


def test_sixteen_runs_at_once_one_thread_each(tmp_path, monkeypatch):
    """A lent GPU machine has 16 cores: `--concurrent 16` keeps 16 runs going at once, one thread
    each. The runs here stand in for stdr-train (a process that records when it ran and writes
    metrics.json), so the test measures the scheduler, not training."""
    q = qm.plan(["embedded_deform"], [], list(range(20)), [], est_s=1)
    stamp = tmp_path / "stamps"
    stamp.mkdir()

    def fake(r, work, threads):
        code = ("import json, os, sys, time; from pathlib import Path; t0 = time.time(); time.sleep(3); "
                f"d = Path({str(work)!r}) / {r.id!r}; d.mkdir(parents=True, exist_ok=True); "
                "(d / 'metrics.json').write_text('{}'); "
                f"Path({str(stamp)!r}, {r.id!r}).write_text(json.dumps([t0, time.time(), "
                "os.environ['OMP_NUM_THREADS'], sys.argv[1]]))")
        return [sys.executable, "-c", code, f"train.threads={threads}"]
    monkeypatch.setattr(qm, "_command", fake)
    rec = qm.execute(q, tmp_path / "work", 16, 120, cores=16, poll_s=0.05, log=lambda m: None)
    assert rec["threads_each"] == 1 and len(rec["finished"]) == 20 and rec["failed"] == []
    spans = [json.loads(p.read_text()) for p in stamp.iterdir()]
    assert all(s[2] == "1" and s[3] == "train.threads=1" for s in spans)
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
