"""A run survives what research use does to it: one writer per run folder (stdr.io.files), a
resume that keeps its run's record (stdr.train.resume), an evaluation that never changes an
unfinished run, and a table row that never silently mixes trainings. Real processes on real
files: the commands are run as a user runs them."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from stdr.io.files import LOCK_NAME, RunLocked, read_holder, run_lock
from stdr.testing import TINY_SCENE

TINY = [*TINY_SCENE, "device=cpu", "model.init_num=300", "eval.lpips=false", "train.progress=false",
        "eval.save_images=false", "train.image_every=0", "eval.fps_repeats=1", "eval.fps_warmup=0",
        "baseline.warmup=10", "train.eval_at_warmup_end=false", "densify.refine_start=5",
        "densify.refine_every=10", "train.threads=1"]


def train_cmd(tmp_path: Path, run: Path, *extra: str) -> list[str]:
    return [sys.executable, "-m", "stdr.cli.train", *TINY, f"data.cache_dir={tmp_path / 'cache'}",
            f"hydra.run.dir={run}", *extra]


def sh(cmd, timeout=600, **kw) -> subprocess.CompletedProcess:
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, **kw)


def one_line_error(r: subprocess.CompletedProcess, prog: str) -> str:
    """The command ended with exit 2 and one `<prog>: error: ...` line, no traceback."""
    assert r.returncode == 2, (r.returncode, r.stderr[-3000:])
    assert "Traceback" not in r.stderr, r.stderr[-3000:]
    lines = [ln for ln in r.stderr.splitlines() if ln.startswith(f"{prog}: error:")]
    assert len(lines) == 1, r.stderr[-3000:]
    return lines[0]


# ---------------------------------------------------------------- one writer per run folder
def hold_lock(run: Path) -> subprocess.Popen:
    """Another process that holds the run's lock as stdr-train does, until killed."""
    holder = subprocess.Popen([sys.executable, "-c", (
        "import sys, time; from stdr.io.files import run_lock\n"
        "with run_lock(sys.argv[1], 'stdr-train'):\n"
        "    print('held', flush=True); time.sleep(600)"), str(run)], stdout=subprocess.PIPE, text=True)
    assert holder.stdout.readline().strip() == "held"
    return holder


def test_the_lock_is_exclusive_between_processes_reentrant_within_one_and_free_after_a_kill(tmp_path):
    run = tmp_path / "run"
    holder = hold_lock(run)
    try:
        with pytest.raises(RunLocked, match=rf"{run} is in use: stdr-train, pid {holder.pid} on host "
                                            r"\S+ since \d{4}-\d\d-\d\d"):
            with run_lock(run, "stdr-eval"):
                pass
        holder.send_signal(signal.SIGKILL)
        holder.wait(timeout=30)
    finally:
        holder.kill()
    assert read_holder(run)["pid"] == holder.pid  # the killed holder's record is still there ...
    with run_lock(run, "stdr-eval"):  # ... but its lock went with it
        assert read_holder(run)["pid"] == os.getpid() and read_holder(run)["prog"] == "stdr-eval"
        with run_lock(run, "stdr-tool pack"):  # the same process again (training's packing step)
            pass
        assert read_holder(run)["pid"] == os.getpid()  # the inner release kept the outer hold
        other = sh([sys.executable, "-c", "import sys; from stdr.io.files import run_lock\n"
                    "with run_lock(sys.argv[1], 'x'): pass", str(run)])
        assert other.returncode != 0 and "is in use: stdr-eval" in other.stderr
    assert (run / LOCK_NAME).read_text() == ""  # released: nobody holds it


