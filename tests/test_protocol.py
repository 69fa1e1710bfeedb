"""Evaluation protocol: the test split never steers training, and a "+STDR vs plain" comparison
changes the plug-in and nothing else."""
import shutil

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf
from PIL import Image
from stdr.data.load import scene_folder
from stdr.baselines import BASELINES
from stdr.testing import make_cfg, tiny_config
from stdr.train.guard import monitor_split

# periodic evaluation on the test split, the detector on and as touchy as it gets
SCHED = ["optim.iterations=40", "baseline.warmup=10", "densify.refine_start=10", "densify.refine_every=10",
         "train.checkpoint_every=0", "train.guard.snapshot_every=10", "train.eval_every=10",
         "data.eval_split=test", "train.guard.divergence_db=0.001"]


def _copy_with_test_images(src, dst, black: bool):
    shutil.copytree(src, dst)
    if black:  # the test images only: opaque black (the scene's background is white, so the
        # better the model, the further its renders from these)
        for png in sorted((dst / "test").glob("*.png")):
            a = np.asarray(Image.open(png)).copy()
            a[..., :3], a[..., 3] = 0, 255
            Image.fromarray(a).save(png)
    return dst


@pytest.mark.slow
def test_test_images_cannot_steer_training(tmp_path):
    """Two copies of a scene that differ only in their test images train bit-identically, with
    periodic evaluation on the test split and the divergence detector on; the detector reads
    the val split, and the test evaluations still differ (the test images do reach the curve)."""
    from stdr.train.trainer import Trainer

    src = scene_folder(tiny_config(tmp_path).data)
    runs = {}
    for name, black in (("same", False), ("black", True)):
        folder = _copy_with_test_images(src, tmp_path / f"scene_{name}", black)
        cfg = tiny_config(tmp_path, SCHED + ["data.format=dnerf", f"data.path={folder}"])
        tr = Trainer(cfg, tmp_path / name)
        tr.train()
        runs[name] = tr
    a, b = runs["same"], runs["black"]
    assert a.monitor == b.monitor == "val" and a.step == b.step == 40
    # recorded: in the checkpoint (so stdr-eval's re-evaluation reports it) and metrics.json's guard
    from stdr.io.checkpoint import load_checkpoint
    from stdr.train.guard import Guard
    g = Guard()
    g.load_state_dict(load_checkpoint(tmp_path / "same" / "checkpoints" / "last.pt")["guard"])
    assert g.summary(None)["monitor"] == "val" and a.state.guard.summary(None)["monitor"] == "val"
    for k in a.state.model.params:
        assert torch.equal(a.state.model.params[k], b.state.model.params[k]), k
    for (ka, va), (kb, vb) in zip(a.state.model.deform.state_dict().items(), b.state.model.deform.state_dict().items()):
        assert ka == kb and torch.equal(va, vb), ka
    # the detector's evaluations: the val split, at the periodic steps, identical in both runs
    guard = [[(h["iteration"], h["psnr"]) for h in tr.state.history if h["tag"] == "guard"] for tr in (a, b)]
    assert [s for s, _ in guard[0]] == [10, 20, 30] and guard[0] == guard[1]
    assert all(h["split"] == "val" for h in a.state.history if h["tag"] == "guard")
    # the curve on the test split did see the different images
    test_a = [h["psnr"] for h in a.state.history if h["split"] == "test"]
    test_b = [h["psnr"] for h in b.state.history if h["split"] == "test"]
    assert len(test_a) == len(test_b) >= 3 and all(abs(x - y) > 1.0 for x, y in zip(test_a, test_b))
    # and a detector that read them would have restored an earlier state in one run only
    assert all(y > x for x, y in zip(test_a, test_a[1:])) and any(y < x for x, y in zip(test_b, test_b[1:]))


def test_the_detector_never_reads_the_test_split():
    g = OmegaConf.create({"monitor": "auto"})
    assert monitor_split(g, "dnerf") == "val" and monitor_split(g, "procedural") == "val"
    assert monitor_split(g, "nerfies") == "train"  # its val frames are its test frames
    with pytest.raises(ValueError, match=r"train\.guard\.monitor=test: .*use auto, val or train"):
        monitor_split(OmegaConf.create({"monitor": "test"}), "dnerf")
    with pytest.raises(ValueError, match=r"train\.guard\.monitor=val: data\.format=nerfies has no val split"):
        monitor_split(OmegaConf.create({"monitor": "val"}), "nerfies")
    with pytest.raises(ValueError, match=r"train\.guard\.monitor='best'"):
        monitor_split(OmegaConf.create({"monitor": "best"}), "dnerf")


def test_a_run_without_periodic_evaluation_has_no_detector(tmp_path):
    """The default (train.eval_every=0): nothing for the detector to compare, no extra split."""
    from stdr.train.trainer import Trainer
    tr = Trainer(tiny_config(tmp_path, ["optim.iterations=1", "baseline.warmup=0"]), tmp_path / "run")
    assert tr.monitor is None and "val" not in tr.scene.splits


def _flat(d, prefix=""):
    out = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(_flat(v, key + "."))
        else:
            out[key] = v
    return out


@pytest.mark.parametrize("baseline", sorted(BASELINES))
def test_plain_and_stdr_experiments_differ_only_in_stdr_keys(baseline):
    """experiment=<data>_<b>_stdr against <data>_<b>, for every data option and budget: only
    stdr.* keys, the experiment's name and the STDR phases of the derived schedule differ."""
    from stdr.store import data_options
    for data in data_options():
        for budget in ("demo", "cpu", "paper"):
            plain, stdr = (_flat(OmegaConf.to_container(make_cfg([f"experiment={data}_{baseline}{s}",
                                                                  f"budget={budget}"]), resolve=True))
                           for s in ("", "_stdr"))
            # the plug-in's resolved phases are the only keys the plain config lacks
            assert set(stdr) - set(plain) == {"schedule.stdr_warmup_end", "schedule.stdr_freeze_at",
                                              "schedule.stdr_freeze_moved"} and set(plain) <= set(stdr)
            diff = sorted(k for k in plain if plain[k] != stdr[k])
            assert "stdr.enabled" in diff and stdr["name"] == plain["name"] + "_stdr", (data, budget)
            outside = [k for k in diff if not (k.startswith("stdr.") or k == "name"
                                               or k.startswith("schedule.stdr_")
                                               or k in ("schedule.events", "schedule.notes"))]
            assert outside == [], (data, budget, {k: (plain[k], stdr[k]) for k in outside})
            # the printed schedule: the plain run's events, plus STDR's phases (each names its stdr.* key)
            extra = [e for e in stdr["schedule.events"] if e not in plain["schedule.events"]]
            assert [e for e in stdr["schedule.events"] if e in plain["schedule.events"]] == plain["schedule.events"]
            assert extra and all(e.endswith("[stdr]") or "[stdr." in e for e in extra), (data, budget, extra)
            notes = [n for n in stdr["schedule.notes"] if n not in plain["schedule.notes"]]
            assert [n for n in stdr["schedule.notes"] if n in plain["schedule.notes"]] == plain["schedule.notes"]
            assert all(n.startswith("STDR") for n in notes), (data, budget, notes)
