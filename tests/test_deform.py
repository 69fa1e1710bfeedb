import json

import pytest
import torch
import yaml

from stdr.baselines import DeformMLP, Deltas, apply_post_activation, apply_pre_activation
from stdr.encoding import positional_encoding
from stdr.baselines.base import choose_precision
from stdr.device import cpu_bf16_flags
from stdr.gaussians import init_params
from stdr.testing import tiny_config
from stdr.train.run import run_training, settle_precision
from stdr.baselines.base import network_deltas


def test_positional_encoding_layout():
    x = torch.tensor([[0.5, -1.0, 2.0]])
    e = positional_encoding(x, 10)
    assert e.shape == (1, 63)
    assert torch.equal(e[:, :3], x)
    assert torch.allclose(e[0, 3:6], torch.sin(x[0]))          # band 2^0, sin
    assert torch.allclose(e[0, 6:9], torch.cos(x[0]))          # band 2^0, cos
    assert torch.allclose(e[0, -3:], torch.cos(x[0] * 2 ** 9))  # band 2^9, cos


def test_deform_mlp_architecture_matches_paper():
    net = DeformMLP(depth=8, width=256, skips=(4,), xyz_freqs=10, t_freqs=6, time_net=True)
    assert net.layers[0].in_features == 63 + 30          # 93 on synthetic data
    assert net.layers[5].in_features == 256 + 93          # skip after layer 4
    assert net.time_net[0].in_features == 13
    real = DeformMLP(time_net=False, t_freqs=10)
    assert real.layers[0].in_features == 63 + 21          # 84 on real data


def test_deform_input_is_detached_and_cond_is_used():
    p = init_params(torch.rand(10, 3), sh_degree=0)
    net = DeformMLP(depth=3, width=16, skips=(1,), cond_dim=2)
    cond = torch.randn(10, 2)
    d1 = net(p, 0.3, cond)
    (d1.means.sum() + d1.scales.sum() + d1.quats.sum()).backward()
    assert p["means"].grad is None                         # canonical xyz detached
    # cond columns start at zero weight (no jump when STDR's field switches on) but train
    assert torch.equal(net(p, 0.3, cond + 1).means, d1.means)
    assert net.layers[0].weight.grad[:, -2:].abs().sum() > 0
    with torch.no_grad():
        net.layers[0].weight[:, -2:] = 0.5
    d2 = net(p, 0.3, cond + 1)
    assert not torch.allclose(net(p, 0.3, cond).means, d2.means)  # conditioning reaches the network
    d3 = net(p, 0.7, cond)
    assert not torch.allclose(d1.means, d3.means)           # time too


def test_apply_rules_differ_as_documented():
    p = init_params(torch.rand(4, 3), sh_degree=0)
    d = Deltas(means=torch.full((4, 3), 0.1), quats=torch.zeros(4, 4), scales=torch.full((4, 3), 0.5))
    post, pre = apply_post_activation(p, d), apply_pre_activation(p, d)
    assert torch.allclose(post.scales, torch.exp(p["scales"]) + 0.5)     # Deformable 3DGS
    assert torch.allclose(pre.scales, torch.exp(p["scales"] + 0.5))      # 4DGS
    assert torch.allclose(post.means, p["means"] + 0.1)


def _concatenated_trunk(net, xyz, t, cond=None):
    """DeformMLP's function written as the published code runs it: one Linear on the
    concatenated input [PE(xyz), time embedding, cond], the input re-concatenated after a skip."""
    n = xyz.shape[0]
    t_emb = positional_encoding(torch.full((1, 1), float(t), dtype=xyz.dtype), net.t_freqs)
    if net.time_net is not None:
        t_emb = net.time_net(t_emb)
    x0 = torch.cat([positional_encoding(xyz, net.xyz_freqs), t_emb.expand(n, -1)] + ([cond] if net.cond_dim else []), -1)
    h = x0
    for i, layer in enumerate(net.layers):
        h = torch.relu(layer(h))
        if i in net.skips:
            h = torch.cat([h, x0], -1)
    return h


