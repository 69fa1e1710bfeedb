"""Fault tolerance: the non-finite guard, recoveries, the divergence detector,
checkpoints that survive a kill, truncation and corruption."""
import json
import math
import mmap
import os
import signal
import subprocess
import sys
import time

import pytest
import torch
from stdr.testing import tiny_config
from stdr.io.checkpoint import CheckpointError, load_checkpoint, previous_path, save_checkpoint
from stdr.train.guard import TrainingDiverged, all_finite, first_nonfinite
import random
from pathlib import Path
from stdr.testing import TINY_SCENE

# a short schedule that crosses densification, the warm-up end and an opacity reset
SCHED = ["optim.iterations=60", "baseline.warmup=20", "densify.refine_start=10", "densify.refine_every=10",
         "densify.reset_every=30", "densify.prune_big_after=30", "train.checkpoint_every=0",
         "train.eval_at_warmup_end=false", "train.guard.enabled=true", "train.guard.snapshot_every=10"]


def _trainer(tmp_path, name, extra=()):
    from stdr.train.trainer import Trainer
    return Trainer(tiny_config(tmp_path, SCHED + list(extra)), tmp_path / name)


def _same_params(a, b):
    assert a.state.model.params.keys() == b.state.model.params.keys()
    for k in a.state.model.params:
        assert torch.equal(a.state.model.params[k], b.state.model.params[k]), k
    for (ka, va), (kb, vb) in zip(a.state.model.deform.state_dict().items(), b.state.model.deform.state_dict().items()):
        assert ka == kb and torch.equal(va, vb), ka


def test_all_finite_is_exact():
    big = torch.full((1000,), 3e38)  # finite elements whose sum overflows to inf
    assert all_finite([big, None, torch.zeros(3)])
    for bad in (float("nan"), float("inf"), -float("inf")):
        t = torch.ones(10)
        t[7] = bad
        assert not all_finite([torch.ones(2), t])
        assert first_nonfinite([("a", torch.ones(2)), ("b", t)]) == "b"
    inf_pair = torch.tensor([float("inf"), -float("inf")])  # sums to NaN
    assert not all_finite([inf_pair])
    assert all_finite([torch.arange(5)])  # integer tensors are not checked


@pytest.mark.slow
@pytest.mark.parametrize("name", ["deform", "deform_stdr", "scgs_stdr", "spgs_stdr", "4dgs_stdr"])
def test_guard_changes_nothing_without_a_fault(tmp_path, name):
    """The guard is on by default, so it must leave every configuration's training bit-identical:
    across densification, the warm-up end, STDR's freeze and the baselines' stages."""
    from stdr.tools.identity_check import SCHEDULE, STDR_PHASES
    extra = [*SCHEDULE, *STDR_PHASES, f"experiment=embedded_{name}", "train.guard.snapshot_every=10"]
    on = _trainer(tmp_path, "on", extra + ["train.guard.enabled=true"])
    on.train()
    off = _trainer(tmp_path, "off", extra + ["train.guard.enabled=false"])
    off.train()
    assert on.step == off.step == 60 and on.state.guard.recoveries == []
    _same_params(on, off)


@pytest.mark.slow
def test_nan_gradient_is_recovered_and_logged(tmp_path):
    from stdr.train.run import run_training as run
    cfg = tiny_config(tmp_path, SCHED + ["train.guard.inject_nan_grad_at=[15]", "eval.fps_repeats=1"])
    res = run(cfg, tmp_path / "nan")
    m = json.loads((tmp_path / "nan" / "metrics.json").read_text())["test"]
    for k in ("psnr", "ssim"):
        assert math.isfinite(m[k]) and math.isfinite(res[k])
    g = m["guard"]
    assert g["n_recoveries"] == 1 and len(g["recoveries"]) == 1
    rec = g["recoveries"][0]
    # detected at step 15, back to the snapshot of step 10, every lr halved
    assert rec["step"] == 15 and rec["restored_to"] == 10 and rec["reason"] == "non-finite grad of means"
    # the CPU's default check is the sync-free one: read at the next snapshot step
    assert g["check"] == "sync-free" and rec["found_at"] == 20
    # ... and the compiled check, with the compiled loss (the metrics say which forms ran)
    assert g["compiled_check"] is True and m["train_loss"] == "compiled"
    assert rec["lr_scale"] == g["lr_scale"] == 0.5 and not rec["stopped"]
    assert m["iterations"] == 60 and m["last"]["step"] == 60 and m["best"]["psnr"] >= m["last"]["psnr"]
    ck = load_checkpoint(tmp_path / "nan" / "checkpoints" / "last.pt")
    assert ck["guard"]["lr_scale"] == 0.5
    assert all(torch.isfinite(v).all() for v in ck["model"]["params"].values())
    tb = list((tmp_path / "nan" / "tb").glob("events.*"))
    assert tb and any(b"guard/recoveries" in p.read_bytes() for p in tb)


