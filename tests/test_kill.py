"""SIGKILL at random moments, some of them inside a checkpoint write: every time the run
resumes, no file is damaged, and it ends bit-identical to the same run trained without
interruption. The real command (stdr-train) in a real process on a real disk."""
from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from stdr.io.checkpoint import load_checkpoint, previous_path
from stdr.testing import TINY_SCENE

CFG = [*TINY_SCENE, "device=cpu", "model.init_num=300", "eval.lpips=false", "train.progress=false",
       "eval.save_images=false", "train.image_every=0", "eval.fps_repeats=1", "eval.fps_warmup=0",
       "baseline.warmup=50", "train.eval_at_warmup_end=false", "train.threads=1", "optim.iterations=700",
       "train.checkpoint_every=7", "densify.refine_start=20", "densify.refine_every=30"]

#: stdr-train, whose checkpoint writer pauses inside the write (the file written and flushed,
#: not yet renamed into place) when STDR_TEST_PAUSE_IN_WRITE names a marker file to create
CHILD = r"""
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

KILLS = 12           # random moments
IN_WRITE = (2, 6, 10)  # of them, those inside a checkpoint write


def _cmd(tmp: Path, run: Path) -> list[str]:
    return [sys.executable, "-c", CHILD, *CFG, f"data.cache_dir={tmp / 'cache'}", f"hydra.run.dir={run}"]


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