def test_a_second_stdr_train_in_one_folder_is_refused_and_a_killed_ones_resume_proceeds(tmp_path):
    run = tmp_path / "run"
    first = subprocess.Popen(train_cmd(tmp_path, run, "optim.iterations=100000", "train.checkpoint_every=20"),
                             stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        t0 = time.time()
        while not (run / "checkpoints" / "last.pt").is_file():  # training, past its first checkpoint
            assert first.poll() is None, first.stdout.read()[-3000:]
            assert time.time() - t0 < 300
            time.sleep(0.2)
        second = sh(train_cmd(tmp_path, run, "optim.iterations=100000", "train.checkpoint_every=20"))
        line = one_line_error(second, "stdr-train")
        assert f"{run} is in use: stdr-train, pid {first.pid} on host" in line and "hydra.run.dir" in line
        assert first.poll() is None  # the first run goes on
        first.send_signal(signal.SIGKILL)
        first.wait(timeout=30)
    finally:
        first.kill()
    third = sh(train_cmd(tmp_path, run, "optim.iterations=100000", "train.checkpoint_every=20",
                         "train.stop_at=45"))
    assert third.returncode == 0, third.stderr[-3000:]
    assert f"the lock was left by stdr-train, pid {first.pid}" in third.stdout and "which is gone" in third.stdout
    assert "resumed from" in third.stdout


# ---------------------------------------------------------------- a resume keeps its record
def test_a_resume_with_a_changed_training_key_is_refused_and_override_records_the_change(tmp_path):
    run = tmp_path / "run"
    r = sh(train_cmd(tmp_path, run, "optim.iterations=40", "train.stop_at=20"))
    assert r.returncode == 0, r.stderr[-3000:]
    before = (run / "config.yaml").read_text()
    hydra_before = {f.name: f.read_bytes() for f in (run / ".hydra").iterdir()}
    changed = sh(train_cmd(tmp_path, run, "optim.iterations=30", "optim.lambda_dssim=0.5"))
    line = one_line_error(changed, "stdr-train")
    assert "resume the run at iteration 20" in line and "2 key(s)" in line
    assert "optim.iterations: 40 (the run's) -> 30 (this command's)" in line
    assert "optim.lambda_dssim: 0.2 (the run's) -> 0.5 (this command's)" in line and "train.resume=override" in line
    assert (run / "config.yaml").read_text() == before  # nothing rewritten, Hydra's record of the command included
    assert {f.name: f.read_bytes() for f in (run / ".hydra").iterdir()} == hydra_before
    # keys that only steer the process may differ: threads, logging, checkpoints, the stop
    ok = sh(train_cmd(tmp_path, run, "optim.iterations=40", "train.stop_at=25", "train.log_every=7",
                      "train.checkpoint_every=3"))
    assert ok.returncode == 0 and "resumed from" in ok.stdout, ok.stderr[-3000:]
    assert "config_changes" not in (run / "config.yaml").read_text()
    over = sh(train_cmd(tmp_path, run, "optim.iterations=30", "train.resume=override"))
    assert over.returncode == 0, over.stderr[-3000:]
    assert "resuming at iteration 25 with changed keys (train.resume=override): optim.iterations: 40" in over.stdout
    rec = yaml.safe_load((run / "config.yaml").read_text())
    assert rec["optim"]["iterations"] == 30  # the values it now trains with ...
    assert [(c["step"], c["keys"]) for c in rec["config_changes"]] == [(25, {"optim.iterations": [40, 30]})]
    entry = json.loads((run / "metrics.json").read_text())["test"]
    assert entry["iterations"] == 30 and entry["config_changes"][0]["keys"] == {"optim.iterations": [40, 30]}


def test_a_config_yaml_edited_by_hand_is_refused_on_resume(tmp_path):
    """config.yaml must say how the checkpoint was trained: a seed edited by hand, with a command that
    agrees with the edit, is refused naming both values; override takes the command's and records it."""
    run = tmp_path / "run"
    assert sh(train_cmd(tmp_path, run, "optim.iterations=30", "train.stop_at=5")).returncode == 0
    text = (run / "config.yaml").read_text()
    assert "\nseed: 0\n" in text
    (run / "config.yaml").write_text(text.replace("\nseed: 0\n", "\nseed: 7\n"))
    r = sh(train_cmd(tmp_path, run, "optim.iterations=30", "seed=7", "train.stop_at=6"))
    line = one_line_error(r, "stdr-train")
    assert "config.yaml differs from the config its checkpoint at iteration 5 was trained with" in line
    assert "seed: 0 (trained) -> 7 (config.yaml)" in line
    r = sh(train_cmd(tmp_path, run, "optim.iterations=30", "seed=7", "train.stop_at=6", "train.resume=override"))
    assert r.returncode == 0, r.stderr[-2000:]
    changes = yaml.safe_load((run / "config.yaml").read_text())["config_changes"]
    assert changes[-1]["step"] == 5 and changes[-1]["keys"] == {"seed": [0, 7]}


def test_train_resume_takes_true_false_or_override_only(tmp_path):
    r = sh(train_cmd(tmp_path, tmp_path / "run", "train.resume=sometimes"))
    assert "train.resume='sometimes': use true (resume from the checkpoint), false (start over) or override" \
        in one_line_error(r, "stdr-train")


@pytest.mark.slow
def test_a_restart_moves_the_earlier_results_aside_and_no_reader_sees_them_as_its_own(tmp_path):
    """`train.resume=false` into a finished run's folder: the earlier metrics.json, history.json,
    checkpoints and the rest go to previous/<time>/ with the config that made them; the new run's
    folder holds its own files only, so stdr-eval refuses it as unfinished instead of reporting the
    earlier run's numbers, and a sweep would not skip it as finished."""
    import shutil
    run = tmp_path / "run"
    r = sh(train_cmd(tmp_path, run, "optim.iterations=30"))
    assert r.returncode == 0, r.stderr[-3000:]
    old = {f: (run / f).read_bytes() for f in ("metrics.json", "history.json", "point_cloud.ply", "config.yaml")}
    r = sh(train_cmd(tmp_path, run, "optim.iterations=30", "train.resume=false", "train.stop_at=5"))
    assert r.returncode == 0, r.stderr[-3000:]
    prev = sorted((run / "previous").iterdir())
    assert len(prev) == 1 and f"train.resume=false: the earlier run's results in {run} moved to {prev[0]}" in r.stdout
    for f, data in old.items():
        assert (prev[0] / f).read_bytes() == data, f
    assert (prev[0] / "checkpoints" / "last.pt").is_file() and (prev[0] / "tb").is_dir()
    assert not (run / "metrics.json").exists() and not (run / "history.json").exists()
    assert not (run / "previous" / prev[0].name / "previous").exists()
    from stdr.io.checkpoint import load_checkpoint
    assert load_checkpoint(run / "checkpoints" / "last.pt")["model"]["step"] == 5
    line = one_line_error(_eval(run, f"out={tmp_path / 't'}", "reevaluate=false"), "stdr-eval")
    assert "has not finished: its checkpoint is at iteration 5 of 30" in line
    # a second restart keeps both earlier runs apart
    shutil.rmtree(tmp_path / "t", ignore_errors=True)
    r = sh(train_cmd(tmp_path, run, "optim.iterations=30", "train.resume=false", "train.stop_at=3"))
    assert r.returncode == 0 and len(list((run / "previous").iterdir())) == 2, r.stderr[-3000:]


# ---------------------------------------------------------------- evaluations and tables
@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """A finished 30-step run, an unfinished one (stopped at 5 of 30) and a finished 20-step run
    on another scene size (another 'scene' in a table)."""
    tmp = tmp_path_factory.mktemp("runs")
    out = {}
    for name, extra in (("done", ["optim.iterations=30"]), ("stopped", ["optim.iterations=30", "train.stop_at=5"]),
                        ("short", ["optim.iterations=20", "data.name=other"])):
        r = sh(train_cmd(tmp, tmp / name, *extra))
        assert r.returncode == 0, r.stderr[-3000:]
        out[name] = tmp / name
    return out


def _eval(*args, cwd=None) -> subprocess.CompletedProcess:
    return sh([sys.executable, "-m", "stdr.cli.eval", *map(str, args)], cwd=cwd)


def _tree(d: Path) -> dict[str, bytes]:
    return {str(p.relative_to(d)): p.read_bytes() for p in sorted(d.rglob("*")) if p.is_file()}


def test_stdr_eval_writes_nothing_into_an_unfinished_run_and_evaluates_it_apart_on_request(runs, tmp_path):
    stopped = runs["stopped"]
    before = _tree(stopped)
    r = _eval(stopped, f"out={tmp_path / 't'}")
    line = one_line_error(r, "stdr-eval")
    assert f"{stopped} has not finished: its checkpoint is at iteration 5 of 30" in line and "unfinished=true" in line
    assert _tree(stopped) == before and not (stopped / "metrics.json").exists()
    r = _eval(stopped, f"out={tmp_path / 't'}", "unfinished=true")
    assert r.returncode == 0, r.stderr[-3000:]
    apart = json.loads((tmp_path / "t" / "unfinished" / "stopped" / "metrics.json").read_text())["test"]
    assert apart["iterations"] == 5 and apart["psnr"] > 0
    assert _tree(stopped) == before  # still untouched


def test_a_table_row_mixing_iteration_counts_is_refused_or_labelled(runs, tmp_path):
    r = _eval(runs["done"], runs["short"], "reevaluate=false", f"out={tmp_path / 't'}")
    line = one_line_error(r, "stdr-eval")
    assert "the 'deform' row mixes runs of different training: iterations 30" in line and "20" in line
    assert "allow_mixed=true" in line
    r = _eval(runs["done"], runs["short"], "reevaluate=false", f"out={tmp_path / 't'}", "allow_mixed=true")
    assert r.returncode == 0, r.stderr[-3000:]
    table = json.loads((tmp_path / "t" / "table.json").read_text())
    assert table["methods"] == ["deform [mixed iterations 20/30]"]
    # re-evaluating: refused before either run is written into
    import shutil
    a, b = tmp_path / "a", tmp_path / "b"
    shutil.copytree(runs["done"], a)
    shutil.copytree(runs["short"], b)
    before = {p: p.read_bytes() for p in (a / "metrics.json", b / "metrics.json", a / "history.json")}
    line = one_line_error(_eval(a, b, f"out={tmp_path / 't2'}"), "stdr-eval")
    assert "the 'deform' row mixes runs of different training: iterations 30" in line
    assert {p: p.read_bytes() for p in before} == before


def test_stdr_eval_and_pack_refuse_a_second_writer_while_training_holds_the_run(runs, tmp_path):
    import shutil
    run = tmp_path / "run"
    shutil.copytree(runs["done"], run)
    holder = hold_lock(run)
    try:
        before = (run / "metrics.json").read_bytes()
        line = one_line_error(_eval(run, f"out={tmp_path / 't'}"), "stdr-eval")
        assert f"{run} is in use: stdr-train, pid {holder.pid}" in line
        assert (run / "metrics.json").read_bytes() == before
        line = one_line_error(sh([sys.executable, "-m", "stdr.cli.tool", "pack", str(run), "--no-eval"]), "stdr-tool")
        assert f"{run} is in use: stdr-train, pid {holder.pid}" in line and not (run / "model.stdrc").exists()
        # a reader needs no lock: tabulating the metrics as they are
        assert _eval(run, "reevaluate=false", f"out={tmp_path / 't2'}").returncode == 0
        # two runs, the second held: the first is not re-evaluated either (nothing written before the refusal)
        first = tmp_path / "first"
        shutil.copytree(runs["done"], first)
        mine = {p: p.read_bytes() for p in (first / "metrics.json", first / "history.json")}
        line = one_line_error(_eval(first, run, f"out={tmp_path / 't3'}"), "stdr-eval")
        assert f"{run} is in use" in line
        assert {p: p.read_bytes() for p in mine} == mine and not (tmp_path / "t3").exists()
    finally:
        holder.kill()


@pytest.mark.parametrize("content", ["", "{\"test\": {\"psnr\": 3", "\x00\x01garbage"])
def test_a_damaged_metrics_json_is_one_line_naming_it(runs, tmp_path, content):
    import shutil
    run = tmp_path / "run"
    shutil.copytree(runs["done"], run)
    (run / "metrics.json").write_text(content)
    line = one_line_error(_eval(run, "reevaluate=false", f"out={tmp_path / 't'}"), "stdr-eval")
    assert f"{run / 'metrics.json'} is damaged" in line and f"(stdr-eval {run})" in line
    # the advice works: the command it names re-evaluates the run and writes metrics.json again
    ok = _eval(run, f"out={tmp_path / 't2'}")
    assert ok.returncode == 0, ok.stderr[-2000:]
    assert json.loads((run / "metrics.json").read_text())["test"]["iterations"] == 30


def test_a_python_tag_in_config_yaml_runs_nothing_and_is_one_line_in_eval_and_view(runs, tmp_path):
    import shutil
    run = tmp_path / "run"
    shutil.copytree(runs["done"], run)
    marker = tmp_path / "pwned"
    cfg = (run / "config.yaml").read_text()
    (run / "config.yaml").write_text(cfg + f"evil: !!python/object/apply:os.system ['touch {marker}']\n")
    line = one_line_error(_eval(run, "reevaluate=false", f"out={tmp_path / 't'}"), "stdr-eval")
    assert f"{run / 'config.yaml'} is not a config stdr can read" in line and "!!python" in line
    r = sh([sys.executable, "-c", "from stdr.cli.view import view_main; import sys; view_main(sys.argv[1:])",
            str(run), "--port", "18765"], timeout=120)
    assert "is not a config stdr can read" in one_line_error(r, "stdr-view")
    assert not marker.exists()


# ---------------------------------------------------------------- one line, nothing left behind
@pytest.mark.parametrize("extra,said", [
    (["+optim.iteratons=5"], "unknown config key optim.iteratons: did you mean optim.iterations?"),
    (["data.max_width=-5"], "data.max_width=-5: use null (no limit) or a whole number >= 1"),
    (["budget=demo", "optim.iterations=400", "baseline.warmup=400"], "the deformation never trains in this run"),
    (["model.init_num=1000000000000"], "model.init_num=1000000000000: 1,000,000,000,000 Gaussians need at least"),
    # fits by its parameters (~0.7 GB), not by its initial scales' nearest-neighbour search (1024 x 3M floats = 12 GB a
    # block): counted before anything is allocated, on a machine with less free memory than that
    (["model.init_num=3000000"] if __import__("stdr.device").device.available_bytes(__import__("torch").device("cpu"))
     < 12 * 2 ** 30 else ["model.init_num=20000000"], "for the nearest-neighbour search of their initial scales"),
    (["+optim." + ".".join(f"k{i}" for i in range(300)) + "=1"], "characters): no such key or option in the config"),
])
def test_a_refused_config_is_one_line_and_leaves_no_folder(tmp_path, extra, said):
    run = tmp_path / "outputs" / "mine" / "run"
    r = sh(train_cmd(tmp_path, run, *extra), cwd=tmp_path)
    assert said in one_line_error(r, "stdr-train")
    assert not (tmp_path / "outputs").exists()  # neither the run folder nor the parents Hydra made


def test_a_run_folder_name_too_long_for_the_file_system_is_one_line(tmp_path):
    r = sh(train_cmd(tmp_path, tmp_path / ("a" * 300)))
    assert "File name too long" in one_line_error(r, "stdr-train") and "choose a shorter one" in r.stderr


@pytest.mark.slow
def test_a_lock_file_of_any_bytes_is_taken_over(tmp_path):
    """A damaged .stdr.lock (here not UTF-8) left by nobody is replaced: the run trains."""
    run = tmp_path / "run"
    run.mkdir()
    (run / LOCK_NAME).write_bytes(b"\xff\xfe\x00 not a record")
    r = sh(train_cmd(tmp_path, run, "optim.iterations=30", "train.stop_at=2"))
    assert r.returncode == 0 and "Traceback" not in r.stderr, r.stderr[-3000:]
    assert read_holder(run) == {}  # released: the record emptied


@pytest.mark.parametrize("content, said", [
    (None, "no queue file there"),
    ('{"runs": [', "not a queue file (Expecting value"),
    ("[]", "not a queue file (a JSON object with a 'runs' list)"),
    ('{"runs": [{"x": 1}]}', "a run entry is not one stdr-tool queue wrote"),
])
def test_a_queue_file_that_is_not_one_is_one_line(tmp_path, content, said):
    q = tmp_path / "q.json"
    if content is not None:
        q.write_text(content)
    for cmd in (["status", str(q)], ["run", str(q), "--work", str(tmp_path / "w"), "--out", str(tmp_path / "o")]):
        r = sh([sys.executable, "-m", "stdr.cli.tool", "queue", *cmd])
        assert f"{q}: {said}" in one_line_error(r, "stdr-tool")
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("cmd", [["verify"], ["prepare", "dnerf-400"]])
def test_stdr_data_on_a_missing_folder_is_one_line(tmp_path, cmd):
    r = sh([sys.executable, "-m", "stdr.cli.data", *cmd, str(tmp_path / "nope"), *([str(tmp_path / "out")]
                                                                                  if cmd[0] == "prepare" else [])])
    assert f"{tmp_path / 'nope'}: no such folder" in one_line_error(r, "stdr-data")


def test_a_refused_config_keeps_the_empty_folders_the_user_made(tmp_path):
    for made in ("outputs/mine", "outputs/mine/run"):
        (tmp_path / made).mkdir(parents=True)
        r = sh(train_cmd(tmp_path, tmp_path / "outputs" / "mine" / "run", "+optim.iteratons=5"), cwd=tmp_path)
        assert "unknown config key optim.iteratons" in one_line_error(r, "stdr-train")
        assert (tmp_path / made).is_dir() and not any((tmp_path / made).iterdir()), made
        assert sorted(p.name for p in (tmp_path / "outputs").rglob("*")) == sorted(Path(made).parts[1:])
        __import__("shutil").rmtree(tmp_path / "outputs")


def test_the_demo_budget_shorter_than_its_warm_up_is_named():
    r = sh([sys.executable, "-m", "stdr.cli.train", "budget=demo", "optim.iterations=400", "hydra.run.dir=/nonexistent/x"])
    assert "baseline.warmup" in one_line_error(r, "stdr-train") and "train.stop_at" in r.stderr


def test_a_sweep_with_a_failed_job_lists_it_and_exits_1(tmp_path):
    sweep = tmp_path / "sweep"
    cmd = [sys.executable, "-m", "stdr.cli.train", "-m", *TINY, f"data.cache_dir={tmp_path / 'cache'}",
           "optim.iterations=12", "model.init_num=300,1000000000000", f"hydra.sweep.dir={sweep}"]
    r = sh(cmd)
    assert r.returncode == 1, (r.stdout[-2000:], r.stderr[-2000:])
    assert "sweep finished with 1 failed job(s)" in r.stdout and "model.init_num=1000000000000" in r.stdout
    assert (sweep / "0" / "metrics.json").is_file()  # the other job finished
    # the same command again: the finished job is skipped, the failed one fails again
    again = sh(cmd)
    assert again.returncode == 1 and "skipping finished run" in again.stdout


@pytest.mark.parametrize("times", [["2"], ["nan"], ["0.5", "-1"]])
def test_stdr_export_refuses_times_outside_the_run_in_one_line(runs, tmp_path, times):
    r = sh([sys.executable, "-c", "from stdr.cli.view import export_main; import sys; export_main(sys.argv[1:])",
            str(runs["done"]), "--times", *times, "--out", str(tmp_path / "ply")], timeout=120)
    assert "the model's times run over [0, 1]" in one_line_error(r, "stdr-export")
    assert not (tmp_path / "ply").exists()


# ---------------------------------------------------------------- a run's data, pinned
@pytest.mark.slow
def test_a_run_reads_the_data_it_trained_on_and_refuses_other_data_under_its_path(tmp_path):
    """Trained with a relative data.path: stdr-eval from another folder, where that relative path is
    another scene, reads the run's own scene (data.json pins its folder); once that folder is gone,
    the other scene is refused in one line and metrics.json is left as it was; a copy of the run's
    scene (a project moved) is accepted."""
    import shutil

    from stdr.data.procedural import SceneOptions, generate_scene
    opts = SceneOptions(n_train=6, n_val=2, n_test=3, resolution=24)
    a, b = tmp_path / "a", tmp_path / "b"
    generate_scene(a / "data" / "scene", opts)
    generate_scene(b / "data" / "scene", SceneOptions(n_train=6, n_val=2, n_test=3, resolution=24, motion="jump"))
    run = a / "run"
    cmd = [sys.executable, "-m", "stdr.cli.train", "experiment=dnerf_deform", "data.path=data/scene", "device=cpu",
           "model.init_num=300", "eval.lpips=false", "train.progress=false", "eval.save_images=false",
           "train.image_every=0", "eval.fps_repeats=1", "eval.fps_warmup=0", "optim.iterations=20",
           "baseline.warmup=10", "train.eval_at_warmup_end=false", "densify.refine_start=5", "train.threads=1",
           f"hydra.run.dir={run}"]
    r = sh(cmd, cwd=a)
    assert r.returncode == 0, r.stderr[-3000:]
    rec = json.loads((run / "data.json").read_text())
    assert rec["root"] == str((a / "data" / "scene").resolve()) and rec["path"] == "data/scene"
    assert set(rec["splits"]) >= {"train", "test"} and rec["splits"]["train"]["frames"] == 6
    trained = json.loads((run / "metrics.json").read_text())["test"]["psnr"]
    ok = _eval(run, f"out={tmp_path / 't1'}", cwd=b)  # from b: data/scene there is another scene
    assert ok.returncode == 0, ok.stderr[-3000:]
    assert json.loads((run / "metrics.json").read_text())["test"]["psnr"] == trained  # the run's own scene, again
    shutil.move(a / "data" / "scene", tmp_path / "kept")
    before = (run / "metrics.json").read_bytes()
    line = one_line_error(_eval(run, f"out={tmp_path / 't2'}", cwd=b), "stdr-eval")
    assert f"{run}: the data at {(b / 'data' / 'scene').resolve()} is not what this run trained on" in line
    assert (run / "metrics.json").read_bytes() == before
    moved = tmp_path / "moved"
    shutil.copytree(tmp_path / "kept", moved / "data" / "scene")
    ok = _eval(run, f"out={tmp_path / 't3'}", cwd=moved)
    assert ok.returncode == 0, ok.stderr[-3000:]
    assert json.loads((run / "metrics.json").read_text())["test"]["psnr"] == trained


# ---------------------------------------------------------------- results name their checkpoint
@pytest.mark.slow
def test_results_name_their_checkpoint_and_readers_refuse_or_say_when_it_is_not_the_runs(tmp_path):
    """metrics.json, history.json's final entry and pack.json record the checkpoint (iteration,
    SHA-256) they came from. A compact file packed at step 5 of a run that then finished says so when
    loaded; metrics.json left behind by training that went on is refused by stdr-eval
    reevaluate=false and is not a finished run to a sweep."""
    from stdr.cli.train import _stale_metrics
    from stdr.io.checkpoint import checkpoint_identity
    run = tmp_path / "run"
    assert sh(train_cmd(tmp_path, run, "optim.iterations=30", "train.stop_at=5")).returncode == 0
    r = sh([sys.executable, "-m", "stdr.cli.tool", "pack", str(run), "--no-eval"])
    assert r.returncode == 0, r.stderr[-2000:]
    assert json.loads((run / "pack.json").read_text())["checkpoint"]["step"] == 5
    r = sh(train_cmd(tmp_path, run, "optim.iterations=30"))
    assert r.returncode == 0, r.stderr[-2000:]
    now = checkpoint_identity(run / "checkpoints" / "last.pt")
    assert now["step"] == 30
    m = json.loads((run / "metrics.json").read_text())["test"]
    assert m["checkpoint"] == now and _stale_metrics(run) == ""
    final = [h for h in json.loads((run / "history.json").read_text()) if h["tag"] == "final"]
    assert final[-1]["checkpoint"] == now
    # the PLY, an export and a video carry it in their headers (comment lines / metadata)
    from plyfile import PlyData
    src = f"stdr checkpoint step=30 sha256={now['sha256']}"
    assert src in PlyData.read(str(run / "point_cloud.ply")).comments
    ex = sh([sys.executable, "-c", "import sys; from stdr.cli.view import export_main; export_main(sys.argv[1:])",
             str(run), "--times", "0.25", "--out", str(tmp_path / "ex")])
    assert ex.returncode == 0, ex.stderr[-2000:]
    assert PlyData.read(str(tmp_path / "ex" / "t_0.2500.ply")).comments == [src, "stdr time t=0.25"]
    vid = sh([sys.executable, "-c", "import sys; from stdr.cli.view import render_main; render_main(sys.argv[1:])",
              str(run), "--out", str(tmp_path / "v"), "--kinds", "time", "--frames", "2", "--width", "32"])
    assert vid.returncode == 0, vid.stderr[-2000:]
    import imageio_ffmpeg
    probe = subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-i", str(tmp_path / "v" / "time_rgb.mp4")],
                           capture_output=True, text=True)
    assert src in probe.stderr
    load = sh([sys.executable, "-c", "import sys; from stdr.model import load_model; load_model(sys.argv[1], 'cpu')",
               str(run / "model.stdrc")])
    assert load.returncode == 0, load.stderr[-2000:]
    assert (f"{run / 'model.stdrc'} was packed from the checkpoint at iteration 5; the run's checkpoints/last.pt is at "
            "iteration 30") in load.stderr
    # training goes on (a longer run, resumed with the change recorded), and the metrics.json of iteration 30 is
    # put back (a copy restored from elsewhere): it is not the run's now
    old = (run / "metrics.json").read_bytes()
    r = sh(train_cmd(tmp_path, run, "optim.iterations=40", "train.resume=override"))
    assert r.returncode == 0, r.stderr[-2000:]
    (run / "metrics.json").write_bytes(old)
    line = one_line_error(_eval(run, f"out={tmp_path / 't'}", "reevaluate=false"), "stdr-eval")
    assert f"{run / 'metrics.json'} is of the checkpoint at iteration 30" in line and "at iteration 40" in line
    assert "iteration 40" in _stale_metrics(run) and (run / "metrics.json").read_bytes() == old
    # re-evaluated, it is the run's again
    assert _eval(run, f"out={tmp_path / 't2'}").returncode == 0 and _stale_metrics(run) == ""


