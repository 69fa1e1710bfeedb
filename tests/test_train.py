"""End-to-end: config composition, training on the embedded scene, exact resume, stdr-eval."""
import json
import os
import shutil
import subprocess
import sys

import pytest
import torch
from stdr.train.run import run_training as run
from stdr.device import resolve_device
from stdr.testing import make_cfg
from stdr.testing import tiny_config as _tiny


def test_configs_compose_for_every_experiment_and_budget():
    cpu = make_cfg(["experiment=dnerf_deform", "budget=cpu", "data.path=/x"])
    paper = make_cfg(["experiment=dnerf_deform", "budget=paper", "data.path=/x"])
    assert cpu.name == paper.name == "dnerf_deform"
    assert cpu.data.format == "dnerf" and cpu.budget == "cpu" and paper.budget == "paper"
    assert paper.optim.iterations == 40000 and paper.baseline.width == 256 and paper.baseline.depth == 8
    assert paper.model.init_num == 100000 and paper.data.max_width is None
    assert cpu.optim.iterations < paper.optim.iterations and cpu.data.max_width == 200
    for ds, fmt_scale in (("nerfds", 1), ("hypernerf", 2)):
        for suffix, enabled in (("", False), ("_stdr", True)):
            c = make_cfg([f"experiment={ds}_deform{suffix}", "data.path=/x"])
            assert c.name == f"{ds}_deform{suffix}" and c.stdr.enabled == enabled
            assert c.data.format == "nerfies" and c.data.split_mode == "ids" and c.data.image_scale == fmt_scale
            assert c.model.init == "points" and c.data.background == "black"
    for base in ("scgs", "spgs", "4dgs"):  # every experiment of every baseline: tests/test_registry.py
        p, cpu = (make_cfg([f"experiment=dnerf_{base}", f"budget={b}", "data.path=/x"]) for b in ("paper", "cpu"))
        assert p.optim.iterations > cpu.optim.iterations and p.baseline.warmup > cpu.baseline.warmup
    assert make_cfg(["experiment=dnerf_scgs", "budget=paper", "data.path=/x"]).optim.iterations == 80000
    assert make_cfg(["experiment=dnerf_4dgs", "budget=paper", "data.path=/x"]).optim.lambda_dssim == 0.0
    interp = make_cfg(["experiment=hypernerf_deform", "data=hypernerf_interp", "data.path=/x"])
    assert interp.data.split_mode == "interp" and interp.name == "hypernerf_deform"
    demo = make_cfg([])
    assert demo.name == "embedded_deform" and demo.budget == "demo" and demo.data.format == "procedural"


@pytest.mark.slow
def test_resume_gives_the_same_result_as_an_uninterrupted_run(tmp_path):
    sched = ["optim.iterations=60", "baseline.warmup=20", "densify.refine_start=10",
             "densify.refine_every=10", "densify.reset_every=30", "densify.prune_big_after=30",
             "train.checkpoint_every=0", "train.eval_at_warmup_end=false"]
    from stdr.train.trainer import Trainer
    a = Trainer(_tiny(tmp_path, sched), tmp_path / "a")
    a.train()
    # the interrupted run also evaluates every 10 steps (a learning curve): evaluation must not
    # change training either
    curve = ["train.eval_every=10", "train.eval_frames=2"]
    b1 = Trainer(_tiny(tmp_path, sched + curve + ["train.stop_at=35"]), tmp_path / "b")
    b1.train()  # stops at 35 (after densification, warm-up end and an opacity reset)
    b2 = Trainer(_tiny(tmp_path, sched + curve), tmp_path / "b")
    b2.train()  # resumes from b/checkpoints/last.pt
    assert b2.step == a.step == 60
    # the curve survives the resume: steps 10..50 from both halves, training seconds increasing
    pts = [h for h in b2.state.history if h["tag"] == "periodic"]
    assert [h["iteration"] for h in pts] == [10, 20, 30, 40, 50] and all(h["frames"] == 2 for h in pts)
    secs = [h["train_seconds"] for h in pts]
    assert secs == sorted(secs) and secs[-1] < b2.state.train_seconds
    for k in a.state.model.params:
        assert torch.equal(a.state.model.params[k], b2.state.model.params[k]), k
    for (ka, va), (kb, vb) in zip(a.state.model.deform.state_dict().items(), b2.state.model.deform.state_dict().items()):
        assert torch.equal(va, vb), ka


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """One 900-step run on the tiny embedded scene (periodic evaluations every 300 steps), shared
    by the tests below; a test that changes the run works on its own copy (`_copy`)."""
    root = tmp_path_factory.mktemp("trained")
    cfg = _tiny(root, ["optim.iterations=900", "baseline.warmup=300", "densify.refine_stop=700",
                       "densify.grow_grad2d=1e-4", "baseline.head_init_std=1e-5", "train.eval_every=300",
                       "train.eval_frames=2"])
    res = run(cfg, root / "run")
    return root / "run", res, json.loads((root / "run" / "metrics.json").read_text())["test"]


