"""Bad input never costs a run: unknown keys and out-of-range values are refused before anything
trains, in one line naming the key and what is allowed (exit code 2); a file that is not ours says
so; a run that stdr-train writes is read by every tool."""
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from stdr.errors import ConfigError, UserError
from stdr.testing import make_cfg
from stdr.validate import check_run_config

ROOT = Path(__file__).resolve().parents[1]


def _refused(overrides, base=None):
    with pytest.raises(ConfigError) as e:
        check_run_config(make_cfg(overrides), base)
    return str(e.value)


@pytest.mark.parametrize("overrides,message", [
    (["+optim.iteratons=100"], "unknown config key optim.iteratons: did you mean optim.iterations?"),
    (["+optm.iterations=100"], "unknown config section optm: did you mean optim?"),
    (["+foo=1"], "unknown config section foo: the sections are"),
    (["+optim.prune_opa=0.1"], "unknown config key optim.prune_opa: did you mean densify.prune_opa?"),
    (["stdr=on", "+stdr.maskk=1"], "unknown config key stdr.maskk: did you mean stdr.mask?"),
    (["+baseline.scgs.num_nodez=3"], "unknown config key baseline.scgs"),  # deform has no scgs node
    (["data.max_width=-5"], "data.max_width=-5: use null (no limit) or a whole number >= 1"),
    (["data.max_width=0"], "data.max_width=0: use null (no limit)"),
    (["optim.iterations=-5"], "optim.iterations=-5: use a whole number >= 1"),
    (["optim.iterations=0"], "optim.iterations=0: use a whole number >= 1"),
    (["data.resolution_scale=0"], "data.resolution_scale=0.0: use a finite number > 0"),
    (["optim.lambda_dssim=nan"], "optim.lambda_dssim=nan: must be a finite number"),
    (["densify.refine_every=0"], "densify.refine_every=0: use a whole number >= 1"),
    (["densify.prune_scale2d=-1"], "densify.prune_scale2d=-1.0: use null (off) or a finite number > 0"),
    (["train.stop_at=0"], "train.stop_at=0: use null (no limit) or a whole number >= 1"),
    (["train.deadline=-1"], "train.deadline=-1.0: use null (off) or a finite number > 0"),
    (["data.eval_split=tset"], "data.eval_split='tset': use one of test, val, train"),
    (["model.sh_degree=4"], "model.sh_degree=4: use 0, 1, 2 or 3"),
    (["prune.share=1.5"], "prune.share=1.5"),
    (["data.path=somewhere"], "data.path=somewhere: the procedural scene (data=embedded) does not read it"),
])
def test_a_bad_key_or_value_is_refused_naming_it(overrides, message):
    assert message in _refused(overrides)


def test_scene_paths_must_be_folders(tmp_path):
    f = tmp_path / "transforms_train.json"
    f.write_text("{}")
    assert "data.path=" + str(f) + ": is a file, not a folder; point it at the scene folder" in _refused(
        ["experiment=dnerf_deform", f"data.path={f}"])
    assert "no such folder" in _refused(["experiment=dnerf_deform", f"data.path={tmp_path / 'nope'}"])
    assert "data.path is not set" in _refused(["experiment=dnerf_deform"])
    assert "(the one holding dataset.json)" in _refused(["experiment=nerfds_deform", f"data.path={f}"])
    check_run_config(make_cfg(["experiment=dnerf_deform", f"data.path={tmp_path}"]))  # a folder passes


def test_every_shipped_experiment_and_budget_passes_the_checks(tmp_path):
    """The checks refuse no configuration the project ships (a scene folder stands in): every
    method on D-NeRF at every budget, and every other data option with deform+STDR."""
    from stdr.store import experiment_names
    names = experiment_names()
    dnerf = [e for e in names if e.startswith("dnerf_")]
    others = sorted({e.rsplit("_deform_stdr", 1)[0] for e in names if e.endswith("_deform_stdr")} - {"dnerf"})
    assert len(dnerf) == 8 and others
    combos = [(e, b) for e in dnerf for b in ("cpu", "cpu_long", "gpu", "paper", "demo")]
    combos += [(f"{d}_deform_stdr", "cpu") for d in others]
    for exp, budget in combos:
        cfg = make_cfg([f"experiment={exp}", f"budget={budget}"])
        if cfg.data.format != "procedural":
            cfg.data.path = str(tmp_path)
        check_run_config(cfg)


def _cli(args, cwd):
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run([sys.executable, "-m", *args], cwd=cwd, capture_output=True, text=True, env=env,
                          timeout=300)


def test_a_new_entry_of_a_map_is_told_to_take_a_plus(capsys):
    """pack.codecs holds entries of the user's choosing: a new one needs Hydra's '+', and the error
    says so with the override to type, not 'unknown config key'."""
    from stdr.cli.common import check_overrides
    with pytest.raises(SystemExit) as e:
        check_overrides("stdr-train", ["compact=on", "pack.codecs.entropy=zstd"])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert "a new entry takes a '+': +pack.codecs.entropy=zstd" in err and "unknown config key" not in err
    check_overrides("stdr-train", ["compact=on", "+pack.codecs.entropy=zstd"])  # with it, the line composes


def test_stdr_train_prints_one_line_and_exits_2_without_training(tmp_path):
    p = _cli(["stdr.cli.train", "+optim.iteratons=100", f"hydra.run.dir={tmp_path / 'run'}"], tmp_path)
    assert p.returncode == 2, p.stderr
    assert p.stderr.strip().splitlines() == ["stdr-train: error: unknown config key optim.iteratons: did you mean "
                                             "optim.iterations?"]
    assert "Traceback" not in p.stdout + p.stderr
    assert not (tmp_path / "run" / "config.yaml").exists() and not (tmp_path / "run" / "checkpoints").exists()


