"""stdr-tool commands on synthetic run folders."""
import json

import torch


def _fake_run(folder, fmt: int, stdr: bool):
    """A run folder as training leaves it: TensorBoard scalars and a final checkpoint."""
    from torch.utils.tensorboard import SummaryWriter
    w = SummaryWriter(str(folder / "tb"))
    for step, (n, c, s, pr) in {100: (50, 5, 2, 0), 200: (60, 8, 4, 2), 300: (58, 0, 0, 2)}.items():
        w.add_scalar("gaussians/count", n, step)
        w.add_scalar("densify/cloned", c, step)
        w.add_scalar("densify/split", s, step)
        w.add_scalar("densify/pruned", pr, step)
    w.close()
    # peak opacities: 0.001 (never reaches 1/255), 0.003, 0.01, 0.5 x 14
    peak = torch.tensor([0.001, 0.003, 0.01] + [0.5] * 14)
    params = {"opacities": torch.logit(peak)}
    if stdr:  # the same peaks reached through a mask whose largest column is 1 - 1e-6
        params["opacities"] = torch.logit(peak / (1 - 1e-6))
        params["stdr_mask"] = torch.full((17, 4), -5.0)
        params["stdr_mask"][:, 2] = torch.logit(torch.tensor(1 - 1e-6))
    (folder / "checkpoints").mkdir(parents=True)
    torch.save({"model": {"params": params}} if fmt == 2 else {"params": params}, folder / "checkpoints" / "last.pt")


def test_densify_trace_reads_both_checkpoint_formats_and_counts_invisible_gaussians(tmp_path, capsys):
    from stdr.tools.densify_trace import main
    runs = []
    for fmt, stdr in ((1, False), (2, True)):
        r = tmp_path / f"f{fmt}" / "scene"
        _fake_run(r, fmt, stdr)
        runs.append(str(r))
    main([*runs, "--windows", "0,150,300", "--out", str(tmp_path / "trace")])
    data = json.loads((tmp_path / "trace.json").read_text())
    for label in ("f1/scene", "f2/scene"):
        r = data["runs"][label]
        assert [(w["count"], w["cloned"], w["split"], w["pruned"]) for w in r["windows"]] == [(50, 5, 2, 0), (58, 8, 4, 4)]
        assert r["peak_opacity"]["n"] == 17 and r["peak_opacity"]["invisible"] == 2  # 0.001 and 0.003 < 1/255
        assert abs(r["peak_opacity"]["fraction_below"] - 3 / 17) < 1e-6  # a float32 mean
    assert "never ≥ 1/255" in (tmp_path / "trace.md").read_text()


def _metrics_run(folder, psnr, fps, n, active, train_s, cull="eval", scene_split="test"):
    folder.mkdir(parents=True)
    entry = {"psnr": psnr, "ssim": 0.9, "lpips": 0.1, "fps": fps, "fps_passes": [fps] * 3, "num_gaussians": n,
             "active_gaussians_mean": active, "active_gaussians_max": active + 10, "model_mb": n * 59 * 4 / 2 ** 20, "train_seconds": train_s,
             "iterations": 100, "render_cull": cull, "conventions": {}}
    (folder / "metrics.json").write_text(json.dumps({scene_split: entry}))


def test_variants_table_means_common_scenes_and_ratios(tmp_path, capsys):
    import pytest

    from stdr.tools import variants
    for sc, (pa, pb) in {"a": (20.0, 21.0), "b": (30.0, 30.5)}.items():
        _metrics_run(tmp_path / "plain" / sc, pa, 10.0, 1000, 1000, 100.0, cull="off")
        _metrics_run(tmp_path / "stdr" / sc, pb, 25.0, 800, 300, 150.0)
    _metrics_run(tmp_path / "stdr" / "extra", 99.0, 1.0, 1, 1, 1.0)  # only one variant has it
    for sc, sec in {"a": {"deform": 10.0, "backward": 30.0}, "b": {"deform": 20.0, "backward": 50.0}}.items():
        (tmp_path / "stdr" / sc / "train_profile.json").write_text(json.dumps({"seconds": sec}))
    out = tmp_path / "t" / "deform"
    variants.main(["--table", "deform", f"plain={tmp_path / 'plain'}", f"+STDR={tmp_path / 'stdr'}",
                   "--out", str(out)])
    data = json.loads(out.with_suffix(".json").read_text())["tables"][0]
    plain, stdr = data["rows"]
    assert data["scenes"] == ["a", "b"] and data["missing"] == {"+STDR": ["extra"]}
    assert stdr["psnr"] == pytest.approx(25.75) and plain["psnr"] == pytest.approx(25.0)
    assert stdr["fps_ratio"] == pytest.approx(2.5) and stdr["num_gaussians_ratio"] == pytest.approx(0.8)
    assert stdr["train_seconds_ratio"] == pytest.approx(1.5) and stdr["active_share"] == pytest.approx(0.375)
    assert plain["render_cull"] == "off" and stdr["render_cull"] == "eval"
    assert stdr["active_gaussians_max"] == pytest.approx(310)  # the mean over the scenes of each run's max
    md = out.with_suffix(".md").read_text()
    assert stdr["d_psnr"] == pytest.approx(0.75) and plain["d_psnr"] == 0
    assert "| +STDR | 25.75 | +0.75 |" in md and "extra" in md
    # the training's sections, averaged over the scenes, for the variants whose runs kept them
    assert stdr["profile"] == {"deform": 15.0, "backward": 40.0} and plain["profile"] is None
    assert "| +STDR | 15.0 | 40.0 | 55.0 |" in md
    # the smallest model a scene needs: a: +STDR is 1 dB better, so plain is not within 0.5 dB;
    # b: plain (30.0) is within 0.5 dB of +STDR's 30.5 and comes first
    variants.main(["--table", "deform", f"plain={tmp_path / 'plain'}", f"+STDR={tmp_path / 'stdr'}",
                   "--smallest-within", "0.5", "--out", str(out)])
    small = {r["scene"]: r for r in json.loads(out.with_suffix(".json").read_text())["tables"][0]["smallest"]}
    assert (small["a"]["best"], small["a"]["smallest"]) == ("+STDR", "+STDR")
    assert (small["b"]["best"], small["b"]["smallest"], small["b"]["gaussians"]) == ("+STDR", "plain", 1000)
    assert "smallest within 0.5 dB" in out.with_suffix(".md").read_text()
    # bad input names what is wrong
    with pytest.raises(SystemExit, match="LABEL=FOLDER"):
        variants.main(["--table", "deform", str(tmp_path / "plain")])
    with pytest.raises(SystemExit, match="no 'val' entry"):
        variants.main(["--table", "deform", f"plain={tmp_path / 'plain'}", "--split", "val"])
    with pytest.raises(SystemExit, match="no scene has a metrics.json in every variant"):
        variants.main(["--table", "x", f"p={tmp_path / 'plain'}", f"q={tmp_path / 't'}"])