def _copy(run_dir, tmp_path):
    dst = tmp_path / "run"
    shutil.copytree(run_dir, dst)
    return dst


def _eval(run_dir, out, *args):
    return subprocess.run([sys.executable, "-m", "stdr.cli.eval", str(run_dir), f"out={out}", *args],
                          capture_output=True, text=True, timeout=600)


@pytest.mark.slow
def test_training_beats_static_warmup_and_writes_its_outputs(trained):
    run_dir, res, test = trained
    for k in ("psnr", "ssim", "lpips", "fps", "num_gaussians", "train_seconds", "iterations"):
        assert k in test
    assert test["iterations"] == 900 and test["psnr"] == res["psnr"]
    hist = json.loads((run_dir / "history.json").read_text())
    warm = [h for h in hist if h["tag"] == "static_warmup"][0]
    assert test["psnr"] > warm["psnr"] + 2.0, (warm["psnr"], test["psnr"])
    assert (run_dir / "point_cloud.ply").is_file() and (run_dir / "checkpoints" / "last.pt").is_file()
    assert list((run_dir / "tb").glob("events.out.tfevents.*"))
    assert test["conventions"]["device"] == str(resolve_device("auto"))
    assert test["conventions"]["machine"] and test["model_mb"] > 0
    # the model's size: every float32 tensor of the model (Gaussians, network, plug-ins), at least
    # the Gaussians' own 59 floats each
    assert test["model_mb"] * 2 ** 20 >= test["num_gaussians"] * 59 * 4
    # the training's CPU seconds next to its wall seconds: how much of the machine it had
    assert 0 < test["train_cpu_seconds"] and 0 < test["train_cpu_utilization"] <= 1.2
    assert test["seen_per_frame"] is not None and 0 < test["seen_per_frame"] <= 1


@pytest.mark.slow
def test_the_learning_curve_holds_the_evaluations_and_ends_with_the_final_metrics(trained):
    _, _, test = trained
    # the warm-up's and the periodic evaluations on a fixed 2-frame subset, then the final
    # metrics (all 4 test frames) as its last point
    curve = test["curve"]
    assert [(p["step"], p["tag"], p["frames"]) for p in curve] == \
        [(300, "static_warmup", 2), (600, "periodic", 2), (900, "final", 4)]
    assert [curve[-1][k] for k in ("psnr", "ssim", "lpips", "num_gaussians", "train_seconds")] == \
        [test[k] for k in ("psnr", "ssim", "lpips", "num_gaussians", "train_seconds")]
    assert curve[0]["train_seconds"] < curve[1]["train_seconds"] < curve[2]["train_seconds"]
    # the FPS is the median of eval.fps_repeats (default 3) timed passes, all of them kept
    assert len(test["fps_passes"]) == 3 and test["fps"] == sorted(test["fps_passes"])[1]


@pytest.mark.slow
def test_stdr_eval_reproduces_the_metrics_from_the_checkpoint_and_writes_tables(trained, tmp_path):
    run_dir = _copy(trained[0], tmp_path)
    test = trained[2]
    out = tmp_path / "tables"
    proc = _eval(run_dir, out, "eval.lpips=false", "device=cpu")  # on the device it is told
    assert proc.returncode == 0, proc.stderr[-3000:]
    again = json.loads((run_dir / "metrics.json").read_text())["test"]
    assert again["conventions"]["device"] == "cpu"
    # re-evaluation keeps the training's curve and ends it with its own (equal) final point
    assert [p["step"] for p in again["curve"]] == [300, 600, 900] and again["curve"][:2] == test["curve"][:2]
    assert again["curve"][-1]["psnr"] == again["psnr"] == pytest.approx(test["psnr"], abs=1e-4)
    table = json.loads((out / "table.json").read_text())
    assert table["cells"]["deform"]["embedded"]["psnr"] == pytest.approx(test["psnr"], abs=1e-4)
    assert "| deform |" in (out / "table.md").read_text()
    assert (out / "table.tex").read_text().startswith("\\begin{tabular}")