def test_an_export_or_a_video_of_an_unfinished_run_says_so(runs, tmp_path):
    stopped, done = runs["stopped"], runs["done"]
    for run, said in ((stopped, True), (done, False)):
        ex = sh([sys.executable, "-c", "import sys; from stdr.cli.view import export_main; export_main(sys.argv[1:])",
                 str(run), "--times", "0.5", "--out", str(tmp_path / f"e_{run.name}")])
        assert ex.returncode == 0, ex.stderr[-2000:]
        assert ("the export is of an unfinished run: its model is at iteration 5 of 30" in ex.stdout) is said
        vid = sh([sys.executable, "-c", "import sys; from stdr.cli.view import render_main; render_main(sys.argv[1:])",
                  str(run), "--out", str(tmp_path / f"v_{run.name}"), "--kinds", "time", "--frames", "2", "--width", "32",
                  "--format", "gif"])
        assert vid.returncode == 0, vid.stderr[-2000:]
        assert ("the video is of an unfinished run: its model is at iteration 5 of 30" in vid.stdout) is said


def test_a_scene_that_cannot_be_read_is_one_line_and_leaves_no_run_folder(tmp_path):
    """The data is read before the run's record is written: an image missing from a D-NeRF scene
    (found only when the loader reads it) leaves no config.yaml, log or lock behind."""
    from stdr.data.procedural import SceneOptions, generate_scene
    scene = generate_scene(tmp_path / "scene", SceneOptions(n_train=6, n_val=2, n_test=3, resolution=24))
    (scene / "train" / "r_003.png").unlink()
    run = tmp_path / "outputs" / "run"
    r = sh([sys.executable, "-m", "stdr.cli.train", "experiment=dnerf_deform", f"data.path={scene}", "device=cpu",
            "train.progress=false", f"hydra.run.dir={run}"], cwd=tmp_path)
    assert "frames[3] image './train/r_003' not found" in one_line_error(r, "stdr-train")
    assert not (tmp_path / "outputs").exists()


