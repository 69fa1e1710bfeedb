"""baseline.precision=auto: the CPU's bf16 instructions and the baseline's verification choose the
network's arithmetic; the run records its choice, a resume keeps it, and the fast path not taken
is explained in one line (docs/performance.md, "bf16 by default")."""
import json

import pytest
import torch
import yaml

from stdr.baselines.base import Deformation, choose_precision
from stdr.device import cpu_bf16_flags
from stdr.testing import tiny_config
from stdr.train.run import run_training, settle_precision

CPU = torch.device("cpu")


class Verified(Deformation):
    bf16_default = True


class Unverified(Deformation):
    bf16_default = False


def _cpuinfo(tmp_path, flags: str):
    p = tmp_path / "cpuinfo"
    p.write_text(f"processor\t: 0\nmodel name\t: Some CPU\nflags\t\t: fpu sse2 avx2 {flags}\n\n"
                 f"processor\t: 1\nflags\t\t: fpu sse2 avx2 {flags}\n")
    return p


def test_the_cpu_flags_are_read_from_cpuinfo(tmp_path):
    assert cpu_bf16_flags(_cpuinfo(tmp_path, "avx512f avx512_bf16")) == ("avx512_bf16",)
    assert cpu_bf16_flags(_cpuinfo(tmp_path, "amx_tile amx_bf16 avx512_bf16")) == ("avx512_bf16", "amx_bf16")
    assert cpu_bf16_flags(_cpuinfo(tmp_path, "avx512f avx512_vnni")) == ()
    assert cpu_bf16_flags(tmp_path / "absent") == ()  # not Linux: no flags, so auto stays fp32


@pytest.mark.parametrize("requested, module, device, flags, chosen, says", [
    ("fp32", Verified, CPU, ("avx512_bf16",), "fp32", ""),
    ("bf16", Unverified, CPU, ("amx_bf16",), "bf16", ""),
    ("bf16", Verified, CPU, (), "bf16", "slower than fp32"),
    ("auto", Verified, CPU, ("avx512_bf16",), "bf16", "AVX512_BF16"),
    ("auto", Verified, CPU, (), "fp32", "no AVX512-BF16 or AMX"),
    ("auto", Unverified, CPU, ("avx512_bf16",), "fp32", "mine is not among"),
    ("auto", Verified, torch.device("cuda"), (), "fp32", "not yet verified on cuda"),
])
def test_auto_picks_bf16_only_on_a_bf16_cpu_for_a_verified_baseline(requested, module, device, flags, chosen, says):
    p, why = choose_precision(requested, module, device, cpu_flags=flags, name="mine")
    assert p == chosen
    assert (says in why) if says else why == ""
    assert "\n" not in why


def test_a_bad_precision_names_the_key():
    with pytest.raises(ValueError, match="baseline.precision='fp16'"):
        choose_precision("fp16", Verified, CPU, cpu_flags=())


@pytest.mark.slow
def test_a_run_records_its_choice_and_a_resume_keeps_the_recorded_one(tmp_path, monkeypatch):
    # a CPU with bf16 and a verified deform: auto trains in bf16 and says so in config.yaml and metrics.json
    from stdr.baselines.deform import DeformMLP
    monkeypatch.setattr(DeformMLP, "bf16_default", True)
    monkeypatch.setattr("stdr.device.cpu_bf16_flags", lambda *a: ("avx512_bf16",))
    sched = ["optim.iterations=30", "baseline.warmup=10", "train.checkpoint_every=0", "train.eval_at_warmup_end=false"]
    run = tmp_path / "run"
    run_training(tiny_config(tmp_path, sched + ["train.stop_at=20"]), run)
    assert yaml.safe_load((run / "config.yaml").read_text())["baseline"]["precision"] == "bf16"
    # the same command on a CPU without bf16: the resume keeps bf16 (exact resume) and says it is slower here
    monkeypatch.setattr("stdr.device.cpu_bf16_flags", lambda *a: ())
    cfg = tiny_config(tmp_path, sched)
    assert cfg.baseline.precision == "auto"
    record = yaml.safe_load((run / "config.yaml").read_text())
    assert "slower than fp32" in settle_precision(cfg, record) and cfg.baseline.precision == "bf16"
    res = run_training(tiny_config(tmp_path, sched), run)
    assert res is not None
    m = json.loads((run / "metrics.json").read_text())
    split = next(iter(m))
    assert m[split]["precision"] == "bf16" and "config_changes" not in m[split]
    # a new run on that CPU: fp32
    run_training(tiny_config(tmp_path, sched), tmp_path / "new")
    assert json.loads((tmp_path / "new" / "metrics.json").read_text())[split]["precision"] == "fp32"


def test_every_built_in_baseline_declares_its_bf16_default():
    """bf16_default is set only where docs/performance.md records the checks it passed."""
    from stdr.baselines.registry import BASELINES
    from pathlib import Path
    doc = (Path(__file__).resolve().parents[1] / "docs" / "performance.md").read_text()
    for name in ("deform", "scgs", "spgs", "4dgs"):
        if BASELINES.get(name).module.bf16_default:
            assert f"`{name}`: bf16 by default" in doc, name


def _record(folder, rid, psnr):
    d = folder / rid
    d.mkdir(parents=True)
    (d / "metrics.json").write_text(json.dumps({"val": {
        "psnr": psnr, "train_seconds": 100.0, "conventions": {"machine": "m"}, "code": {"commit": "abcdef0"}}}))


def test_the_val_check_gives_a_verdict_only_on_every_planned_pair(tmp_path):
    from studies import precision_val as pv
    pairs = [(sc, s) for sc in pv.SCENES for s in pv.SEEDS]
    for i, (sc, s) in enumerate(pairs):  # deform: bf16 0.05 dB below on every pair; stdr: 0.3 dB below
        _record(tmp_path, f"dnerf_deform__{sc}__s{s}__fp32", 30.0 + i)
        _record(tmp_path, f"dnerf_deform__{sc}__s{s}__bf16", 29.95 + i)
        _record(tmp_path, f"dnerf_deform_stdr__{sc}__s{s}__fp32", 30.0)
        _record(tmp_path, f"dnerf_deform_stdr__{sc}__s{s}__bf16", 29.7)
    _record(tmp_path, "dnerf_scgs__standup__s0__fp32", 30.0)  # a lone variant makes no pair
    s = pv.summary(pv.load(tmp_path))
    assert s["dnerf_deform"]["verdict"] == "pass" and abs(s["dnerf_deform"]["mean_delta"] + 0.05) < 1e-9
    assert s["dnerf_deform_stdr"]["verdict"] == "fail"
    assert s["dnerf_scgs"]["verdict"] == "incomplete" and s["dnerf_scgs"]["pairs"] == []
    import shutil
    shutil.rmtree(tmp_path / f"dnerf_deform__{pairs[-1][0]}__s{pairs[-1][1]}__bf16")
    assert pv.summary(pv.load(tmp_path))["dnerf_deform"]["verdict"] == "incomplete"
    assert "| dnerf_deform_stdr | 8 of 8 | -0.300 |" in pv.table(tmp_path)
