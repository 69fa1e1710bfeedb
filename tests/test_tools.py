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
             "active_gaussians_mean": active, "model_mb": n * 59 * 4 / 2 ** 20, "train_seconds": train_s,
             "iterations": 100, "render_cull": cull, "static_skip": 0.0, "conventions": {}}
    (folder / "metrics.json").write_text(json.dumps({scene_split: entry}))


def test_variants_table_means_common_scenes_and_ratios(tmp_path, capsys):
    import pytest

    from stdr.tools import variants
    for sc, (pa, pb) in {"a": (20.0, 21.0), "b": (30.0, 30.5)}.items():
        _metrics_run(tmp_path / "plain" / sc, pa, 10.0, 1000, 1000, 100.0, cull="off")
        _metrics_run(tmp_path / "stdr" / sc, pb, 25.0, 800, 300, 150.0)
    _metrics_run(tmp_path / "stdr" / "extra", 99.0, 1.0, 1, 1, 1.0)  # only one variant has it
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
    md = out.with_suffix(".md").read_text()
    assert stdr["d_psnr"] == pytest.approx(0.75) and plain["d_psnr"] == 0
    assert "| +STDR | 25.75 | +0.75 |" in md and "extra" in md
    # bad input names what is wrong
    with pytest.raises(SystemExit, match="LABEL=FOLDER"):
        variants.main(["--table", "deform", str(tmp_path / "plain")])
    with pytest.raises(SystemExit, match="no 'val' entry"):
        variants.main(["--table", "deform", f"plain={tmp_path / 'plain'}", "--split", "val"])
    with pytest.raises(SystemExit, match="no scene has a metrics.json in every variant"):
        variants.main(["--table", "x", f"p={tmp_path / 'plain'}", f"q={tmp_path / 't'}"])