@pytest.mark.slow
def test_remeasure_fps_retimes_the_renders_only(trained, tmp_path):
    """fps and its passes change, the old values go to fps_history, every quality number and the
    curve stay as they were, and the table shows the new fps."""
    run_dir, out = _copy(trained[0], tmp_path), tmp_path / "tables"
    before = trained[2]
    proc = _eval(run_dir, out, "remeasure=fps", "eval.fps_repeats=5", "device=cpu")
    assert proc.returncode == 0, proc.stderr[-3000:]
    after = json.loads((run_dir / "metrics.json").read_text())["test"]
    assert after["fps_history"] == [{"fps": before["fps"], "fps_passes": before["fps_passes"],
                                     "machine": before["conventions"]["machine"],
                                     "torch_threads": before["conventions"]["torch_threads"],
                                     "render_backend": before["conventions"]["render_backend"],
                                     "device": before["conventions"]["device"], "render_cull": "eval",
                                     "active_gaussians_mean": before["active_gaussians_mean"]}]
    assert after["fps"] > 0 and after["conventions"]["fps_remeasured"] is True
    assert len(after["fps_passes"]) == 5 and after["fps"] == sorted(after["fps_passes"])[2]
    timing = ("fps", "fps_passes", "fps_history", "conventions")
    assert {k: v for k, v in after.items() if k not in timing} == \
        {k: v for k, v in before.items() if k not in timing}
    assert {k: v for k, v in after["conventions"].items() if not k.startswith("fps_")} == before["conventions"]
    assert json.loads((out / "table.json").read_text())["cells"]["deform"]["embedded"]["fps"] == \
        pytest.approx(after["fps"])


@pytest.mark.slow
def test_a_render_key_given_to_stdr_eval_changes_the_fps_setting_only(trained, tmp_path):
    """Here FPS without temporal culling: the rows counted are those that setting renders, all of
    them, and the history says which setting the earlier FPS had."""
    run_dir = _copy(trained[0], tmp_path)
    proc = _eval(run_dir, tmp_path / "tables", "remeasure=fps", "render.cull=off", "device=cpu")
    assert proc.returncode == 0, proc.stderr[-3000:]
    after = json.loads((run_dir / "metrics.json").read_text())["test"]
    assert after["conventions"]["fps_render_cull"] == "off" and len(after["fps_history"]) == 1
    assert after["render_cull"] == "off" and after["active_gaussians_mean"] == after["num_gaussians"]
    assert after["fps_history"][-1]["render_cull"] == "eval"


@pytest.mark.slow
def test_remeasure_size_fills_model_mb_only_and_bad_remeasure_values_are_errors(trained, tmp_path):
    run_dir, out = _copy(trained[0], tmp_path), tmp_path / "tables"
    m = json.loads((run_dir / "metrics.json").read_text())
    del m["test"]["model_mb"]
    (run_dir / "metrics.json").write_text(json.dumps(m))
    proc = _eval(run_dir, out, "remeasure=size", "device=cpu")
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert json.loads((run_dir / "metrics.json").read_text())["test"] == trained[2]
    proc = _eval(run_dir, out, "remeasure=fps", "eval.fps_repeats=0", "device=cpu")
    assert proc.returncode != 0 and "eval.fps_repeats=0" in proc.stderr
    proc = _eval(run_dir, out, "remeasure=psnr")
    assert proc.returncode != 0 and "remeasure='psnr'" in proc.stderr


def test_stdr_eval_render_keys_change_only_themselves():
    """`stdr-eval RUN render.X=...` sets X in the run's own render config; the run's other render
    keys (here antialiasing) are kept, never reset to the defaults."""
    from omegaconf import OmegaConf

    from stdr.cli.eval import apply_overrides
    from stdr.config import EvalAppConfig
    from stdr.store import load_config
    from stdr.testing import tiny_config as _t
    cfg = load_config(OmegaConf.to_container(_t("/tmp/unused", ["render.antialiased=true", "render.eps2d=0.1",
                                                               "stdr.lambda_temp=0.5"])))
    app = OmegaConf.merge(OmegaConf.structured(EvalAppConfig), {"render": {"cull": "off"}})
    assert app.render.backend is None and app.render.cull == "off"
    apply_overrides(cfg, "render", app.render)
    assert cfg.render.cull == "off" and cfg.render.antialiased is True and cfg.render.eps2d == 0.1
    assert cfg.stdr.lambda_temp == 0.5  # the run's other keys are its own
    with pytest.raises(Exception, match="stdr"):  # training keys cannot be changed at evaluation
        OmegaConf.merge(OmegaConf.structured(EvalAppConfig), {"stdr": {"lambda_temp": 0.1}})
    with pytest.raises(Exception, match="tile_sizes"):
        OmegaConf.merge(OmegaConf.structured(EvalAppConfig), {"render": {"tile_sizes": 8}})


