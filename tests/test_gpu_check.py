"""scripts/gpu_check.py, the staged GPU check: its deadline and caps, what it leaves in OUT after
every stage, and (slow) the whole --dry-run on the CPU, which runs every stage's plumbing."""
import importlib.util
import json
import os
import re
import subprocess
import sys
import tarfile
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _module():
    spec = importlib.util.spec_from_file_location("gpu_check", ROOT / "scripts" / "gpu_check.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look their module up there
    spec.loader.exec_module(mod)
    return mod


def test_stages_are_skipped_at_the_deadline_killed_at_their_cap_and_packed_after_each(tmp_path):
    gc = _module()
    out = tmp_path / "out"
    out.mkdir()
    r = gc.Runner(out, tmp_path / "work", budget=60, only=set())
    py = sys.executable
    assert r.run(gc.Stage("quick", 1, 30, [py, "-c", "print('hello from quick')"]))
    t = time.monotonic()
    assert not r.run(gc.Stage("hang", 1, 2, [py, "-c", "import time; time.sleep(60)"]))
    assert time.monotonic() - t < 20  # killed at its cap, not after the sleep
    assert not r.run(gc.Stage("late", 1000, 1000, [py, "-c", "raise SystemExit(0)"]))
    assert not r.run(gc.Stage("bad", 1, 30, [py, "-c", "raise SystemExit(7)"]))
    recs = {x["stage"]: x for x in json.loads((out / "summary.json").read_text())}
    assert [x for x in recs] == ["quick", "hang", "late", "bad"]
    assert recs["quick"]["status"] == "ok" and recs["quick"]["rc"] == 0
    assert recs["hang"]["status"] == "timeout"
    assert recs["late"]["status"] == "skipped" and "estimate 1000 s" in recs["late"]["why"]
    assert recs["bad"]["status"] == "failed" and recs["bad"]["rc"] == 7
    with tarfile.open(out / "results.tgz") as tar:
        names = tar.getnames()
        assert "res/quick.log" in names and "res/bad.log" in names and "res/late.log" not in names
        assert "hello from quick" in tar.extractfile("res/quick.log").read().decode()
    md = (out / "summary.md").read_text()
    assert "| hang | timeout |" in md and "| late | skipped | 0 |" in md
    assert "late: skipped" in (out / "progress.log").read_text()


def test_only_the_named_stages_run_and_the_facts_of_a_pytest_log_are_read(tmp_path):
    gc = _module()
    r = gc.Runner(tmp_path, tmp_path / "w", budget=60, only={"b"})
    py = sys.executable
    assert not r.run(gc.Stage("a", 1, 10, [py, "-c", "pass"]))
    assert r.run(gc.Stage("b", 1, 10, [py, "-c", "pass"]))
    assert [x["stage"] for x in r.records] == ["b"]
    log = "....\nFAILED tests/test_x.py::test_y[cuda] - AssertionError\n2 failed, 7 passed, 2 skipped, 37 deselected in 2.03s"
    facts = gc.pytest_facts(log, None)
    assert facts == {"failed": 2, "passed": 7, "skipped": 2, "deselected": 37,
                     "failing": ["tests/test_x.py::test_y[cuda]"]}


def test_gpu_mode_needs_a_dnerf_scene(tmp_path, capsys):
    gc = _module()
    with pytest.raises(SystemExit):
        gc.main([str(tmp_path / "out"), "--scene", str(tmp_path)])
    assert "--scene must be a D-NeRF scene folder with transforms_train.json" in capsys.readouterr().err


@pytest.mark.slow
def test_dry_run_runs_every_stage_on_the_cpu(tmp_path):
    """`bash scripts/gpu_check.sh --dry-run OUT`: every stage ends ok on the CPU; the training
    stages ran the compiled projection on the CPU backend and their metrics came back."""
    out = tmp_path / "out"
    proc = subprocess.run(["bash", str(ROOT / "scripts" / "gpu_check.sh"), "--dry-run", str(out),
                           "--work", str(tmp_path / "work")], capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    recs = json.loads((out / "summary.json").read_text())
    gc = _module()
    first, rest = gc.build_stages(type("A", (), {"work": tmp_path / "w", "scene": None, "lpips_weights": None})(), "python", True)
    assert [r["stage"] for r in recs] == [s.name for s in first + rest]
    assert all(r["status"] == "ok" for r in recs), [(r["stage"], r["status"]) for r in recs]
    runs = [r for r in recs if r["stage"].startswith("run_")]
    assert {r["stage"] for r in runs} == {"run_deform", "run_gpu_deform", "run_gpu_deform_fast", "run_gpu_deform_stdr", "run_deform_twin", "run_deform_stdr", "run_4dgs",
                                          "run_4dgs_stdr", "run_scgs", "run_spgs", "run_paper_deform", "run_paper_scgs"}
    for r in runs:
        assert r["backend"] == "cpu" and r["device"] == "cpu", r
        assert r["projection"] == ("torch" if r["stage"] == "run_deform_twin" else "compiled"), r
        assert r["psnr"] > 5
    with tarfile.open(out / "results.tgz") as tar:
        names = set(tar.getnames())
        assert {f"res/runs/{r['stage']}/metrics.json" for r in runs} <= names
        cfgs = [tar.extractfile(f"res/runs/{n}/config.yaml").read().decode() for n in ("run_gpu_deform", "run_gpu_deform_stdr")]
    assert all("budget: gpu" in c for c in cfgs) and "budget: gpu" not in tar_text(out, "res/runs/run_deform/config.yaml")
    assert {"res/kernels.xml", "res/bench_raster.json", "res/bench_train.json", "res/bench_train_fast.json",
            "res/bench_train_compile.json"} <= names
    paper = tar_text(out, "res/runs/run_paper_deform/config.yaml")  # the paper budget with the speed keys on
    assert "budget: paper" in paper and "fused_loss: true" in paper and "sync_free: true" in paper


def tar_text(out: Path, name: str) -> str:
    with tarfile.open(out / "results.tgz") as tar:
        return tar.extractfile(name).read().decode()


def test_runs_use_the_lpips_weights_given_and_say_alex_when_no_vgg_weights_came(tmp_path):
    gc = _module()
    scene = tmp_path / "scene"
    scene.mkdir()
    for files, alex in (({"lpips_v0.1_alex_lin.pth", "alexnet_features.pth"}, True),
                        ({"lpips_v0.1_vgg_lin.pth", "vgg16_features.pth"}, False)):
        w = tmp_path / ("alex" if alex else "vgg")
        w.mkdir()
        for f in files:
            (w / f).write_bytes(b"")
        args = type("A", (), {"work": tmp_path / "w", "scene": scene, "lpips_weights": w})()
        _, rest = gc.build_stages(args, "python", False)
        runs = [s for s in rest if s.name.startswith("run_")]
        assert runs and all(s.env["STDR_LPIPS_WEIGHTS"] == str(w.resolve()) for s in runs)
        assert all(("eval.lpips_net=alex" in s.cmd) == alex for s in runs)
        assert all(s.cmd[-1].startswith("hydra.run.dir=") for s in runs)


def test_after_the_kernels_the_binning_under_memcheck_then_the_speed_key_trainings(tmp_path):
    """On a GPU, right after the kernels: the binning tests under compute-sanitizer memcheck
    (uncached allocations, so an access past a tensor is an error); the speed-key trainings against
    the torch forms with blocking launches (under memcheck they outlast any stage); one short run
    with the keys under memcheck. The tests must exist under the names the stages give."""
    gc = _module()
    scene = tmp_path / "scene"
    scene.mkdir()
    args = type("A", (), {"work": tmp_path / "w", "scene": scene, "lpips_weights": None})()
    _, rest = gc.build_stages(args, "python", False)
    names = [s.name for s in rest]
    k = names.index("kernels")
    assert names[k + 1:k + 4] == ["binning_memcheck", "train_keys", "memcheck_keys"]
    binning, keys, run = rest[k + 1:k + 4]
    assert binning.cmd[:2] == ["bash", "-c"] and "exec compute-sanitizer --tool memcheck --error-exitcode 9 " in binning.cmd[2]
    assert binning.env == {"CUDA_LAUNCH_BLOCKING": "1", "PYTORCH_NO_CUDA_MEMORY_CACHING": "1"}
    assert re.findall(r"tests/\S+", binning.cmd[2].split(" then ")[1].split(";")[0]) == ["tests/test_binning.py"]
    assert "compute-sanitizer" not in keys.cmd and keys.env == {"CUDA_LAUNCH_BLOCKING": "1"}
    ids = [c for c in keys.cmd if str(c).startswith("tests/")]
    assert ids == [f"tests/test_device.py::{gc.SPEED_KEYS_TEST}"]
    script = run.cmd[2].split(" then ")[1].split(";")[0]
    assert run.cmd[:2] == ["bash", "-c"] and script.startswith("exec compute-sanitizer --tool memcheck")
    assert all(k in script for k in gc.FAST) and "device=cuda" in script and "train.guard.inject_nan_grad_at=[17]" in script
    proc = subprocess.run([sys.executable, "-m", "pytest", "--collect-only", "-q", "tests/test_binning.py", *ids], cwd=ROOT,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-2000:]
    assert f"{gc.SPEED_KEYS_TEST}[deform_stdr]" in proc.stdout and "test_binning.py::" in proc.stdout


def test_memchecked_runs_under_the_sanitizer_where_it_works_and_says_so_where_it_cannot(tmp_path):
    """A stand-in compute-sanitizer on PATH (the probe's interpreter is `true`, which passes): one that
    runs its program (after its flags) gives the
    program's output with the sanitizer's mark and exit status 9 on the program's failure; one that
    refuses the device gives the program run alone after NO_SANITIZER, and the facts record it."""
    gc = _module()
    bindir = tmp_path / "bin"
    bindir.mkdir()
    fake = bindir / "compute-sanitizer"
    prog = ["bash", "-c", 'echo "prog ran with $0"; exit ${FAIL:-0}', "an arg with spaces"]
    for works in (True, False):
        fake.write_text("#!/bin/bash\n" + ('shift 4; echo SANITIZER; "$@"; rc=$?; [ $rc -ne 0 ] && exit 9; exit 0\n'
                                            if works else 'echo "Device not supported" >&2; exit 1\n'))
        fake.chmod(0o755)
        env = {**os.environ, "PATH": f"{bindir}{os.pathsep}{os.environ['PATH']}"}
        for fail in ("0", "3"):
            p = subprocess.run(gc.memchecked(prog, "true"), capture_output=True, text=True,
                               env={**env, "FAIL": fail}, timeout=120)
            assert "prog ran with an arg with spaces" in p.stdout
            assert p.stdout.count("SANITIZER") == (1 if works else 0)  # the probe's own output is discarded
            assert (gc.NO_SANITIZER in p.stdout) == (not works)
            assert p.returncode == (0 if fail == "0" else (9 if works else 3))
            assert gc.sanitizer_facts()(p.stdout, None) == {"sanitizer": works}
            # as the stage's log holds it: the command (which quotes the line) first
            log = "$ " + " ".join(gc.memchecked(prog, "true")) + "\n" + p.stdout
            assert gc.sanitizer_facts()(log, None) == {"sanitizer": works}


def test_the_gpu_payload_names_what_is_missing_before_it_writes(tmp_path):
    """scripts/gpu_payload.sh with a shared folder that lacks the LPIPS weights or a scene: exit 2,
    the missing path named, and the payload already there left as it was."""
    marker = ROOT / "build" / "gpucarry" / "kept.txt"
    had = marker.parent.is_dir()
    marker.parent.mkdir(parents=True, exist_ok=True)
    marker.write_text("x")
    shared = tmp_path / "shared"
    p = subprocess.run(["bash", str(ROOT / "scripts" / "gpu_payload.sh"), str(shared)], capture_output=True, text=True,
                       timeout=60)
    assert p.returncode == 2 and f"{shared}/weights/lpips/alexnet_features.pth is missing" in p.stderr
    (shared / "weights" / "lpips").mkdir(parents=True)
    for f in ("alexnet_features.pth", "lpips_v0.1_alex_lin.pth"):
        (shared / "weights" / "lpips" / f).write_bytes(b"")
    p = subprocess.run(["bash", str(ROOT / "scripts" / "gpu_payload.sh"), str(shared)], capture_output=True, text=True,
                       timeout=60)
    assert p.returncode == 2 and f"no D-NeRF scene at {shared}/data/dnerf/bouncingballs" in p.stderr
    assert marker.read_text() == "x"
    marker.unlink()
    if not had:
        marker.parent.rmdir()
