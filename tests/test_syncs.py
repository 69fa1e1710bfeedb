"""Host syncs: the counter itself, and an ordinary training step of every baseline with and
without STDR makes none (so on a GPU its launches never wait for the device), with the guard's
check sync-free or, read every step, its one sync."""
from pathlib import Path

import pytest
import torch

from stdr.syncs import DeviceSyncCounter, SyncCounter, host_only
from stdr.tools.identity_check import NAMES, SCHEDULE, STDR_PHASES


def test_the_counter_sees_each_kind_of_sync_and_where():
    x = torch.arange(6.0)
    with SyncCounter() as sc:
        x.sum().item()
        bool(x[0] > 0)
        float(x[1])
        x.tolist()
        x[x > 2]                  # boolean indexing runs nonzero
        torch.nonzero(x)
        x.index_select(0, torch.tensor([1, 2]))  # not a sync
        torch.where(x > 1, x, 0.0)               # not a sync
        torch.tensor([1.0, 2.0], device=x.device)  # host data copied to the device
        torch.tensor([1.0, 2.0])                   # a host tensor: no copy
        x.new_tensor([3.0])
        x[[0, 2]]                 # a list index: a host index tensor copied over
        x[torch.tensor([1])] = 0.5  # a Python number through a tensor index
        x[1:3] = 0.5                # a fill: not a copy
        torch.linalg.svd(torch.eye(3))  # cuSOLVER checks its flags on the host
        with host_only():
            x.tolist()            # host work by design: counted apart
    assert sc.total == 11
    names = sorted(k.split()[-1] for k, n in sc.sites().items() for _ in range(n))
    assert names == ["__bool__", "__float__", "__getitem__", "__getitem__", "__setitem__", "item", "linalg_svd",
                     "new_tensor", "nonzero", "tensor", "tolist"]
    assert sum(sc.host.values()) == 1
    assert all(k.startswith("(outside the stdr package)") for k in sc.sites())  # made by this test, not by stdr


def _ordinary(step: int) -> bool:
    """Not a refinement, reset, phase switch or snapshot step of the identity check's schedule."""
    return step % 10 != 0 and step not in (1, 20, 21, 30, 31, 40, 41)


def _count(name: str, guard: bool, folder: str, cuda: bool = False, sync_free=None, extra=()):
    """Syncs of each ordinary step of the identity check's schedule (60 steps, every phase):
    those SyncCounter sees, or with `cuda` those the CUDA runtime reports."""
    from stdr.testing import tiny_config
    from stdr.train.trainer import Trainer
    phases = STDR_PHASES if name.endswith("_stdr") else []
    dev = ["device=cuda", "render.backend=cuda", "render.compiled_projection=true"] if cuda else []
    cfg = tiny_config(folder, [f"experiment=embedded_{name}", *SCHEDULE, *phases, "train.log_every=1000", *dev,
                               f"train.guard.enabled={str(guard).lower()}", "train.guard.snapshot_every=1000",
                               *([] if sync_free is None else [f"train.guard.sync_free={str(sync_free).lower()}"]),
                               *extra])
    tr = Trainer(cfg, Path(folder) / "run", splits=("train",))
    counts, sites = [], {}
    while tr.step < cfg.optim.iterations - 1:
        with (DeviceSyncCounter() if cuda else SyncCounter()) as sc:
            tr.train_step()
        if _ordinary(tr.step):
            counts.append(sc.total)
            sites.update(sc.sites())
    assert len(counts) >= 40
    return counts, sites


def _files(sites) -> set[str]:
    return {k.split(":")[0] for k in sites}


# the one sync an ordinary step keeps by design: SC-GS's ARAP term finds its rotations by SVD
SVD_SITE = "stdr/baselines/scgs.py"


@pytest.mark.slow
@pytest.mark.parametrize("name", NAMES)
def test_an_ordinary_training_step_makes_no_host_sync(name, tmp_path):
    counts, sites = _count(name, False, str(tmp_path))
    if name.startswith("scgs"):
        assert {k.split()[-1] for k in sites} == {"linalg_svd"} and _files(sites) == {SVD_SITE}, sites
        assert set(counts) <= {0, 1} and 1 in counts
    else:
        assert sum(counts) == 0, sites


@pytest.mark.slow
@pytest.mark.parametrize("sync_free", [True, False])
def test_the_guards_check_is_sync_free_or_one_sync_a_step(tmp_path, sync_free):
    """The guard checks the loss and gradients before the optimizer runs (docs/performance.md):
    sync-free (the CPU's default), its verdict is a device flag; read every step, one sync."""
    counts, sites = _count("deform_stdr", True, str(tmp_path), sync_free=sync_free)
    if sync_free:
        assert sum(counts) == 0, sites
    else:
        assert set(counts) == {1} and [k.split(":")[0] for k in sites] == ["stdr/train/guard.py"], sites