@pytest.mark.slow
def test_recovery_restores_the_snapshot_exactly_and_lowers_every_lr(tmp_path):
    ref = _trainer(tmp_path, "ref", ["train.stop_at=10"])
    ref.train()  # the state after 10 steps
    tr = _trainer(tmp_path, "tr", ["train.stop_at=25"])
    tr.train()  # snapshots at 0, 10, 20
    assert tr.state.guard.snapshot["model"]["step"] == 20
    tr.state.guard.snapshot = tr.state.guard.best_snapshot = None
    tr2 = _trainer(tmp_path, "tr2", ["train.stop_at=17"])
    tr2.train()  # last snapshot: step 10
    tr2.state.guard.recover(tr2.state, tr2.log, "a test")
    assert tr2.step == 10 and tr2.state.guard.lr_scale == 0.5
    _same_params(ref, tr2)
    from stdr.train.optim import gaussian_lr, net_lr, update_lrs
    update_lrs(tr2.cfg, tr2.state, tr2.net_groups, tr2.step)
    for k, o in tr2.state.optimizers.items():
        assert o.param_groups[0]["lr"] == pytest.approx(0.5 * gaussian_lr(tr2.cfg, tr2.state.model, k, 10), rel=1e-12), k
    for spec, g in zip(tr2.net_groups, tr2.state.net_opt.param_groups):
        assert g["lr"] == pytest.approx(0.5 * net_lr(tr2.cfg, spec, 10), rel=1e-12)


@pytest.mark.slow
@pytest.mark.parametrize("sync_free", ["true", "false"])
def test_too_many_recoveries_stop_with_a_clear_error_and_a_good_checkpoint(tmp_path, sync_free):
    # one fault in each snapshot interval: the sync-free check finds each at the interval's end
    # (no log step in between: train.log_every=50)
    tr = _trainer(tmp_path, "stop", ["train.guard.max_recoveries=2", "train.guard.inject_nan_grad_at=[12,23,34]",
                                     f"train.guard.sync_free={sync_free}", "train.log_every=50"])
    with pytest.raises(TrainingDiverged, match=r"max_recoveries=2.*last good state \(iteration 30\)"):
        tr.train()
    recs = tr.state.guard.recoveries
    assert [r["step"] for r in recs] == [12, 23, 34] and [r["stopped"] for r in recs] == [False, False, True]
    assert [r["restored_to"] for r in recs] == [10, 20, 30]
    assert [r["found_at"] for r in recs] == ([20, 30, 40] if sync_free == "true" else [12, 23, 34])
    ck = load_checkpoint(tmp_path / "stop" / "checkpoints" / "last.pt")
    assert ck["model"]["step"] == 30 and len(ck["guard"]["recoveries"]) == 3
    assert all(torch.isfinite(v).all() for v in ck["model"]["params"].values())


@pytest.mark.slow
def test_the_sync_free_check_recovers_exactly_as_the_check_of_every_step(tmp_path):
    """Fused Adam applies nothing from the faulty step on, the flag is read at the next snapshot
    step and the same snapshot is restored: the run goes on bit-identical to one whose check
    read every step, with the same record but for when the fault was found."""
    nan = ["train.guard.inject_nan_grad_at=[15]"]
    free = _trainer(tmp_path, "free", nan + ["train.guard.sync_free=true"])
    free.train()
    each = _trainer(tmp_path, "each", nan + ["train.guard.sync_free=false"])
    each.train()
    assert free.state.guard.sync_free and not each.state.guard.sync_free
    (a,), (b,) = free.state.guard.recoveries, each.state.guard.recoveries
    assert a["found_at"] == 20 and b["found_at"] == 15
    assert {k: v for k, v in a.items() if k not in ("found_at", "train_seconds")} == \
        {k: v for k, v in b.items() if k not in ("found_at", "train_seconds")}
    _same_params(free, each)


def test_a_faulty_step_applies_nothing_until_the_flag_is_read(tmp_path):
    tr = _trainer(tmp_path, "flag", ["train.guard.inject_nan_grad_at=[1]", "train.guard.sync_free=true"])
    before = {k: v.detach().clone() for k, v in tr.state.model.params.items()}
    tr.train_step()  # step 1: NaN in the gradient of the means
    assert float(tr.state.guard.flag) == 1.0
    for k, v in tr.state.model.params.items():
        assert torch.equal(v, before[k]), k
        st = tr.state.optimizers[k].state.get(v, {}) if k in tr.state.optimizers else {}
        assert "step" not in st or float(st["step"]) == 0, k  # Adam's step count did not advance
    tr.train_step()  # a clean step: still nothing applied until the flag is read
    for k, v in tr.state.model.params.items():
        assert torch.equal(v, before[k]), k
    assert tr.state.guard.poll() == (1, "non-finite grad of means") and tr.state.guard.poll() is None


def test_the_sync_free_check_needs_fused_adam(tmp_path):
    with pytest.raises(ValueError, match=r"train.guard.sync_free=true needs optim.fused_adam=true"):
        _trainer(tmp_path, "x", ["optim.fused_adam=false", "train.guard.sync_free=true"])
    tr = _trainer(tmp_path, "y", ["optim.fused_adam=false"])  # null: the check of every step
    assert not tr.state.guard.sync_free and tr.state.guard.summary(None)["check"] == "every step"


