"""The compact preset (`compact=on`, stdr/configs/compact/on.yaml): it sets its keys for every
method, yields to explicit keys, trains every baseline with STDR into a pruned model with the
preset's mask form, and `stdr-tool compact` applies it to a trained run by default."""
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import load_script
from omegaconf import OmegaConf

from stdr.config import CONFIG_DIR
from stdr.store import experiment_names
from stdr.model import load_model
from stdr.testing import make_cfg, tiny_config

ON = OmegaConf.load(Path(CONFIG_DIR) / "compact" / "on.yaml")
ROOT = Path(__file__).resolve().parents[1]
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
    assert on.pack.enabled == ON.pack.enabled and dict(on.pack.codecs) == dict(ON.pack.codecs)
    assert on.pack.finetune == ON.pack.finetune and not off.pack.enabled and not off.pack.codecs
    assert on.pack.finetune_state == OmegaConf.select(ON, "pack.finetune_state", default=None) and not off.pack.finetune_state
    # everything else is the method's own
    strip = ("compact", "prune", "stdr", "pack")
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
    steps = [e["step"] for e in tr.state.prune_log]
    assert steps == sorted({40 if a == "refine_stop" else round(float(a) * 60) for a in ON.prune.at})
    for ev in tr.state.prune_log:  # no densification after step 40: each event alone changes the count
        assert ev["after"] == ev["before"] - int(share * ev["before"])
    assert tr.state.model.num_gaussians == tr.state.prune_log[-1]["after"]
    bits = OmegaConf.select(ON, "stdr.mask_bits", default=32)
    assert tr.state.model.params["stdr_mask"].dtype == (torch.uint8 if bits == 8 else torch.float32)
    assert tr.state.model.params["stdr_mask"].shape[0] == tr.state.model.num_gaussians


@pytest.mark.parametrize("gated", [False, True])
def test_stdr_tool_compact_applies_the_preset_to_a_trained_run_by_default(tmp_path, gated):
    from stdr.train.run import run_training as run
    from stdr.tools.compact_run import main
    from stdr.compact.pack import spec_of_config
    run(tiny_config(tmp_path, ["stdr=on", *SCHED, f"stdr.mask_after_freeze={str(gated).lower()}"]), tmp_path / "run")
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
    # the compact file in the preset's codecs; a run whose mask still gates opacity after the freeze
    # cannot store the derived form and gets the 8-bit mask (exact: the run now stores it in 8 bits)
    used = json.loads((tmp_path / "run_compact" / "pack.json").read_text())["spec"]
    want = spec_of_config(ON.pack)
    for k in ("means", "scales", "quats", "opacities", "sh0", "shN"):
        assert used[k] == want[k], k
    assert used["stdr_mask"] == ("raw" if gated else want["stdr_mask"])  # raw: the uint8 mask as it is
    small = load_model(tmp_path / "run_compact" / "model.stdrc", "cpu")
    assert ("stdr_mask" in small.params) == gated and ("stdr_cond" in small.params) == (not gated)


def test_the_presets_file_codecs_are_what_the_bytes_study_chose():
    """compact=on's `pack` section is the codecs research/measurements/compact_bytes/decision.json chose
    (steps 1-3), with the state candidate research/measurements/compact_state/decision.json chose for
    every method (amendment 2's preset, when it names one): one spec for every method. On a model
    without a 4DGS grid or an STDR mask the entries for them change nothing, so each method's file
    is what the studies measured for it."""
    from stdr.compression.file import encode_model
    from stdr.model import build_model
    from stdr.compact.pack import spec_of_config
    study = load_script(ROOT / "studies" / "compact_bytes.py", "compact_bytes_study")
    dec = json.loads((ROOT / "research" / "measurements" / "compact_bytes" / "decision.json").read_text())
    assert dec["complete"] and dec["step3_measured"]
    state = json.loads((ROOT / "research" / "measurements" / "compact_state" / "decision.json").read_text())
    cs = load_script(ROOT / "studies" / "compact_state.py", "compact_state_study")
    extra = dict(cs.CANDIDATES.get(state["preset"], {}))
    # amendment 3: 4DGS's grid in 4 bits with its quantization-aware fine-tune, when adopted
    grid4 = (state.get("grid4") or {}).get("adopted")
    if grid4:
        extra.update({k: v for k, v in cs.GRID4["s8wg4ft"].items() if k in ("state:grids", "finetune_state")})
    preset = spec_of_config(ON.pack)
    assert ON.pack.enabled and preset == {**study.chosen_spec("dnerf_4dgs_stdr", dec)[1], **extra}
    for b in ("deform", "scgs", "spgs", "4dgs"):
        cfg = make_cfg([f"experiment=dnerf_{b}", "compact=on"])
        torch.manual_seed(0)
        model = build_model(cfg, np.linspace(0, 1, 8), torch.zeros(3), torch.device("cpu"),
                            torch.rand(300, 3), torch.rand(300, 3))
        a, c = encode_model(model, preset), encode_model(model, {**study.chosen_spec(f"dnerf_{b}", dec)[1], **extra})
        assert _flat(a["model"]) == _flat(c["model"]), b
        grid_codecs = {v for k, v in _flat(a["model"]).items() if ".grids." in k and k.endswith("codec")}
        assert grid_codecs == ({"q4" if grid4 else "q8"} if b == "4dgs" else set()), b


def _flat(x, p=""):
    """A payload as {dotted path: value}, tensors as (dtype, shape, their bytes)."""
    if isinstance(x, torch.Tensor):
        return {p: (str(x.dtype), tuple(x.shape), x.reshape(-1).contiguous().view(torch.uint8).numpy().tobytes())}
    if isinstance(x, dict):
        return {q: v for k, y in x.items() for q, v in _flat(y, f"{p}.{k}").items()}
    if isinstance(x, (list, tuple)):
        return {q: v for i, y in enumerate(x) for q, v in _flat(y, f"{p}.{i}").items()}
    return {p: x}


def test_the_preset_refuses_a_gated_stdr_run_before_training_and_names_the_fix(tmp_path):
    """STDR's derived form needs stdr.mask_after_freeze=false: with true the preset's run stops at
    its start (no training), and the message names the 8-bit mask's key; that key then trains."""
    from stdr.train.run import run_training as run
    gated = ["stdr=on", "compact=on", *SCHED, "stdr.mask_after_freeze=true"]
    with pytest.raises(ValueError, match=r"pack.codecs: stdr_mask=derived .*stdr_mask=q8"):
        run(tiny_config(tmp_path, gated), tmp_path / "gated")
    assert not (tmp_path / "gated" / "metrics.json").exists()
    cfg = tiny_config(tmp_path, [*gated, "pack.codecs.stdr_mask=q8", "pack.finetune=20"])
    run(cfg, tmp_path / "ok")
    assert json.loads((tmp_path / "ok" / "pack.json").read_text())["spec"]["stdr_mask"] == "raw"  # the uint8 mask