def test_bench_train_times_the_step_by_section_at_fixed_counts(tmp_path):
    import pytest

    from stdr.testing import TINY_SCENE
    from stdr.tools import bench_train
    out = tmp_path / "bench"
    common = [*TINY_SCENE, f"data.cache_dir={tmp_path / 'cache'}", "device=cpu", "model.init_num=300",
              "train.threads=2"]
    bench_train.main(["--experiments", "embedded_deform", "embedded_deform_stdr", "--gaussians", "400", "900",
                      "--res", "64", "--iters", "2", "--warmup-iters", "1", "--out", str(out), "--", *common])
    data = json.loads(out.with_suffix(".json").read_text())
    rows = data["rows"]
    assert [(r["experiment"], r["gaussians"], r["stdr"]) for r in rows] == [
        ("embedded_deform", 400, False), ("embedded_deform", 900, False),
        ("embedded_deform_stdr", 400, True), ("embedded_deform_stdr", 900, True)]
    for r in rows:
        sec, parts = r["sections_ms"], r["backward_parts_ms"]
        assert {"deform", "render_fwd", "loss", "backward", "optimizer", "densify"} <= set(sec)
        assert ("stdr_reg" in sec) == r["stdr"]
        # the backward is split at the projection's outputs and the deformed Gaussians, nothing lost
        assert set(parts) == set(bench_train.PARTS) and all(v >= 0 for v in parts.values())
        assert sum(parts.values()) == pytest.approx(sec["backward"], rel=1e-6)
        assert r["ms"] > 0 and (r["width"], r["height"]) == (64, 64) and r["iters"] == 2
        assert r["step"] >= 0 and r["active_mean"] <= r["gaussians"]
        # the bounds' tally (one more step): the backward's parts add up to it, the sections to the step
        w = r["work"]
        assert w["sections"]["deform"]["gflop"] > 0 and w["sections"]["optimizer"]["mb"] > 0
        assert sum(v["bound_ms"] for v in w["backward_parts"].values()) == pytest.approx(
            w["sections"]["backward"]["bound_ms"], rel=1e-9)
        assert sum(v["bound_ms"] for v in w["sections"].values()) == pytest.approx(w["step"]["bound_ms"], rel=1e-9)
    assert data["mm_ms_before"] > 0 and data["mm_ms_after"] > 0 and data["threads"] == 2
    assert all(data["rates"][k] > 0 for k in ("fp32", "bf16", "bandwidth"))
    md = out.with_suffix(".md").read_text()
    assert "÷ mm" in md and "bwd: projection+sh" in md and "embedded_deform_stdr" in md
    assert "| embedded_deform | 64x64 | 400 | whole step |" in md and "× bound" in md
    with pytest.raises(SystemExit, match="no checkpoints/last.pt"):
        bench_train.main(["--experiments", "embedded_deform", "--run", str(tmp_path), "--", *common])
    # --compare: the same file against a copy with one row twice as fast and one row removed
    faster = json.loads(json.dumps(data))
    faster["rows"][0]["ms"] = data["rows"][0]["ms"] / 2
    del faster["rows"][3]
    (tmp_path / "after.json").write_text(json.dumps(faster))
    bench_train.main(["--compare", str(out.with_suffix(".json")), str(tmp_path / "after.json"),
                      "--out", str(tmp_path / "cmp")])
    cmp = json.loads((tmp_path / "cmp.json").read_text())
    assert [(r["experiment"], r["gaussians"]) for r in cmp["rows"]] == [
        ("embedded_deform", 400), ("embedded_deform", 900), ("embedded_deform_stdr", 400)]
    assert cmp["rows"][0]["speedup"] == pytest.approx(2.0) and cmp["rows"][1]["speedup"] == pytest.approx(1.0)
    assert "Not compared (in one file only): embedded_deform_stdr 64x64 900" in (tmp_path / "cmp.md").read_text()
    with pytest.raises(SystemExit, match="not a bench-train result"):
        (tmp_path / "bad.json").write_text("{}")
        bench_train.main(["--compare", str(tmp_path / "bad.json"), str(tmp_path / "after.json")])


