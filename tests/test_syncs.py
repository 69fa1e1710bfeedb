"""Host syncs: the counter itself, and an ordinary training step of every baseline with and
without STDR makes none (so on a GPU its launches never wait for the device), except the
guard's one per-step finiteness check when the guard is on."""
from pathlib import Path

import pytest
import torch

from stdr.train.syncs import SyncCounter, host_only
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
        with host_only():
            x.tolist()            # host work by design: counted apart
    assert sc.total == 6
    names = sorted(k.split()[-1] for k in sc.sites())
    assert names == ["__bool__", "__float__", "__getitem__", "item", "nonzero", "tolist"]
    assert sum(sc.host.values()) == 1
    assert all(k.startswith("(outside the stdr package)") for k in sc.sites())  # made by this test, not by stdr


def _ordinary(step: int) -> bool:
    """Not a refinement, reset, phase switch or snapshot step of the identity check's schedule."""
    return step % 10 != 0 and step not in (1, 20, 21, 30, 31, 40, 41)


def _count(name: str, guard: bool, folder: str):
    """Syncs of each ordinary step of the identity check's schedule (60 steps, every phase)."""
    from stdr.testing import tiny_config
    from stdr.train.trainer import Trainer
    phases = STDR_PHASES if name.endswith("_stdr") else []
    cfg = tiny_config(folder, [f"experiment=embedded_{name}", *SCHEDULE, *phases, "train.log_every=1000",
                               f"train.guard.enabled={str(guard).lower()}", "train.guard.snapshot_every=1000"])
    tr = Trainer(cfg, Path(folder) / "run", splits=("train",))
    counts, sites = [], {}
    while tr.step < cfg.optim.iterations - 1:
        with SyncCounter() as sc:
            tr.train_step()
        if _ordinary(tr.step):
            counts.append(sc.total)
            sites.update(sc.sites())
    assert len(counts) >= 40
    return counts, sites


@pytest.mark.slow
@pytest.mark.parametrize("name", NAMES)
def test_an_ordinary_training_step_makes_no_host_sync(name, tmp_path):
    counts, sites = _count(name, False, str(tmp_path))
    assert sum(counts) == 0, sites


@pytest.mark.slow
def test_with_the_guard_on_its_check_is_the_one_sync_a_step(tmp_path):
    """The guard checks the loss and gradients before the optimizer runs (docs/performance.md)."""
    counts, sites = _count("deform_stdr", True, str(tmp_path))
    assert set(counts) == {1} and [k.split(":")[0] for k in sites] == ["stdr/train/guard.py"], sites