@pytest.mark.parametrize("user", [{}, {"MKL_CBWR": "COMPATIBLE", "MKL_DYNAMIC": "TRUE"}])
def test_stdr_train_sets_mkl_reproducibility_conditions_before_its_first_call(user):
    """stdr-train's entry sets oneMKL's reproducibility conditions (MKL_CBWR=AUTO,STRICT, a
    fixed thread count: MKL's dynamic threading off): MKL_VERBOSE then reports CNR:AUTO and Dyn:0
    for a GEMM, with torch's thread count left alone (where MKL's default is Dyn:1). A user's
    values are kept."""
    if "blas_info=mkl" not in torch.__config__.show().lower():
        pytest.skip("this torch does not use MKL for BLAS")
    env = {k: v for k, v in os.environ.items() if k not in ("MKL_CBWR", "MKL_DYNAMIC")}
    env.update(user, MKL_VERBOSE="1")
    code = ("from stdr.cli.common import reproducible_blas; reproducible_blas(); import torch; "
            "a = torch.randn(300, 300); a @ a")
    proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    words = (proc.stdout + proc.stderr).split()
    assert {w for w in words if w.startswith("CNR:")} == {f"CNR:{user.get('MKL_CBWR', 'AUTO,STRICT')}"}
    assert {w for w in words if w.startswith("Dyn:")} == {"Dyn:1" if user else "Dyn:0"}


def test_the_stdr_train_command_runs_with_mkl_reproducibility_and_records_it(tmp_path):
    from stdr.testing import TINY_SCENE
    env = {k: v for k, v in os.environ.items() if k not in ("MKL_CBWR", "MKL_DYNAMIC")}
    over = TINY_SCENE + [f"data.cache_dir={tmp_path / 'cache'}", "device=cpu", "model.init_num=500",
                         "eval.lpips=false", "train.progress=false", "eval.save_images=false",
                         "train.image_every=0", "optim.iterations=20", "baseline.warmup=10",
                         f"hydra.run.dir={tmp_path / 'run'}"]
    proc = subprocess.run([sys.executable, "-m", "stdr.cli.train", *over], env=env, capture_output=True,
                          text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    conv = json.loads((tmp_path / "run" / "metrics.json").read_text())["test"]["conventions"]
    assert conv["mkl_cbwr"] == "AUTO,STRICT" and conv["mkl_dynamic"] == "FALSE"


def test_stdr_eval_reevaluation_keeps_every_field_of_the_training_entry(tmp_path, monkeypatch, capsys):
    """One builder of a split's metrics.json entry for stdr-train and stdr-eval: re-evaluating a
    trained run leaves every key of the first entry in place, with the same values except what is
    measured again (timings, the code stamp) and the curve's last point (this evaluation)."""
    from stdr.cli import eval as eval_cli
    from stdr.cli import train as train_cli
    from stdr.testing import TINY_SCENE
    run = tmp_path / "run"
    monkeypatch.setattr(sys, "argv", ["stdr-train", "experiment=embedded_deform_stdr", *TINY_SCENE,
                                      f"data.cache_dir={tmp_path / 'cache'}", "device=cpu", "model.init_num=500",
                                      "eval.lpips=false", "train.progress=false", "eval.save_images=false",
                                      "train.image_every=0", "optim.iterations=40", "baseline.warmup=10",
                                      "stdr.warmup_end=15", "stdr.freeze_at=25", f"hydra.run.dir={run}"])
    train_cli.main()
    first = json.loads((run / "metrics.json").read_text())["test"]
    history = json.loads((run / "history.json").read_text())
    assert first["train_loss"] in ("compiled", "torch") and first["train_cpu_seconds"] > 0
    assert 0 < first["train_cpu_utilization"] <= 1.5
    monkeypatch.setattr(sys, "argv", ["stdr-eval", str(run), f"out={tmp_path / 'table'}", "eval.lpips=false",
                                      "eval.save_images=false"])
    eval_cli.main()
    capsys.readouterr()
    again = json.loads((run / "metrics.json").read_text())["test"]
    assert set(first) <= set(again), set(first) - set(again)
    # the learning curve on disk keeps the training's evaluations and gains this one
    again_history = json.loads((run / "history.json").read_text())
    assert again_history[:-1] == history and again_history[-1]["tag"] == "final"
    assert again_history[-1]["psnr"] == again["psnr"] and again["curve"][-1]["psnr"] == again["psnr"]
    remeasured = {"fps", "fps_passes", "render_seconds", "frame_seconds", "code", "curve", "last", "best", "conventions"}
    for k in set(first) - remeasured:
        if isinstance(first[k], float):
            assert again[k] == pytest.approx(first[k], rel=1e-6, abs=1e-9), k
        else:
            assert again[k] == first[k], k
