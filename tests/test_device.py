"""The `device` key: every tensor of a run follows it (checked on the CPU with torch's default
device set to 'meta'), and a short run plus a resume on CUDA where a GPU exists."""
import json

import pytest
import torch


from stdr.baselines import BASELINES
from stdr.device import resolve_device
from stdr.testing import tiny_config as _tiny
from stdr.tools import identity_check as _ic


# the schedule of stdr-tool identity-check, which crosses every phase boundary in 60 steps: static
# warm-up, densification with an opacity reset, STDR's three phases, SC-GS's node -> skinning switch
SCHEDULE = [s for s in _ic.SCHEDULE if not s.startswith("optim.iterations=")] + _ic.STDR_PHASES


def test_device_names_resolve_or_fail_with_the_reason():
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    with pytest.raises(ValueError, match="device='gpu0' is not a torch device name"):
        resolve_device("gpu0")
    with pytest.raises(ValueError, match="only cpu and cuda"):
        resolve_device("meta")
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="device=cuda: .*(CPU-only build|sees no GPU).*device=cpu"):
            resolve_device("cuda")


class _DefaultDevice:
    """torch's default device for the `with` block: every tensor created without an explicit
    device lands there. 'meta' tensors hold no data and refuse to mix with real ones, so any
    factory call inside a step that ignores the run's device fails loudly."""

    def __init__(self, device):
        self.device = device
        self.hooks = []

    def __enter__(self):
        torch.set_default_device(self.device)
        # torch's optimizers are torch's code: before 2.13, Adam created a new parameter's step
        # counter on the default device (2.13 says device="cpu"), so their steps run with none
        from torch.optim.optimizer import register_optimizer_step_post_hook, register_optimizer_step_pre_hook
        self.hooks = [register_optimizer_step_pre_hook(lambda *a: torch.set_default_device(None)),
                      register_optimizer_step_post_hook(lambda *a: torch.set_default_device(self.device))]

    def __exit__(self, *exc):
        for h in self.hooks:
            h.remove()
        torch.set_default_device(None)


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(BASELINES))
def test_no_step_creates_a_tensor_on_a_hard_coded_device(tmp_path, name):
    """Training (densification, opacity reset, STDR's phases and field, the baseline's stages),
    a checkpoint, a resume and the evaluation run with the default device set to 'meta', and end
    bit-identical to the same run without it."""
    from stdr.train.trainer import Trainer

    sched = SCHEDULE + [f"experiment=embedded_{name}_stdr", "device=cpu"]
    a = Trainer(_tiny(tmp_path, sched + ["optim.iterations=60"]), tmp_path / "a", splits=("train", "test"))
    a.train()
    Trainer(_tiny(tmp_path, sched + ["optim.iterations=60", "train.stop_at=35"]), tmp_path / "b").train()
    b = Trainer(_tiny(tmp_path, sched + ["optim.iterations=60"]), tmp_path / "b", splits=("train", "test"))
    with _DefaultDevice("meta"):
        b.train()  # resumes at 35 from the checkpoint
        res = b.evaluate_final("test")
    assert b.step == a.step == 60
    for k in a.state.model.params:
        assert b.state.model.params[k].device.type == "cpu" and torch.equal(a.state.model.params[k], b.state.model.params[k]), k
    assert res["psnr"] == pytest.approx(a.evaluate("test")["psnr"], abs=1e-6)
    entry = json.loads((tmp_path / "b" / "metrics.json").read_text())["test"]
    conv = entry["conventions"]
    assert conv["device"] == "cpu" and conv["render_backend"] == b.backend
    assert set(entry["code"]) == {"version", "commit", "dirty"}  # which checkout wrote the numbers


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device on this machine (torch.cuda.is_available() is False)")
@pytest.mark.parametrize("name", sorted(BASELINES))
def test_training_on_cuda_keeps_every_tensor_there_and_resumes(tmp_path, name):
    """device=cuda, every baseline with STDR: parameters, optimizer moments, strategy state, the
    deformation module and STDR's field live on the GPU; the CUDA rasterizer and the CUDA
    projection + SH kernels are used (pinned, so a broken build fails instead of falling back);
    a stopped run resumes on the GPU. The CUDA backward accumulates with atomics, so the resumed
    run is compared within a tolerance."""
    from stdr.train.trainer import Trainer

    sched = SCHEDULE + [f"experiment=embedded_{name}_stdr", "device=cuda", "render.backend=cuda",
                        "render.compiled_projection=true"]
    a = Trainer(_tiny(tmp_path, sched + ["optim.iterations=60"]), tmp_path / "a", splits=("train", "test"))
    assert a.backend == "cuda"
    a.train()
    for k, p in a.state.model.params.items():
        assert p.device.type == "cuda", k
        for v in a.state.optimizers[k].state[p].values():
            assert not torch.is_tensor(v) or v.dim() == 0 or v.device.type == "cuda", k
    assert all(v.device.type == "cuda" for v in a.state.strategy_state.values() if torch.is_tensor(v))
    assert all(p.device.type == "cuda" for p in a.state.model.deform.parameters())
    assert all(p.device.type == "cuda" for p in a.state.model.plugin("stdr").field.parameters())
    assert a.scene.frames("train")[0].image.device.type == "cuda"
    Trainer(_tiny(tmp_path, sched + ["optim.iterations=60", "train.stop_at=35"]), tmp_path / "b").train()
    b = Trainer(_tiny(tmp_path, sched + ["optim.iterations=60"]), tmp_path / "b", splits=("train", "test"))
    b.train()
    assert b.step == 60
    ra, rb = a.evaluate_final("test"), b.evaluate_final("test")
    assert ra["conventions"]["device"].startswith("cuda") and ra["conventions"]["render_backend"] == "cuda"
    assert ra["conventions"]["render_projection"] == "compiled"
    assert abs(ra["psnr"] - rb["psnr"]) < 0.5, (ra["psnr"], rb["psnr"])