def test_a_nan_pose_is_one_line_naming_the_frame(tmp_path):
    from stdr.data.procedural import SceneOptions, generate_scene
    scene = generate_scene(tmp_path / "scene", SceneOptions(resolution=24, n_train=4, n_val=1, n_test=2))
    meta = json.loads((scene / "transforms_train.json").read_text())
    meta["frames"][2]["transform_matrix"][1][3] = float("nan")
    (scene / "transforms_train.json").write_text(json.dumps(meta))
    p = _cli(["stdr.cli.train", "experiment=dnerf_deform", f"data.path={scene}", "device=cpu",
              f"hydra.run.dir={tmp_path / 'run'}"], tmp_path)
    assert p.returncode == 2
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in p.stderr, p.stderr[-2000:]
    assert "transforms_train.json: frames[2]" in lines[0] and "non-finite values (nan)" in lines[0]


# ------------------------------------------------------------------ files that are not ours
def test_a_foreign_pickle_is_named_as_not_ours_in_every_tool(tmp_path):
    """A pickle of other code's objects (bare, or in a checksummed envelope) is 'not an stdr
    checkpoint', never 'damaged', and torch's advice to load it with weights_only=False is not
    passed on; a cut file is damaged."""
    import hashlib
    import io

    import torch

    from stdr.io.checkpoint import ENVELOPE, CheckpointError, load_checkpoint
    bare = tmp_path / "bare.pt"
    torch.save({"x": Path("/tmp")}, bare)  # an object torch will not load without running code
    buf = io.BytesIO()
    torch.save({"x": Path("/tmp")}, buf)
    raw = buf.getvalue()
    env = tmp_path / "env.pt"
    torch.save({"envelope": ENVELOPE, "sha256": hashlib.sha256(raw).hexdigest(),
                "data": torch.frombuffer(bytearray(raw), dtype=torch.uint8)}, env)
    text = tmp_path / "notes.pt"
    text.write_text("hello")
    for f in (bare, env, text):
        with pytest.raises(CheckpointError) as e:
            load_checkpoint(f)
        msg = str(e.value)
        assert "is not an stdr checkpoint" in msg and "damaged" not in msg and "weights_only=False" not in msg, msg
    cut = tmp_path / "cut.pt"
    cut.write_bytes(bare.read_bytes()[: bare.stat().st_size // 2])
    with pytest.raises(CheckpointError, match="is damaged"):
        load_checkpoint(cut)
    assert issubclass(CheckpointError, UserError)
    for prog in (["stdr.cli.view", "export"], ):  # a command line: one line, exit code 2
        p = subprocess.run([sys.executable, "-c", "import sys; from stdr.cli.view import export_main; "
                            f"export_main(['{env}', '--times', '0'])"], capture_output=True, text=True,
                           env={**os.environ, "PYTHONPATH": str(ROOT)}, timeout=300)
        assert p.returncode == 2 and p.stderr.strip().count("\n") == 0, (prog, p.stderr[-2000:])
        assert p.stderr.startswith("stdr-export: error:") and "not an stdr checkpoint" in p.stderr


# ------------------------------------------------------------------ a run every tool reads
def test_a_run_stdr_train_writes_is_read_by_every_tool(tmp_path):
    """The round trip the key check guarantees: stdr-eval's loader, stdr-export, the viewer's
    loader and a resume all read what stdr-train wrote (with a plug-in's keys set)."""
    from stdr.train.run import run_training as run
    from stdr.cli.view import export_main
    from stdr.store import load_config
    from stdr.testing import tiny_config
    from stdr.view.core import open_run
    sched = ["optim.iterations=30", "baseline.warmup=10", "densify.refine_start=5", "densify.refine_every=10",
             "train.checkpoint_every=0", "train.eval_at_warmup_end=false", "eval.fps_repeats=1", "stdr=on",
             "stdr.warmup_end=12", "stdr.freeze_at=20"]
    rd = tmp_path / "run"
    cfg = tiny_config(tmp_path, sched)
    check_run_config(cfg)
    run(cfg, rd)
    load_config(rd / "config.yaml")  # stdr-eval rebuilds the run from this
    export_main([str(rd), "--times", "0.5", "--out", str(tmp_path / "ply")])
    assert len(list((tmp_path / "ply").glob("*.ply"))) == 1
    assert open_run(rd, device="cpu").model.num_gaussians > 0
    longer = tiny_config(tmp_path, [s.replace("optim.iterations=30", "optim.iterations=35") for s in sched]
                         + ["train.resume=override"])  # a changed key: the resume says so (stdr.train.resume)
    res = run(longer, rd)  # resumes from checkpoints/last.pt at 30
    assert res is not None and res["iterations"] == 35
    assert res["config_changes"][0]["keys"] == {"optim.iterations": [30, 35]}
    load_config(rd / "config.yaml")  # the record of the change is read back too
    shutil.rmtree(rd)
    assert np.isfinite(res["psnr"])


@pytest.mark.parametrize("argv", [["--width", "-5"], ["--width", "0"], ["--frames", "0"], ["--fps", "nan"]])
def test_stdr_render_refuses_non_positive_sizes(tmp_path, argv, capsys):
    from stdr.cli.view import render_main
    with pytest.raises(SystemExit) as e:
        render_main([str(tmp_path), *argv])
    assert e.value.code == 2 and "must be > 0" in capsys.readouterr().err