def test_a_re_evaluation_keeps_the_training_time_fps_and_says_when_the_machine_is_busy(runs, tmp_path, monkeypatch):
    import shutil

    from stdr.cli import eval as ev
    run = tmp_path / "run"
    shutil.copytree(runs["done"], run)
    trained = json.loads((run / "metrics.json").read_text())["test"]["fps"]
    for k in range(2):  # the first timing stays, whatever the later ones measure
        assert _eval(run, f"out={tmp_path / f't{k}'}").returncode == 0
        assert json.loads((run / "metrics.json").read_text())["test"]["fps_at_training"] == trained
    monkeypatch.setattr(ev.os, "getloadavg", lambda: (7.5, 7.0, 6.0))
    monkeypatch.setattr(ev.os, "cpu_count", lambda: 2)
    assert ev.machine_load() == "the machine is busy (load 7.5 on 2 cores)"
    monkeypatch.setattr(ev.os, "getloadavg", lambda: (0.4, 0.3, 0.2))
    assert ev.machine_load() == ""


def test_stdr_eval_prints_where_its_tables_are_with_hydra_job_chdir(runs, tmp_path):
    """out= is read from the folder the command was typed in, whatever hydra.job.chdir does, and the
    printed path is that folder's table."""
    r = _eval(runs["done"], "reevaluate=false", "out=rel/tables", "hydra.job.chdir=true", cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    table = tmp_path / "rel" / "tables" / "table.md"
    assert table.is_file() and str(table) in r.stdout