def test_the_device_counter_counts_nothing_without_cuda_and_restores_the_mode():
    x = torch.arange(4.0)
    with DeviceSyncCounter() as dc:
        x.sum().item()
    if not torch.cuda.is_available():
        assert dc.total == 0 and dc.sites() == {}
    else:
        assert torch.cuda.get_sync_debug_mode() == 0
        y = x.cuda()
        with DeviceSyncCounter() as dc:
            y.sum().item()
            y[y > 1]
        assert dc.total == 2, dc.sites()
        assert torch.cuda.get_sync_debug_mode() == 0


CUDA = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device on this machine")


# where the warning for a sync inside a custom autograd Function's forward (the compiled
# rasterizer's) is attributed: torch's Function.apply
APPLY = "torch/autograd/function.py"


def _short(f: str) -> str:
    return APPLY if f.endswith(APPLY) else f


def _outside(sites) -> set[str]:
    return {_short(f) for f in _files(sites) if not f.startswith("stdr/")}


@CUDA
@pytest.mark.parametrize("name", NAMES)
def test_on_cuda_an_ordinary_step_makes_only_the_rasterizers_syncs(name, tmp_path):
    """The ground truth of the test above: what the CUDA runtime reports as synchronizing is
    the rasterizer's buffer sizes (RASTERIZER_SYNCS, inside compiled code) and, for SC-GS, the
    SVD the CPU test names; nothing else in the stdr package."""
    from stdr.syncs import RASTERIZER_SYNCS
    counts, sites = _count(name, False, str(tmp_path), cuda=True)
    assert _outside(sites) == {APPLY}, sites
    if name.startswith("scgs"):  # the SVD on the steps with the ARAP term
        assert {_short(f) for f in _files(sites)} == {APPLY, SVD_SITE}, sites
        assert min(counts) == RASTERIZER_SYNCS and max(counts) > RASTERIZER_SYNCS, sites
    else:
        assert set(counts) == {RASTERIZER_SYNCS}, sites


@CUDA
@pytest.mark.parametrize("sync_free", [True, False])
def test_on_cuda_the_guard_adds_one_sync_or_none(tmp_path, sync_free):
    """Read every step (CUDA's default until this test has passed on a GPU: stdr.verified.VERIFIED),
    the guard adds one sync; sync-free, none."""
    from stdr.syncs import RASTERIZER_SYNCS
    counts, sites = _count("deform_stdr", True, str(tmp_path), cuda=True, sync_free=sync_free)
    if sync_free:
        assert set(counts) == {RASTERIZER_SYNCS}, sites
        assert not {f for f in _files(sites) if f.startswith("stdr/")}, sites
    else:
        assert set(counts) == {RASTERIZER_SYNCS + 1}, sites
        assert {f for f in _files(sites) if f.startswith("stdr/")} == {"stdr/train/guard.py"}, sites


@CUDA
def test_on_cuda_the_compiled_loss_and_check_add_no_sync(tmp_path):
    """The CUDA kernels of the loss (its gradient read on the device) and of the guard's check
    (before they are CUDA defaults in stdr.verified.VERIFIED) leave an
    ordinary step with the rasterizer's syncs alone, and the guard's fault recovery unchanged."""
    from stdr.syncs import RASTERIZER_SYNCS
    counts, sites = _count("deform_stdr", True, str(tmp_path), cuda=True, sync_free=True,
                           extra=["optim.fused_loss=true", "train.guard.compiled=true"])
    assert set(counts) == {RASTERIZER_SYNCS}, sites
    assert not {f for f in _files(sites) if f.startswith("stdr/")}, sites


@CUDA
@pytest.mark.parametrize("compiled_check", [False, True])
def test_on_cuda_the_sync_free_guard_recovers_a_fault(tmp_path, compiled_check):
    """A NaN gradient on the GPU: fused Adam's found_inf holds every update until the flag is
    read, and the recovery is the one the CPU tests pin (tests/test_guard.py)."""
    from stdr.testing import tiny_config
    from stdr.train.trainer import Trainer
    cfg = tiny_config(tmp_path, ["optim.iterations=40", "baseline.warmup=20", "densify.refine_start=10",
                                 "densify.refine_every=10", "train.checkpoint_every=0", "train.eval_at_warmup_end=false",
                                 "train.guard.snapshot_every=10", "train.guard.inject_nan_grad_at=[15]",
                                 "train.guard.sync_free=true", "device=cuda", "render.backend=cuda",
                                 f"train.guard.compiled={str(compiled_check).lower()}"])
    tr = Trainer(cfg, tmp_path / "run", splits=("train",))
    assert tr.state.guard.compiled == compiled_check
    tr.train()
    (rec,) = tr.state.guard.recoveries
    assert (rec["step"], rec["found_at"], rec["restored_to"], rec["reason"]) == (15, 20, 10, "non-finite grad of means")
    assert tr.step == 40 and all(torch.isfinite(v).all() for v in tr.state.model.params.values())