@pytest.mark.slow
def test_divergence_restores_the_best_evaluation(tmp_path):
    tr = _trainer(tmp_path, "div", ["optim.iterations=20", "baseline.warmup=10", "train.guard.divergence_db=5"])
    tr.train()
    tr.state.guard.after_evaluation(tr.state, tr.log, 20.0)  # the best so far, at step 20
    best_params = {k: v.detach().clone() for k, v in tr.state.model.params.items()}
    tr.cfg.optim.iterations = 30
    tr.train()  # resumes from its own checkpoint (step 20) and goes on to 30
    assert tr.step == 30
    tr.state.guard.after_evaluation(tr.state, tr.log, 16.0)  # 4 dB down: within the tolerance
    assert tr.step == 30 and tr.state.guard.recoveries == []
    tr.state.guard.after_evaluation(tr.state, tr.log, 14.0)  # 6 dB down: diverged
    assert tr.step == 20 and len(tr.state.guard.recoveries) == 1
    assert tr.state.guard.recoveries[0]["reason"].startswith("divergence") and tr.state.guard.lr_scale == 0.5
    for k, v in best_params.items():
        assert torch.equal(tr.state.model.params[k], v), k
    tr.state.guard.after_evaluation(tr.state, tr.log, float("nan"))  # a non-finite evaluation is a recovery too
    assert "non-finite evaluation" in tr.state.guard.recoveries[-1]["reason"]


@pytest.mark.slow
def test_a_run_with_a_recovery_resumes_exactly(tmp_path):
    nan = ["train.guard.inject_nan_grad_at=[15]"]
    a = _trainer(tmp_path, "a", nan)
    a.train()
    b1 = _trainer(tmp_path, "b", nan + ["train.checkpoint_every=10", "train.stop_at=35"])
    b1.train()  # recovers at 15, stops at 35 (checkpoints at 10, 20, 30 and 35)
    b2 = _trainer(tmp_path, "b", nan + ["train.checkpoint_every=10"])
    b2.train()
    assert a.state.guard.lr_scale == b2.state.guard.lr_scale == 0.5 and len(b2.state.guard.recoveries) == 1
    _same_params(a, b2)


CHILD = r"""
import sys, time
from pathlib import Path
from stdr.testing import tiny_config
from stdr.train.trainer import Trainer
folder, marker = Path(sys.argv[1]), Path(sys.argv[2])
tr = Trainer(tiny_config(folder, sys.argv[3:]), folder / "run")
step = tr.train_step
def paused_step():
    out = step()
    if tr.step == 25:  # between two checkpoints: steps 21-25 are lost with the kill
        marker.write_text("25")
        time.sleep(120)
    return out
tr.train_step = paused_step
tr.train()
"""


