"""The compact preset (`compact=on`, stdr/configs/compact/on.yaml): it sets its keys for every
method, yields to explicit keys, trains every baseline with STDR into a pruned model with the
preset's mask form, and `stdr-tool compact` applies it to a trained run by default."""
import json
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from stdr.cli.common import CONFIG_DIR
from stdr.config import experiment_names
from stdr.testing import make_cfg, tiny_config

ON = OmegaConf.load(Path(CONFIG_DIR) / "compact" / "on.yaml")
SCHED = ["optim.iterations=60", "baseline.warmup=10", "stdr.freeze_at=25", "densify.refine_start=10",
         "densify.refine_every=10", "densify.reset_every=0", "densify.refine_stop=40", "densify.prune_big_after=30",
         "train.checkpoint_every=0", "train.eval_at_warmup_end=false", "eval.fps_repeats=1"]


@pytest.mark.parametrize("exp", [e for e in experiment_names() if e.startswith("dnerf_")])
def test_compact_on_sets_the_presets_keys_for_every_method(exp):
    on, off = make_cfg([f"experiment={exp}", "compact=on"]), make_cfg([f"experiment={exp}"])
    assert on.compact == "on" and off.compact == "off"
    assert on.prune.share == ON.prune.share > 0 and list(on.prune.at) == list(ON.prune.at)
    assert on.prune.time_weight == ON.prune.time_weight
    assert on.stdr.mask_bits == OmegaConf.select(ON, "stdr.mask_bits", default=32)
    assert on.stdr.time_bins == OmegaConf.select(ON, "stdr.time_bins", default=0)
    assert off.prune.share == 0 and off.stdr.mask_bits == 32 and off.stdr.time_bins == 0
    # everything else is the method's own
    strip = ("compact", "prune", "stdr")
    assert {k: v for k, v in OmegaConf.to_container(on).items() if k not in strip} == \
        {k: v for k, v in OmegaConf.to_container(off).items() if k not in strip}
    assert on.stdr.enabled == off.stdr.enabled == exp.endswith("_stdr")


def test_an_explicit_key_beats_the_preset_and_an_unknown_option_is_named():
    cfg = make_cfg(["experiment=dnerf_deform_stdr", "compact=on", "prune.share=0.1", "stdr.mask_bits=32"])
    assert cfg.prune.share == 0.1 and cfg.stdr.mask_bits == 32
    with pytest.raises(Exception, match="compact"):
        make_cfg(["compact=yes"])


@pytest.mark.parametrize("baseline", ["deform", "scgs", "spgs", "4dgs"])
def test_the_preset_trains_every_baseline_with_stdr_into_a_pruned_model(tmp_path, baseline):
    from stdr.train.trainer import Trainer
    tr = Trainer(tiny_config(tmp_path, [f"baseline={baseline}", "stdr=on", "compact=on", *SCHED]), tmp_path / "r")
    tr.train()
    share = float(ON.prune.share)
    steps = [e["step"] for e in tr.prune_log]
    assert steps == sorted({40 if a == "refine_stop" else round(float(a) * 60) for a in ON.prune.at})
    for ev in tr.prune_log:  # no densification after step 40: each event alone changes the count
        assert ev["after"] == ev["before"] - int(share * ev["before"])
    assert tr.model.num_gaussians == tr.prune_log[-1]["after"]
    bits = OmegaConf.select(ON, "stdr.mask_bits", default=32)
    assert tr.model.params["stdr_mask"].dtype == (torch.uint8 if bits == 8 else torch.float32)
    assert tr.model.params["stdr_mask"].shape[0] == tr.model.num_gaussians


def test_stdr_tool_compact_applies_the_preset_to_a_trained_run_by_default(tmp_path):
    from stdr.cli.train import run
    from stdr.tools.compact import main
    run(tiny_config(tmp_path, ["stdr=on", *SCHED]), tmp_path / "run")
    before = json.loads((tmp_path / "run" / "metrics.json").read_text())["test"]
    main([str(tmp_path / "run"), "--steps", "5"])
    m = json.loads((tmp_path / "run_compact" / "metrics.json").read_text())["test"]
    # one event removing what the preset's events remove together
    share = 1 - (1 - float(ON.prune.share)) ** len(ON.prune.at)
    assert m["prune"][0]["before"] == before["num_gaussians"]
    assert m["num_gaussians"] == before["num_gaussians"] - int(share * before["num_gaussians"])
    assert m["stdr"]["mask_bits"] == OmegaConf.select(ON, "stdr.mask_bits", default=32)
    saved = OmegaConf.load(tmp_path / "run_compact" / "config.yaml")
    assert saved.prune.time_weight == ON.prune.time_weight
