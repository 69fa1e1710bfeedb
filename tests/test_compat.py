"""What the renames listed in CHANGELOG.md keep working: a run folder
written by the code before them (tests/data/run_7c77121.tar.xz: main at 7c77121, `stdr-train
experiment=embedded_deform_stdr budget=demo` with the small sizes of RUN_OVERRIDES below, 30 steps;
config.yaml, metrics.json, history.json and the checkpoint as that code wrote them)."""
import json
import sys
import tarfile
from pathlib import Path

import pytest
import torch

FIXTURE = Path(__file__).parent / "data" / "run_7c77121.tar.xz"
RUN_OVERRIDES = ["experiment=embedded_deform_stdr", "budget=demo", "device=cpu", "model.init_num=100",
                 "model.sh_degree=0", "baseline.depth=2", "baseline.width=16", "stdr.field_width=16",
                 "stdr.temporal_dim=4", "stdr.time_bins=8", "baseline.warmup=10", "stdr.warmup_end=15",
                 "stdr.freeze_at=25", "eval.lpips=false", "eval.save_images=false", "train.image_every=0",
                 "train.progress=false"]

def _old_run(tmp_path) -> Path:
    run = tmp_path / "run"
    with tarfile.open(FIXTURE) as tar:
        tar.extractall(run, filter="data")
    cfg = (run / "config.yaml").read_text()  # the machine's own data cache: the procedural scene is made again
    (run / "config.yaml").write_text(cfg.replace("cache_dir: /work/runs/fixture_cache",
                                                 f"cache_dir: {tmp_path / 'cache'}"))
    return run


def test_a_run_folder_from_before_the_renames_loads_and_re_evaluates_to_its_numbers(tmp_path, monkeypatch, capsys):
    from stdr.cli import eval as eval_cli
    from stdr.model import load_model
    run = _old_run(tmp_path)
    first = json.loads((run / "metrics.json").read_text())["test"]
    model = load_model(run / "checkpoints" / "last.pt", "cpu")
    assert model.step == 30 and model.num_gaussians == first["num_gaussians"]
    assert [p.name for p in model.plugins] == ["stdr"] and model.params["stdr_mask"].shape[1] == 8
    monkeypatch.setattr(sys, "argv", ["stdr-eval", str(run), f"out={tmp_path / 'table'}", "eval.lpips=false",
                                      "eval.save_images=false"])
    eval_cli.main()
    capsys.readouterr()
    again = json.loads((run / "metrics.json").read_text())["test"]
    assert set(first) <= set(again), set(first) - set(again)
    # the same model renders the same images (a float tolerance: the fixture was written on another CPU)
    assert again["psnr"] == pytest.approx(first["psnr"], abs=0.02)
    assert again["ssim"] == pytest.approx(first["ssim"], abs=1e-3)
    assert again["curve"][:-1] == first["curve"][:-1] and again["train_seconds"] == first["train_seconds"]


@pytest.mark.slow
def test_a_run_folder_from_before_the_renames_resumes_training(tmp_path, monkeypatch, capsys):
    """The old checkpoint's optimizer, strategy and sampler state load into today's trainer: the
    run goes on from step 30 to 36 and is evaluated. Training longer, and today's defaults where
    the run had others (stdr.mask_after_freeze), are changes a resume names: train.resume=override
    records them; keys renamed since the run was trained are not changes."""
    from stdr.cli import train as train_cli
    run = _old_run(tmp_path)
    monkeypatch.setattr(sys, "argv", ["stdr-train", *RUN_OVERRIDES, f"data.cache_dir={tmp_path / 'cache'}",
                                      "optim.iterations=36", f"hydra.run.dir={run}", "train.resume=override"])
    train_cli.main()
    out = capsys.readouterr().out
    assert "resumed from" in out and "at iteration 30" in out
    m = json.loads((run / "metrics.json").read_text())["test"]
    assert m["config_changes"][0]["step"] == 30
    assert set(m["config_changes"][0]["keys"]) == {"optim.iterations", "stdr.mask_after_freeze"}
    assert m["iterations"] == 36 and torch.isfinite(torch.tensor(m["psnr"]))