def test_blockwise_trunk_equals_the_concatenated_mlp_with_gradients():
    """The trunk multiplies the input's column blocks separately (the time embedding once); the
    function and every gradient (weights, time net, conditioning) equal the concatenated form."""
    torch.manual_seed(0)
    for kw in (dict(depth=6, width=32, skips=(3,)), dict(depth=4, width=16, skips=(1,), cond_dim=5, time_net=False,
                                                         t_freqs=10)):
        net = DeformMLP(**kw, head_init_std=None).double()
        xyz = torch.randn(300, 3, dtype=torch.float64)
        cond = torch.randn(300, 5, dtype=torch.float64, requires_grad=True) if kw.get("cond_dim") else None
        a, b = net.trunk(xyz, 0.37, cond), _concatenated_trunk(net, xyz, 0.37, cond)
        assert float((a - b).detach().abs().max()) <= 1e-12
        wrt = [p for n, p in net.named_parameters() if not n.startswith("head")] + ([cond] if cond is not None else [])
        ga = torch.autograd.grad(a.square().sum(), wrt)
        gb = torch.autograd.grad(b.square().sum(), wrt)
        for x, y in zip(ga, gb):
            assert float((x - y).abs().max()) <= 1e-10 * max(1.0, float(y.abs().max()))


def test_bf16_precision_is_an_option_with_fp32_deltas():
    from stdr.baselines.base import check_precision
    torch.manual_seed(0)
    net = DeformMLP(depth=3, width=64, skips=(1,), head_init_std=None)
    params = init_params(torch.rand(200, 3), torch.rand(200, 3), sh_degree=0)
    full = network_deltas(net, params, 0.4)
    net.precision = "bf16"
    half = network_deltas(net, params, 0.4)
    for k in ("means", "quats", "scales"):
        x, y = getattr(half, k), getattr(full, k)
        assert x.dtype == torch.float32
        assert 0 < float((x - y).detach().abs().max()) <= 0.05 * float(y.detach().abs().max())  # bf16: ~3 significant digits
    with pytest.raises(ValueError, match="baseline.precision='fp16'"):
        check_precision("fp16")


# ---------------------------------------------------------------- baseline.precision=auto
# The CPU's bf16 instructions and the baseline's verification choose the network's arithmetic; the
# run records its choice, a resume keeps it, and the fast path not taken is explained in one line
# (docs/performance.md, "bf16 by default").
CPU = torch.device("cpu")



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


@pytest.mark.parametrize("requested, verified, device, flags, chosen, says", [
    ("fp32", True, CPU, ("avx512_bf16",), "fp32", ""),
    ("bf16", False, CPU, ("amx_bf16",), "bf16", ""),
    ("bf16", True, CPU, (), "bf16", "slower than fp32"),
    ("auto", True, CPU, ("avx512_bf16",), "bf16", "AVX512_BF16"),
    ("auto", True, CPU, (), "fp32", "no AVX512-BF16 or AMX"),
    ("auto", False, CPU, ("avx512_bf16",), "fp32", "mine is not among"),
    ("auto", True, torch.device("cuda"), (), "fp32", "not yet verified on cuda"),
])
def test_auto_picks_bf16_only_on_a_bf16_cpu_for_a_verified_baseline(requested, verified, device, flags, chosen, says):
    p, why = choose_precision(requested, verified, device, cpu_flags=flags, name="mine")
    assert p == chosen
    assert (says in why) if says else why == ""
    assert "\n" not in why


def test_a_bad_precision_names_the_key():
    with pytest.raises(ValueError, match="baseline.precision='fp16'"):
        choose_precision("fp16", True, CPU, cpu_flags=())


@pytest.mark.slow
def test_a_run_records_its_choice_and_a_resume_keeps_the_recorded_one(tmp_path, monkeypatch):
    # a CPU with bf16 and a verified deform: auto trains in bf16 and says so in config.yaml and metrics.json
    from stdr.baselines import get_baseline
    assert get_baseline("deform").bf16_default
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
    """bf16_default (register_baseline) is set only where docs/performance.md records the checks it passed."""
    from stdr.baselines.registry import BASELINES
    from pathlib import Path
    doc = (Path(__file__).resolve().parents[1] / "docs" / "performance.md").read_text()
    for name in ("deform", "scgs", "spgs", "4dgs"):
        if BASELINES.get(name).bf16_default:
            assert f"`{name}`: bf16 by default" in doc, name


