"""studies/long_budget.py: the cpu_long STDR study's table from its records (pairs, gaps, means)."""
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from studies import long_budget as lb  # noqa: E402


def _rec(tmp: Path, scene, seed, method, curve):
    """curve: {step: (train, val, test)}"""
    pts = [{"step": s, **{sp: {"psnr": v, "ssim": 0.9, "frames": 10} for sp, v in zip(lb.SPLITS, vals)}}
           for s, vals in curve.items()]
    rec = {"scene": scene, "seed": seed, "method": method, "code": "abc1234", "machine": "M", "threads": 1,
           "points": pts, "final_test": {"psnr": pts[-1]["test"]["psnr"], "ssim": 0.95, "lpips": None,
                                         "num_gaussians": 1000, "train_seconds": 10.0}}
    p = tmp / "records" / method / f"{scene}_s{seed}.json"
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(json.dumps(rec))


def test_the_table_pairs_runs_and_averages_the_differences_and_gaps(tmp_path):
    _rec(tmp_path, "a", 0, "deform", {5: (30.0, 28.0, 27.0), 10: (32.0, 29.0, 28.0)})
    _rec(tmp_path, "a", 0, "deform_stdr", {5: (30.5, 28.0, 26.0), 10: (33.0, 28.0, 26.5)})
    _rec(tmp_path, "b", 1, "deform", {5: (20.0, 19.0, 18.0), 10: (22.0, 21.0, 20.0)})
    _rec(tmp_path, "b", 1, "deform_stdr", {5: (20.5, 19.5, 18.0), 10: (22.0, 20.0, 19.5)})
    _rec(tmp_path, "c", 0, "deform", {5: (25.0, 25.0, 25.0)})  # no STDR twin: listed, never averaged
    text = lb.table(tmp_path)
    assert "mean over 2 scene/seed pairs (a s0, b s1)" in text
    # step 10: Δ train (+1.0, 0.0) -> +0.50; Δ val (-1, -1) -> -1.00; Δ test (-1.5, -0.5) -> -1.00;
    # gaps: plain (4, 2) -> 3.00, STDR (6.5, 2.5) -> 4.50
    assert "| 10 | +0.50 | -1.00 | -1.00 | 3.00 | 4.50 |" in text
    assert "| 5 | +0.50 | +0.25 | -0.50 | 2.50 | 3.50 |" in text
    assert "| c | 0 | deform | 25.00 / 25.00 / 25.00 | – | 0.00 |" in text
    assert "code abc1234" in text and "threads [1]" in text


def test_the_unseen_times_table_pairs_seeds_and_measures_distances(tmp_path):
    from studies import unseen_times as ut
    for exp, psnrs in (("embedded_deform", [30.0, 32.0]), ("embedded_deform_stdr", [29.0, 32.5])):
        d = tmp_path / f"{exp}__default__s0"
        d.mkdir()
        (d / "metrics.json").write_text(json.dumps({"val": {
            "psnr": sum(psnrs) / 2, "per_frame_psnr": psnrs, "per_frame_time": [0.1, 0.55],
            "code": {"commit": "abcdef0123"}, "conventions": {"machine": "M"}}}))
    lone = tmp_path / "embedded_deform__default__s1"
    lone.mkdir()
    (lone / "metrics.json").write_text((tmp_path / "embedded_deform__default__s0" / "metrics.json").read_text())
    text = ut.table(tmp_path, train_times=[0.0, 0.5, 1.0])
    # s0: plain 31.00, STDR 30.75, Δ -0.25; per frame -1.00 / +0.50; distances 0.1 and 0.05
    assert "| 0 | 31.00 | 30.75 | -0.25 | -1.00 / +0.50 | 2 | 0.0500 / 0.1000 |" in text
    assert "Without their pair (not in the mean): embedded_deform s1 (31.00 dB)" in text
    assert "Mean Δ over 1 seed(s): -0.25 dB." in text and "code abcdef0" in text