@pytest.mark.slow
def test_a_run_killed_with_sigkill_resumes_to_the_same_result(tmp_path):
    sched = SCHED + ["train.checkpoint_every=10"]
    marker = tmp_path / "paused"
    # results are bit-identical for a given thread count: the child uses this process's
    # (conftest pins it; the environment's OMP_NUM_THREADS may differ)
    threads = f"train.threads={torch.get_num_threads()}"
    child = subprocess.Popen([sys.executable, "-c", CHILD, str(tmp_path), str(marker), *sched, threads],
                             stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        t0 = time.time()
        while not marker.exists():
            if child.poll() is not None:
                pytest.fail(f"the training process ended early: {child.stderr.read().decode()[-2000:]}")
            if time.time() - t0 > 300:
                pytest.fail("the training process did not reach step 25 in 300 s")
            time.sleep(0.05)
        os.kill(child.pid, signal.SIGKILL)
        child.wait(timeout=30)
    finally:
        if child.poll() is None:
            child.kill()
    assert child.returncode == -signal.SIGKILL
    ckpts = tmp_path / "run" / "checkpoints"
    assert load_checkpoint(ckpts / "last.pt")["model"]["step"] == 20
    resumed = _trainer(tmp_path, "run", ["train.checkpoint_every=10"])
    resumed.train()
    whole = _trainer(tmp_path, "whole", ["train.checkpoint_every=10"])
    whole.train()
    assert resumed.step == whole.step == 60
    _same_params(resumed, whole)


def test_checkpoints_keep_the_previous_one_and_detect_damage(tmp_path):
    p = tmp_path / "ck" / "last.pt"
    save_checkpoint(p, {"model": {"step": 10}, "x": torch.arange(1000.0)}, keep_previous=True)
    save_checkpoint(p, {"model": {"step": 20}, "x": torch.arange(1000.0) * 2}, keep_previous=True)
    assert load_checkpoint(p)["model"]["step"] == 20
    assert load_checkpoint(previous_path(p))["model"]["step"] == 10
    raw = p.read_bytes()
    # a flipped byte inside the stored tensor data: torch alone would load wrong values
    flipped = bytearray(raw)
    flipped[len(raw) // 2] ^= 0xFF
    p.write_bytes(bytes(flipped))
    with pytest.raises(CheckpointError, match=r"last.pt is damaged: its SHA-256 does not match.*"
                                              r"last.previous.pt is intact \(iteration 10\)"):
        load_checkpoint(p)
    p.write_bytes(raw[: len(raw) // 3])  # truncated
    with pytest.raises(CheckpointError, match=r"last.pt is damaged: it cannot be read.*last.previous.pt is intact"):
        load_checkpoint(p)
    assert load_checkpoint(previous_path(p))["model"]["step"] == 10  # untouched
    # files written before the checksum (a plain torch.save payload) still load
    legacy = tmp_path / "legacy.pt"
    torch.save({"model": {"step": 5}}, legacy)
    assert load_checkpoint(legacy)["model"]["step"] == 5
    with pytest.raises(CheckpointError, match="has no optimizers.*cannot resume training"):
        load_checkpoint(legacy, require=("model", "optimizers"))


@pytest.mark.slow
def test_resuming_from_a_truncated_checkpoint_is_a_clear_error(tmp_path):
    tr = _trainer(tmp_path, "r", ["optim.iterations=30", "train.checkpoint_every=10"])
    tr.train()  # checkpoints at 10, 20 and the final one at 30
    last = tmp_path / "r" / "checkpoints" / "last.pt"
    last.write_bytes(last.read_bytes()[:1000])
    again = _trainer(tmp_path, "r", ["optim.iterations=40", "train.checkpoint_every=10"])
    with pytest.raises(CheckpointError, match=r"last.pt is damaged.*last.previous.pt is intact \(iteration 20\)"):
        again.train()
    assert load_checkpoint(previous_path(last))["model"]["step"] == 20


@pytest.mark.parametrize("key,value,match", [
    ("train.guard.lr_factor", "0", "lr_factor"), ("train.guard.lr_factor", "1.5", "lr_factor"),
    ("train.guard.snapshot_every", "0", "snapshot_every"), ("train.guard.max_recoveries", "-1", "max_recoveries"),
    ("train.guard.divergence_db", "-2", "divergence_db")])
def test_bad_guard_keys_are_named(tmp_path, key, value, match):
    from stdr.train.trainer import Trainer
    with pytest.raises(ValueError, match=match):
        Trainer(tiny_config(tmp_path, SCHED + [f"{key}={value}"]), tmp_path / "bad")


def test_best_and_last_of_a_curve():
    from stdr.eval.evaluate import best_and_last
    curve = [{"step": 10, "psnr": 20.0, "tag": "periodic"}, {"step": 20, "psnr": float("nan"), "tag": "periodic"},
             {"step": 30, "psnr": 25.0, "tag": "periodic"}, {"step": 40, "psnr": 22.0, "tag": "final"}]
    out = best_and_last(curve)
    assert out["best"]["step"] == 30 and out["best"]["psnr"] == 25.0
    assert out["last"]["step"] == 40 and out["last"]["tag"] == "final"
    assert best_and_last([]) == {"best": None, "last": None}


def test_peak_memory_follows_an_allocation_and_survives_a_resume():
    from stdr.train.guard import Guard
    cpu = torch.device("cpu")
    g = Guard()
    before = g.note_memory(cpu)
    x = mmap.mmap(-1, 256 * 2**20)  # 256 MiB of fresh pages (an allocator would reuse freed ones)
    x[::4096] = b"\1" * (256 * 2**20 // 4096)  # one write a page: all of them resident
    during = g.note_memory(cpu)
    assert during - before > 200 and g.peak_memory_mb == pytest.approx(during)
    x.close()
    g.note_memory(cpu)
    assert g.peak_memory_mb == pytest.approx(during)  # a peak, not the last sample
    h = Guard()
    h.load_state_dict(g.state_dict())
    assert h.peak_memory_mb == g.peak_memory_mb and g.summary(10)["peak_memory_mb"] == g.peak_memory_mb


def _faulty_tensors():
    """Tensors of every checked dtype, with a NaN or an infinity at the start, the middle or the
    end (beyond one work chunk of the compiled check), and clean ones."""
    out = []
    for dtype in (torch.float32, torch.float64, torch.float16, torch.bfloat16):
        for n in (1, 7, 200_003):
            for where in (0, n // 2, n - 1):
                for bad in (float("nan"), float("inf"), -float("inf")):
                    t = torch.linspace(-3e4, 3e4, n).to(dtype)
                    t[where] = bad
                    out.append(t)
            out.append(torch.linspace(-3e4, 3e4, n).to(dtype))
    big = torch.full((1000,), 3.3e38)  # the largest finite values are finite
    return out + [big, -big, torch.tensor([]), torch.zeros(3, 4).t()]  # empty; not contiguous


def test_the_compiled_check_agrees_with_the_torch_one():
    from stdr import extension
    from stdr.train.guard import nonfinite_flags, nonfinite_flags_compiled
    if not extension.available("cpu"):
        pytest.skip("the CPU extension cannot be built here")
    ts = _faulty_tensors()
    checked = [t for t in ts if t.numel()]
    want = nonfinite_flags(checked)
    assert want.sum() > 0 and (~want).sum() > 0
    assert torch.equal(nonfinite_flags_compiled(checked), want)
    assert not nonfinite_flags_compiled([torch.tensor([])]).any()  # empty: nothing to find
    assert all_finite([ts[-4]], compiled=True) and not all_finite([ts[0]], compiled=True)


@pytest.mark.parametrize("backend", ["cpu"] + (["cuda"] if torch.cuda.is_available() and torch.version.cuda else []))
def test_the_compiled_step_update_is_the_torch_one(backend):
    """Guard.flag_step's state over a sequence of steps (clean, faulty, faulty again, clean),
    compiled against the torch operators: the same flag, first faulty step and index."""
    from types import SimpleNamespace

    from stdr import extension
    from stdr.train.guard import Guard
    if not extension.available(backend):
        pytest.skip(f"the {backend} extension cannot be built here")
    bad = torch.ones(5)
    bad[3] = float("nan")
    big = torch.ones(300_000)  # more elements than one block of the CUDA check covers
    big[-1] = float("inf")
    steps = {1: [torch.ones(3), torch.ones(5)], 2: [torch.ones(3), bad], 3: [bad, torch.ones(5)],
             4: [torch.ones(3), torch.ones(5)]}
    steps = {k: [t.to(backend) for t in v] for k, v in steps.items()}
    states = {}
    for compiled_ in (False, True):
        g = Guard(checks=True, sync_free=True, compiled=compiled_, cfg=SimpleNamespace(inject_nan_grad_at=[]))
        seen = []
        for step, (p, q) in steps.items():
            params = {"means": SimpleNamespace(grad=p), "scales": SimpleNamespace(grad=q)}
            state = SimpleNamespace(model=SimpleNamespace(params=params), network_params=lambda: [])
            flag = g.flag_step(state, torch.tensor(0.5, device=backend), step)
            seen.append((float(flag), int(g.bad_step), int(g.bad_index)))
        states[compiled_] = (seen, g.poll())
    assert states[True] == states[False]
    assert states[True][0] == [(0.0, -1, -1), (1.0, 2, 2), (1.0, 2, 2), (1.0, 2, 2)]
    assert states[True][1] == (2, "non-finite grad of scales")
    # a fault at the very end of a large tensor, found by the compiled update alone
    g = Guard(checks=True, sync_free=True, compiled=True, cfg=SimpleNamespace(inject_nan_grad_at=[]))
    params = {"means": SimpleNamespace(grad=torch.ones(3, device=backend)), "scales": SimpleNamespace(grad=big.to(backend))}
    state = SimpleNamespace(model=SimpleNamespace(params=params), network_params=lambda: [])
    g.flag_step(state, torch.tensor(0.5, device=backend), 7)
    assert g.poll() == (7, "non-finite grad of scales")


def test_the_compiled_check_is_the_default_on_the_cpu_and_finds_the_same_fault(tmp_path):
    from stdr import extension
    from stdr.verified import VERIFIED
    if not extension.available("cpu"):
        pytest.skip("the CPU extension cannot be built here")
    assert VERIFIED["train.guard.compiled"] == ("cpu",)  # CPU code: CUDA runs keep the torch operators
    runs = {}
    for key in ("null", "false"):
        tr = _trainer(tmp_path, key, [f"train.guard.compiled={key}", "train.guard.inject_nan_grad_at=[25]"])
        tr.train()
        runs[key] = tr
    assert runs["null"].state.guard.compiled and not runs["false"].state.guard.compiled
    def when(tr):  # each recovery but its clock
        return [{k: v for k, v in r.items() if k != "train_seconds"} for r in tr.state.guard.recoveries]
    assert when(runs["null"]) == when(runs["false"]) and len(when(runs["null"])) == 1
    assert runs["null"].state.guard.recoveries[0]["reason"] == "non-finite grad of means"
    _same_params(runs["null"], runs["false"])


def test_last_reset_is_the_schedule_reset_due_follows():
    """DensifyStrategy.last_reset(step) is the last step <= step at which reset_due fires while
    densifying (counted by brute force over the schedule, white start included)."""
    from stdr.densify.strategy import DensifyStrategy
    for kw in ({"reset_every": 30, "refine_start": 10, "refine_stop": 100},
               {"reset_every": 0, "refine_start": 10, "refine_stop": 100},
               {"reset_every": 30, "refine_start": 10, "refine_stop": 100, "reset_white_at_start": True}):
        s = DensifyStrategy(**kw)
        for white in (False, True):
            state = {"white_background": white}
            fired = [t for t in range(1, 130) if t < s.refine_stop and s.reset_due(t, state)]
            for step in range(1, 130):
                want = max([t for t in fired if t <= step], default=None)
                assert s.last_reset(step, white) == want, (kw, white, step)


def test_an_evaluation_right_after_an_opacity_reset_is_no_divergence(tmp_path):
    """The reset drops the render by design (measured with the reset at 200: 15.9 -> 12.6 dB, back to
    15.0 at 220). With train.guard.after_reset=0 a 2 dB detector takes the drop for a divergence,
    restores, resets again and loses the run; with the window the run trains through, and an
    evaluation far from a reset is still compared."""
    keys = ["optim.iterations=140", "densify.reset_every=120", "train.eval_every=20", "train.guard.divergence_db=2"]
    lost = _trainer(tmp_path, "lost", keys + ["train.guard.after_reset=0"])
    with pytest.raises(TrainingDiverged, match="divergence"):
        lost.train()
    assert {r["found_at"] for r in lost.state.guard.recoveries} == {120}
    tr = _trainer(tmp_path, "kept", keys)  # the default window, 500 steps
    tr.train()
    assert tr.state.guard.recoveries == [] and tr.step == 140
    assert [h["iteration"] for h in tr.state.history if h["tag"] == "periodic"][-2:] == [100, 120]
    assert tr.state.guard.best["step"] < 120  # the evaluations after the reset are neither best nor compared
    tr.state.guard.after_evaluation(tr.state, tr.log, tr.state.guard.best["psnr"] - 10)  # far from a reset: compared
    assert len(tr.state.guard.recoveries) == 1


# ---------------------------------------------------------------- SIGKILL at random moments
# SIGKILL at random moments, some of them inside a checkpoint write: every time the run
# resumes, no file is damaged, and it ends bit-identical to the same run trained without
# interruption. The real command (stdr-train) in a real process on a real disk.
CFG = [*TINY_SCENE, "device=cpu", "model.init_num=300", "eval.lpips=false", "train.progress=false",
       "eval.save_images=false", "train.image_every=0", "eval.fps_repeats=1", "eval.fps_warmup=0",
       "baseline.warmup=50", "train.eval_at_warmup_end=false", "train.threads=1", "optim.iterations=700",
       "train.checkpoint_every=7", "densify.refine_start=20", "densify.refine_every=30"]

#: stdr-train, whose checkpoint writer pauses inside the write (the file written and flushed,
#: not yet renamed into place) when STDR_TEST_PAUSE_IN_WRITE names a marker file to create
KILL_CHILD = r"""
import os, sys, time
import stdr.io.checkpoint as ck
marker = os.environ.get("STDR_TEST_PAUSE_IN_WRITE")
if marker:
    real = ck.os.fsync
    class _Os:
        def __getattr__(self, name):
            return getattr(os, name)
        def fsync(self, fd):
            real(fd)
            open(marker, "w").close()
            time.sleep(600)
    ck.os = _Os()
from stdr.cli.train import main
sys.argv = ["stdr-train", *sys.argv[1:]]
main()
"""

KILLS = 10             # random moments
IN_WRITE = (2, 5, 8)  # of them, those inside a checkpoint write


def _cmd(tmp: Path, run: Path) -> list[str]:
    return [sys.executable, "-c", KILL_CHILD, *CFG, f"data.cache_dir={tmp / 'cache'}", f"hydra.run.dir={run}"]


def _params(run: Path) -> dict:
    return load_checkpoint(run / "checkpoints" / "last.pt")["model"]


def _equal(a, b, where="model") -> None:
    if torch.is_tensor(a):
        assert torch.equal(a, b), where
    elif isinstance(a, dict):
        assert a.keys() == b.keys(), where
        for k in a:
            _equal(a[k], b[k], f"{where}.{k}")


@pytest.mark.slow
def test_sigkill_at_random_moments_resumes_bit_identical_with_no_file_damaged(tmp_path):
    rng = random.Random(20261201)
    run = tmp_path / "run"
    tried = damaged = in_write = 0
    steps = []  # the checkpoint's step after each kill
    for k in range(KILLS):
        marker = tmp_path / f"in_write_{k}"
        env = {**os.environ, **({"STDR_TEST_PAUSE_IN_WRITE": str(marker)} if k in IN_WRITE else {})}
        p = subprocess.Popen(_cmd(tmp_path, run), env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        try:
            if k in IN_WRITE:
                t0 = time.time()
                while not marker.exists():
                    assert p.poll() is None, p.stderr.read().decode()[-2000:]
                    assert time.time() - t0 < 300, "no checkpoint write reached"
                    time.sleep(0.02)
                in_write += 1
            else:  # once this process trains (it has written a checkpoint of its own), at a random moment:
                # a step, the densification, a checkpoint write, wherever it is then
                ck = run / "checkpoints" / "last.pt"
                seen = ck.stat().st_mtime_ns if ck.exists() else None
                t0 = time.time()
                while not ck.exists() or ck.stat().st_mtime_ns == seen:
                    assert p.poll() is None, p.stderr.read().decode()[-2000:]
                    assert time.time() - t0 < 300, "the run wrote no checkpoint"
                    time.sleep(0.01)
                time.sleep(rng.uniform(0.0, 0.8))
            if p.poll() is not None:
                pytest.fail(f"the run ended before kill {k}: {p.stderr.read().decode()[-2000:]}")
            os.kill(p.pid, signal.SIGKILL)
            p.wait(timeout=30)
        finally:
            if p.poll() is None:
                p.kill()
        tried += 1
        if k in IN_WRITE:  # killed with the new checkpoint written but not yet in place
            assert (run / "checkpoints" / ".last.tmp.pt").is_file()
        steps.append(_params(run)["step"] if (run / "checkpoints" / "last.pt").exists() else None)
        for f in (run / "checkpoints" / "last.pt", previous_path(run / "checkpoints" / "last.pt")):
            if f.exists():
                try:
                    load_checkpoint(f)
                except Exception:  # noqa: BLE001 - counted: must stay 0
                    damaged += 1
    final = subprocess.run(_cmd(tmp_path, run), capture_output=True, text=True, timeout=600)
    assert final.returncode == 0, final.stderr[-3000:]
    ref = tmp_path / "ref"
    whole = subprocess.run(_cmd(tmp_path, ref), capture_output=True, text=True, timeout=600)
    assert whole.returncode == 0, whole.stderr[-3000:]
    print(f"[kill] {tried} SIGKILLs ({in_write} inside a checkpoint write), {damaged} damaged files; checkpoint "
          f"steps after each kill {steps}; final step {_params(run)['step']}")
    assert tried == KILLS and in_write == len(IN_WRITE) and damaged == 0
    assert not [p.name for p in (run / "checkpoints").iterdir() if p.name.startswith(".")]
    assert _params(run)["step"] == _params(ref)["step"] == 700
    _equal(_params(run), _params(ref))


# ---------------------------------------------------------------- Ctrl+C and SIGTERM
# The real command in a real process, a real signal: the step in progress is checkpointed, one line
# says where it stopped, the exit code is the signal's (130, 143), and the same command resumes to
# the bits of a run never stopped. A second Ctrl+C stops at once.
STOP_CFG = [c for c in CFG if not c.startswith(("optim.iterations=", "train.checkpoint_every="))] + [
    "optim.iterations=3000", "train.checkpoint_every=0", "train.checkpoint_minutes=0"]


def _stop_cmd(tmp: Path, run: Path, *extra) -> list[str]:
    return [sys.executable, "-m", "stdr.cli.train", *STOP_CFG, f"data.cache_dir={tmp / 'cache'}",
            f"hydra.run.dir={run}", *extra]


def _as_a_terminal_starts_it():
    """The child as a shell starts it: SIGINT at its default, whatever the test process has (a
    pytest-xdist worker ignores SIGINT, and an ignored signal is inherited: Python then installs no
    KeyboardInterrupt handler, and training rightly leaves an ignored Ctrl+C ignored)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _training(p: subprocess.Popen, run: Path, timeout: float = 300) -> None:
    """Wait until the process trains: TensorBoard's first scalars are on the disk (log_every)."""
    t0 = time.time()
    while not any(f.stat().st_size > 200 for f in (run / "tb").glob("events.*")) if (run / "tb").is_dir() else True:
        assert p.poll() is None, p.communicate()[0][-2000:]
        assert time.time() - t0 < timeout, "the run did not start training"
        time.sleep(0.05)


@pytest.mark.slow
@pytest.mark.parametrize("sig, code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_ctrl_c_and_sigterm_checkpoint_the_step_and_the_run_resumes_bit_identical(tmp_path, sig, code):
    run = tmp_path / "run"
    p = subprocess.Popen(_stop_cmd(tmp_path, run), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                         preexec_fn=_as_a_terminal_starts_it)
    try:
        _training(p, run)
        time.sleep(1.0)
        p.send_signal(sig)
        out = p.communicate(timeout=120)[0]
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == code, out[-3000:]
    assert "Traceback" not in out, out[-3000:]
    step = _params(run)["step"]
    assert 0 < step < 3000
    line = [ln for ln in out.splitlines() if ln.startswith("[stdr] stopped at iteration")]
    assert line == [f"[stdr] stopped at iteration {step} of 3000 ({sig.name}); checkpoint "
                    f"{run / 'checkpoints' / 'last.pt'}: the same command resumes from it"], out[-3000:]
    assert not (run / "metrics.json").exists()
    # the same command resumes; it and an uninterrupted run stop a few steps later with the same bits
    stop = [f"train.stop_at={step + 5}"]
    done = subprocess.run(_stop_cmd(tmp_path, run, *stop), capture_output=True, text=True, timeout=600)
    assert done.returncode == 0 and f"resumed from {run / 'checkpoints' / 'last.pt'} at iteration {step}" in done.stdout, \
        done.stdout[-2000:] + done.stderr[-2000:]
    ref = subprocess.run(_stop_cmd(tmp_path, tmp_path / "ref", *stop), capture_output=True, text=True, timeout=600)
    assert ref.returncode == 0, ref.stderr[-2000:]
    _equal(_params(run), _params(tmp_path / "ref"))


@pytest.mark.slow
def test_a_second_ctrl_c_stops_at_once(tmp_path):
    run = tmp_path / "run"
    # the checkpoint write pauses (KILL_CHILD's marker): only a second Ctrl+C can end this process
    marker = tmp_path / "in_write"
    env = {**os.environ, "STDR_TEST_PAUSE_IN_WRITE": str(marker)}
    p = subprocess.Popen([sys.executable, "-c", KILL_CHILD, *_stop_cmd(tmp_path, run)[3:]], env=env,
                         stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, preexec_fn=_as_a_terminal_starts_it)
    try:
        _training(p, run)
        p.send_signal(signal.SIGINT)
        t0 = time.time()
        while not marker.exists():  # the first Ctrl+C: the step ends, its checkpoint is being written
            assert p.poll() is None and time.time() - t0 < 120
            time.sleep(0.02)
        p.send_signal(signal.SIGINT)
        out = p.communicate(timeout=30)[0]
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == 130, out[-3000:]
    assert "Traceback" not in out, out[-3000:]
    assert "[stdr] Ctrl+C again: stopped without a checkpoint" in out, out[-3000:]
    assert not list((run / "checkpoints").glob(".*")), "the unfinished checkpoint write left its temporary file"


@pytest.mark.slow
def test_a_checkpoint_is_written_every_checkpoint_minutes_of_wall_time(tmp_path, monkeypatch):
    """train.checkpoint_minutes bounds what a hard kill loses, whatever checkpoint_every says;
    0 turns it off."""
    from stdr.train import trainer as tr_mod
    sched = ["optim.iterations=30", "baseline.warmup=10", "train.checkpoint_every=0", "train.eval_at_warmup_end=false"]
    clock = {"t": 1000.0}

    def tick():  # every read of the clock is 3 s later: a step takes at least that
        clock["t"] += 3.0
        return clock["t"]
    monkeypatch.setattr(tr_mod, "_clock", tick)
    saves = {}
    for minutes in (0.25, 0):
        t = tr_mod.Trainer(tiny_config(tmp_path, sched + [f"train.checkpoint_minutes={minutes}"]), tmp_path / f"m{minutes}")
        steps = []
        real = t.state.save
        monkeypatch.setattr(t.state, "save", lambda real=real, t=t, steps=steps: (steps.append(t.step), real()))
        t.train()
        saves[minutes] = steps
    assert saves[0] == [30]  # the end only
    assert len(saves[0.25]) >= 4 and saves[0.25][-1] == 30 and all(0 < s < 30 for s in saves[0.25][:-1])


# A launcher's SIGTERM (submitit's in a Slurm job: scancel, a time limit, a preemption send it before
# the kill): training takes it too, checkpoints the step and then writes nothing while it waits for the
# cluster: the warning signal goes to the launcher (a requeue), else it exits 143 after the wait.
LAUNCHER_CHILD = r"""
import signal, sys
def term(signum, frame):
    print("launcher: SIGTERM bypassed", flush=True)
def warn(signum, frame):
    print("launcher: requeued", flush=True)
    sys.exit(0)
signal.signal(signal.SIGTERM, term)
signal.signal(signal.SIGUSR2, warn)
from stdr.cli.train import main
sys.argv = ["stdr-train", *sys.argv[1:]]
main()
"""


@pytest.mark.slow
@pytest.mark.parametrize("then", ["nothing", "warning"])
def test_a_launchers_sigterm_checkpoints_then_waits_for_the_cluster(tmp_path, then):
    run, log = tmp_path / "run", tmp_path / "out.txt"
    env = {**os.environ, "STDR_TERM_WAIT_S": "4" if then == "nothing" else "300"}
    with open(log, "w") as out:
        p = subprocess.Popen([sys.executable, "-c", LAUNCHER_CHILD, *_stop_cmd(tmp_path, run)[3:]], env=env,
                             stdout=out, stderr=subprocess.STDOUT, text=True)
        try:
            _training(p, run)
            p.send_signal(signal.SIGTERM)
            t0 = time.time()
            while "waiting up to" not in log.read_text():
                assert p.poll() is None and time.time() - t0 < 120, log.read_text()[-3000:]
                time.sleep(0.05)
            waiting = time.time()
            if then == "warning":
                p.send_signal(signal.SIGUSR2)
            p.wait(timeout=60)
        finally:
            if p.poll() is None:
                p.kill()
    text = log.read_text()
    assert "launcher: SIGTERM bypassed" in text and "Traceback" not in text, text[-3000:]
    if then == "nothing":
        assert p.returncode == 143 and time.time() - waiting >= 3.0, text[-3000:]
    else:
        assert p.returncode == 0 and "launcher: requeued" in text, text[-3000:]
    step = _params(run)["step"]
    assert 0 < step < 3000 and f"[stdr] stopped at iteration {step} of 3000 (SIGTERM)" in text, text[-3000:]
    assert not [f for d in (run, run / "checkpoints") for f in d.iterdir() if ".tmp" in f.name]
    assert not (run / "metrics.json").exists()


@pytest.mark.parametrize("text", ["abc", "-5", "nan"])
def test_a_bad_term_wait_is_one_line_naming_the_variable_before_training(monkeypatch, text):
    from stdr.errors import ConfigError
    from stdr.train.resume import preemption
    monkeypatch.setenv("STDR_TERM_WAIT_S", text)
    with pytest.raises(ConfigError, match=f"STDR_TERM_WAIT_S='{text}': give the seconds"):
        with preemption():
            pass