# the three speed keys whose CUDA kernels a lent GPU checks (scripts/gpu_check.py's FAST)
SPEED_KEYS = ["optim.fused_loss=true", "train.guard.compiled=true", "train.guard.sync_free=true"]


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device on this machine (torch.cuda.is_available() is False)")
@pytest.mark.parametrize("name", ["deform_stdr", "4dgs"])
def test_training_with_the_speed_keys_on_cuda_through_prunes_resets_and_a_recovery(tmp_path, name):
    """What a long GPU run has and a parity test does not: 150 steps with the three speed keys
    on, through six densifications (clone, split, opacity and size prunes: the model's size
    changes under the kernels), two opacity resets, periodic evaluations in the middle and a guard
    recovery from an injected NaN (the sync-free check flags it, fused Adam skips, the snapshot is
    restored). The run must finish with finite parameters and within 1 dB of the same run with the
    torch forms (CUDA's atomic adds make the two differ in the last bits, then more)."""
    from stdr.train.trainer import Trainer

    sched = SCHEDULE + [f"experiment=embedded_{name}", "device=cuda", "render.backend=cuda",
                        "render.compiled_projection=true", "optim.iterations=150", "densify.refine_stop=90",
                        "train.eval_every=40", "train.guard.snapshot_every=20", "train.guard.inject_nan_grad_at=[57]"]
    runs = {}
    for label, keys in (("fast", SPEED_KEYS), ("torch", [k.replace("=true", "=false") for k in SPEED_KEYS])):
        t = Trainer(_tiny(tmp_path, sched + keys), tmp_path / label, splits=("train", "test"))
        assert (t.fused_loss, t.state.guard.compiled, t.state.guard.sync_free) == ((True,) * 3 if label == "fast" else (False,) * 3)
        t.train()
        torch.cuda.synchronize()
        assert t.step == 150
        assert all(bool(torch.isfinite(p).all()) for p in t.state.model.params.values())
        assert [r["step"] for r in t.state.guard.recoveries] == [57], t.state.guard.recoveries
        runs[label] = t.evaluate("test")["psnr"]
    assert abs(runs["fast"] - runs["torch"]) < 1.0, runs