def _record(folder, rid, psnr, budget="cpu"):
    d = folder / rid
    d.mkdir(parents=True)
    (d / "config.yaml").write_text(f"budget: {budget}\n")
    (d / "metrics.json").write_text(json.dumps({"val": {
        "psnr": psnr, "train_seconds": 100.0, "train_cpu_utilization": 0.9, "conventions": {"machine": "m"},
        "code": {"commit": "abcdef0"}}}))


def test_the_val_check_gives_a_verdict_only_on_every_planned_pair(tmp_path):
    from studies import precision_val as pv
    scenes, seeds = pv.PLANS["cpu"]
    pairs = [(sc, s) for sc in scenes for s in seeds]
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
    # a run paused or crowded out (little of its thread) keeps its PSNR in the check, not its time
    slow = tmp_path / f"dnerf_deform_stdr__{pairs[0][0]}__s{pairs[0][1]}__bf16" / "metrics.json"
    m = json.loads(slow.read_text())
    m["val"].update(train_cpu_utilization=0.1, train_seconds=1000.0)
    slow.write_text(json.dumps(m))
    text = pv.table(tmp_path)
    assert "– (not timed)" in text and "| dnerf_deform_stdr | 8 of 8 | -0.300 | -0.30 | 8 | 1.00 | fail |" in text


def test_the_val_check_plans_by_the_records_budget_and_refuses_a_mix(tmp_path):
    from studies import precision_val as pv
    for sc in ("jumpingjacks", "standup"):  # the cpu_long plan: two scenes, seed 0
        _record(tmp_path, f"dnerf_deform__{sc}__s0__fp32", 30.0, budget="cpu_long")
        _record(tmp_path, f"dnerf_deform__{sc}__s0__bf16", 30.1, budget="cpu_long")
    assert "| dnerf_deform | 2 of 2 | +0.100 |" in pv.table(tmp_path)
    assert pv.table(tmp_path).startswith("# bf16 against fp32 on val (budget=cpu_long)")
    _record(tmp_path, "dnerf_deform__bouncingballs__s0__fp32", 30.0, budget="cpu")
    with pytest.raises(SystemExit, match=r"budgets \['cpu', 'cpu_long'\]"):
        pv.table(tmp_path)


def test_the_val_check_compares_two_named_variants_across_records_folders(tmp_path):
    """STDR's field in bf16: the field-fp32 side is the `bf16` runs of one folder, the field-bf16
    side (`bf16field`) another folder's; a run in both folders is refused."""
    from studies import precision_val as pv
    old, new = tmp_path / "runs", tmp_path / "runs_field"
    for sc in ("jumpingjacks", "standup"):
        _record(old, f"dnerf_deform_stdr__{sc}__s0__fp32", 29.0, budget="cpu_long")
        _record(old, f"dnerf_deform_stdr__{sc}__s0__bf16", 30.0, budget="cpu_long")
        _record(old, f"dnerf_deform__{sc}__s0__bf16", 30.0, budget="cpu_long")
        _record(new, f"dnerf_deform_stdr__{sc}__s0__bf16field", 29.8, budget="cpu_long")
    s = pv.summary(pv.load(new, (old,)), ("bf16", "bf16field"))
    assert s["dnerf_deform_stdr"]["verdict"] == "fail" and abs(s["dnerf_deform_stdr"]["mean_delta"] + 0.2) < 1e-9
    text = pv.table(new, (old,), ("bf16", "bf16field"))
    assert "| dnerf_deform |" not in text  # the table's methods are its own folder's; --with adds their pairs' other side
    assert text.startswith("# bf16field against bf16 on val (budget=cpu_long)")
    assert "| dnerf_deform_stdr | 2 of 2 | -0.200 |" in text
    _record(old, "dnerf_deform_stdr__standup__s0__bf16field", 29.8, budget="cpu_long")
    with pytest.raises(SystemExit, match="in two records folders"):
        pv.load(new, (old,))
