"""stdr-chart: speed/accuracy charts from run folders (fixture runs: metrics.json + config.yaml)."""
import csv
import json

import pytest
import yaml

from stdr.cli.chart import main as stdr_chart
from stdr.eval.chart import pareto


def _run(root, method, scene, psnr, fps, n, seed=0, curve=True, lpips=0.1, width=256):
    base, stdr = method.split("+")[0], method.endswith("+STDR")
    d = root / f"{method}_s{seed}" / scene
    d.mkdir(parents=True)
    cfg = {"seed": seed, "budget": "cpu", "data": {"name": scene}, "baseline": {"name": base, "width": width},
           "render": {"backend": "auto"}, "stdr": {"enabled": stdr}}
    (d / "config.yaml").write_text(yaml.safe_dump(cfg))
    m = {"psnr": psnr, "ssim": 0.9, "lpips": lpips, "fps": fps, "num_gaussians": n, "train_seconds": 100.0,
         "model_mb": n * 59 * 4 / 2 ** 20, "width": 200, "height": 200,
         "conventions": {"machine": "Test CPU, 2 logical CPUs", "device_name": "cpu", "render_backend": "cpu"}}
    if curve:
        m["curve"] = [{"step": 500, "train_seconds": 20.0, "psnr": psnr - 5, "ssim": 0.8, "lpips": None,
                       "num_gaussians": n // 2, "frames": 5, "tag": "static_warmup"},
                      {"step": 2000, "train_seconds": 100.0, "psnr": psnr, "ssim": 0.9, "lpips": lpips,
                       "num_gaussians": n, "frames": 20, "tag": "final"}]
    (d / "metrics.json").write_text(json.dumps({"test": m}))
    return d


def _fixture(root):
    for scene, off in (("a", 0.0), ("b", -4.0)):
        _run(root, "deform", scene, 30.0 + off, 40.0, 10000)
        _run(root, "deform+STDR", scene, 30.5 + off, 30.0, 11000)
        _run(root, "4dgs", scene, 29.0 + off, 80.0, 8000)
        _run(root, "4dgs+STDR", scene, 28.5 + off, 90.0, 7000)
        _run(root, "deform", scene, 31.0 + off, 44.0, 10000, seed=1)  # a second seed: averaged


def _csv(path):
    with open(path) as f:
        return list(csv.DictReader(f))


def test_chart_writes_images_and_the_plotted_numbers(tmp_path, capsys):
    _fixture(tmp_path / "runs")
    out = tmp_path / "charts"
    stdr_chart([str(tmp_path / "runs"), "--out", str(out)])
    for name in ("speed_accuracy_psnr", "size_accuracy_psnr", "learning_curves_psnr"):
        for ext in ("png", "svg", "csv"):
            assert (out / f"{name}.{ext}").stat().st_size > 1000 or ext == "csv", name
        from PIL import Image
        with Image.open(out / f"{name}.png") as im:  # a palette PNG (palette_png): a third of the bytes
            assert im.mode == "P" and len(im.getcolors(256) or []) > 8, name
    rows = _csv(out / "speed_accuracy_psnr.csv")
    mean = {r["method"]: r for r in rows if r["scene"] == "mean"}
    assert set(mean) == {"deform", "deform+STDR", "4dgs", "4dgs+STDR"}
    # deform: seeds 0 and 1 averaged per scene (30, 31 on a; 26, 27 on b), then over scenes
    assert float(mean["deform"]["psnr"]) == pytest.approx(28.5)
    assert float(mean["deform"]["fps"]) == pytest.approx(42.0)
    assert float(mean["deform"]["psnr_std"]) == pytest.approx(0.7071, abs=1e-3)  # over the seeds' scene means
    assert {r["scene"] for r in rows} == {"mean", "a", "b"}
    curves = _csv(out / "learning_curves_psnr.csv")
    d = [r for r in curves if r["method"] == "deform+STDR"]
    assert [(int(r["step"]), float(r["train_seconds"]), float(r["psnr"])) for r in d] == \
        [(500, 20.0, 28.5 - 5), (2000, 100.0, 28.5)]  # mean over scenes a and b
    svg = (out / "speed_accuracy_psnr.svg").read_text()
    assert "Test CPU" in svg and "budget: cpu" in svg  # the caption says where and how it was measured
    # LPIPS on the y axis when asked
    stdr_chart([str(tmp_path / "runs"), "--out", str(out), "--metric", "lpips", "--charts", "speed_accuracy"])
    assert float(_csv(out / "speed_accuracy_lpips.csv")[0]["lpips"]) == pytest.approx(0.1)


def test_pareto_frontier():
    pts = [(10, 30.0), (20, 29.0), (15, 28.0), (40, 25.0), (5, 31.0)]
    assert pareto(pts) == [(5, 31.0), (10, 30.0), (20, 29.0), (40, 25.0)]
    assert pareto([(10, 0.1), (20, 0.2), (5, 0.05), (15, 0.3)], higher_is_better=False) == \
        [(5, 0.05), (10, 0.1), (20, 0.2)]  # (15, 0.3): slower and worse than (20, 0.2)


def test_bad_input_gets_an_error_naming_the_run(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(SystemExit, match="no finished run directories"):
        stdr_chart([str(tmp_path / "empty"), "--out", str(tmp_path / "o")])
    d = _run(tmp_path / "r", "deform", "a", 30.0, 40.0, 1000, lpips=None)
    with pytest.raises(SystemExit, match=f"{d}/metrics.json.*'lpips'"):
        stdr_chart([str(d), "--out", str(tmp_path / "o"), "--metric", "lpips"])
    (d / "metrics.json").unlink()
    with pytest.raises(SystemExit, match=f"{d}/metrics.json not found"):
        stdr_chart([str(d), "--out", str(tmp_path / "o")])
    with pytest.raises(SystemExit, match="neither a run directory"):
        stdr_chart([str(tmp_path / "nope"), "--out", str(tmp_path / "o")])
    # runs of one method and scene whose configs differ beyond the seed are never averaged
    _run(tmp_path / "mix", "deform", "a", 30.0, 40.0, 1000)
    _run(tmp_path / "mix", "deform", "a", 31.0, 40.0, 1000, seed=1, width=64)
    with pytest.raises(SystemExit, match="differ in"):
        stdr_chart([str(tmp_path / "mix"), "--out", str(tmp_path / "o")])
    # a learning-curve chart asked for by name needs curves (points without training seconds,
    # from runs before they were recorded, do not count)
    old = _run(tmp_path / "old", "deform", "a", 30.0, 40.0, 1000)
    m = json.loads((old / "metrics.json").read_text())
    for p in m["test"]["curve"]:
        p["train_seconds"] = None
    (old / "metrics.json").write_text(json.dumps(m))
    with pytest.raises(SystemExit, match="train.eval_every"):
        stdr_chart([str(old), "--out", str(tmp_path / "o"), "--charts", "learning_curves"])
    _run(tmp_path / "nocurve", "deform", "a", 30.0, 40.0, 1000, curve=False)
    with pytest.raises(SystemExit, match="train.eval_every"):
        stdr_chart([str(tmp_path / "nocurve"), "--out", str(tmp_path / "o"), "--charts", "learning_curves"])


def test_labelled_folders_chart_differing_configs_as_separate_methods(tmp_path):
    # two lengths of one baseline differ in config: unlabelled they are refused, labelled they
    # become two methods (e.g. a budget ladder's learning curves)
    _run(tmp_path / "short", "deform", "a", 30.0, 40.0, 1000)
    _run(tmp_path / "long", "deform", "a", 33.0, 40.0, 1000, width=64)
    with pytest.raises(SystemExit, match="differ in"):
        stdr_chart([str(tmp_path / "short"), str(tmp_path / "long"), "--out", str(tmp_path / "o")])
    out = tmp_path / "o"
    stdr_chart([f"2k={tmp_path / 'short'}", f"10k={tmp_path / 'long'}", "--out", str(out),
                "--charts", "learning_curves"])
    curves = _csv(out / "learning_curves_psnr.csv")
    assert {r["method"] for r in curves} == {"2k", "10k"}
    assert [float(r["psnr"]) for r in curves if r["method"] == "10k"] == [28.0, 33.0]
    with pytest.raises(SystemExit, match="LABEL=PATH"):
        stdr_chart([f"x={tmp_path / 'missing'}", "--out", str(out)])


def test_compact_runs_are_squares_with_an_arrow_from_their_full_model(tmp_path):
    """A run with contribution pruning is its own point, marked as compact, and paired with the
    unpruned run of the same baseline and plug-ins (not with the other one)."""
    import matplotlib
    matplotlib.use("Agg")
    from stdr.eval.chart import _full_of, labelled, read_runs, speed_points
    for scene in ("a", "b"):
        _run(tmp_path / "runs", "deform", scene, 30.0, 40.0, 10000)
        _run(tmp_path / "runs", "deform+STDR", scene, 30.5, 30.0, 11000)
        for method, psnr in (("deform", 29.9), ("deform+STDR", 30.4)):
            d = _run(tmp_path / "runs", method, scene, psnr, 80.0, 5000, seed=7)
            cfg = yaml.safe_load((d / "config.yaml").read_text())
            cfg["prune"] = {"share": 0.3, "at": ["refine_stop", "0.9"], "time_weight": 0.0}
            (d / "config.yaml").write_text(yaml.safe_dump(cfg))
    rows = read_runs(labelled([str(tmp_path / "runs")]), "test", "psnr")
    pts = [p for p in speed_points(rows, "psnr") if p["scene"] == "mean"]
    by = {p["method"]: p for p in pts}
    assert set(by) == {"deform", "deform+STDR", "deform pruned 0.3x2", "deform+STDR pruned 0.3x2"}
    assert [m for m, p in sorted(by.items()) if p["pruned"]] == ["deform pruned 0.3x2", "deform+STDR pruned 0.3x2"]
    assert _full_of(by["deform pruned 0.3x2"], pts)["method"] == "deform"
    assert _full_of(by["deform+STDR pruned 0.3x2"], pts)["method"] == "deform+STDR"
    out = tmp_path / "charts"
    stdr_chart([str(tmp_path / "runs"), "--out", str(out), "--charts", "size_accuracy"])
    assert "compact (pruned)" in (out / "size_accuracy_psnr.svg").read_text()