def test_tally_counts_each_operators_flops_and_bytes_in_its_section_and_backward_part():
    import pytest

    from stdr.tools.bench_bounds import Tally, WorkProfiler
    rates = {"fp32": 1e9, "bf16": 2e9, "bandwidth": 1e9}  # FLOP/s and bytes/s: bounds in round numbers
    tally = Tally(rates)
    prof = WorkProfiler(tally, after="rest")
    a, b = torch.ones(64, 32), torch.ones(32, 16)
    with tally:
        with prof("mm"):
            c = a @ b  # 2 * 64 * 32 * 16 FLOPs; reads a and b, writes c
        with prof("inplace"):
            c.t()  # a view: moves nothing
            c.add_(1.0)  # reads c and writes it
        with prof("bf16"):
            a.bfloat16() @ b.bfloat16()  # two casts, and a product at the bf16 rate
        w = torch.ones(4, 2, requires_grad=True)
        x = torch.ones(8, 4)
        y = x @ w
        prof.watch("head", (y,))
        prof.backward(y.relu().sum())
    s = tally.summary(1)["sections"]
    assert s["mm"]["gflop"] * 1e9 == 2 * 64 * 32 * 16
    assert s["mm"]["mb"] * 1e6 == (64 * 32 + 32 * 16 + 64 * 16) * 4
    assert s["mm"]["bound_ms"] == pytest.approx(2 * 64 * 32 * 16 / 1e9 * 1e3)  # FLOP-limited: 65,536 > 14,336
    assert s["mm"]["flop_limited_ms"] == s["mm"]["bound_ms"]
    assert s["inplace"]["mb"] * 1e6 == 2 * 64 * 16 * 4 and s["inplace"]["gflop"] == 0
    assert s["inplace"]["flop_limited_ms"] == 0 and s["inplace"]["bound_ms"] == pytest.approx(2 * 64 * 16 * 4 / 1e9 * 1e3)
    bf = s["bf16"]  # casts: fp32 read, bf16 written; the product: bf16 operands and result
    assert bf["mb"] * 1e6 == (64 * 32 + 32 * 16) * (4 + 2) + (64 * 32 + 32 * 16 + 64 * 16) * 2
    assert bf["bound_ms"] == pytest.approx((2 * 64 * 32 * 16 / 2e9 + (64 * 32 + 32 * 16) * 6 / 1e9) * 1e3)
    # the backward: the relu's and sum's gradients until y's gradient is ready ("head"), then the
    # product's weight gradient x.t() @ g, 2 * 4 * 8 * 2 FLOPs ("rest"); both also in "backward"
    parts = tally.summary(1)["backward_parts"]
    assert parts["head"]["gflop"] == 0 and parts["head"]["mb"] > 0
    assert parts["rest"]["gflop"] * 1e9 == 2 * 4 * 8 * 2
    assert s["backward"]["gflop"] * 1e9 == 2 * 4 * 8 * 2
    assert s["backward"]["mb"] == pytest.approx(parts["head"]["mb"] + parts["rest"]["mb"])


def test_observe_calls_reports_the_compiled_modules_calls_while_open():
    import pytest

    from stdr import extension
    if not extension.available("cpu"):
        pytest.skip("the CPU extension does not build here")
    calls = []
    t = torch.ones(5)
    with extension.observe_calls(lambda name, args, out: calls.append((name, len(args)))):
        extension.load_extension("cpu").nonfinite_flags([t])
        with pytest.raises(RuntimeError, match="already open"):
            with extension.observe_calls(print):
                pass
    assert calls == [("nonfinite_flags", 1)]
    ext = extension.load_extension("cpu")  # closed: the module itself, nothing reported
    ext.nonfinite_flags([t])
    assert calls == [("nonfinite_flags", 1)] and not isinstance(ext, extension._Observed)


def test_profiler_adds_no_hooks_in_training():
    import torch

    from stdr.train.timing import Profiler
    p = Profiler()  # training's profiler: watch() must not touch the graph
    x = torch.ones(3, requires_grad=True)
    y = x * 2
    p.watch("part", (y,))
    assert not y._backward_hooks
    p.backward(y.sum())
    assert dict(p.backward_parts) == {} and p.seconds["backward"] > 0 and torch.equal(x.grad, torch.full((3,), 2.0))
