from pathlib import Path

import pytest

from stdr.eval.table import collect, latex, markdown


def _row(method, scene, psnr, seed=0, width=128, lpips=0.1):
    return {"method": method, "scene": scene, "split": "test", "run_dir": f"{method}/{scene}/{seed}",
            "metrics": {"psnr": psnr, "ssim": 0.9, "lpips": lpips, "fps": 10.0, "num_gaussians": 1000,
                        "train_seconds": 60.0},
            "config": {"seed": seed, "baseline": {"width": width}}}


def test_table_means_and_seed_averaging():
    t = collect([_row("deform", "a", 30.0), _row("deform", "b", 20.0), _row("deform", "a", 32.0, seed=1),
                 _row("deform+STDR", "a", 31.0), _row("deform+STDR", "b", 21.0, lpips=None)])
    assert t["cells"]["deform"]["a"]["psnr"] == pytest.approx(31.0)   # two seeds averaged
    assert t["cells"]["deform"]["a"]["n_runs"] == 2
    assert t["means"]["deform"]["psnr"] == pytest.approx(25.5)        # mean over scenes
    assert t["means"]["deform+STDR"]["lpips"] is None                 # incomplete -> no mean
    assert t["cells"]["deform"]["a"]["psnr_std"] == pytest.approx(2 ** 0.5)  # sample std of 30, 32
    assert t["cells"]["deform"]["b"]["psnr_std"] is None                      # one run: no spread
    assert t["means"]["deform"]["n_seeds"] == 1   # seed 1 has no run on scene b: its mean is undefined
    assert t["means"]["deform"]["psnr_std"] is None
    md = markdown(t)
    assert "| deform | 31.00 ± 1.41 |" in md and "| deform+STDR | 31.00 |" in md
    assert "\\multicolumn{3}{c}{mean}" in latex(t) and "31.00 $\\pm$ 1.41" in latex(t)


def test_table_mean_spread_is_over_seed_means():
    # two seeds on two scenes: seed means 25 and 27 -> std sqrt(2); per-scene spreads are larger
    t = collect([_row("deform", "a", 30.0), _row("deform", "b", 20.0),
                 _row("deform", "a", 34.0, seed=1), _row("deform", "b", 20.0, seed=1)])
    assert t["means"]["deform"]["psnr"] == pytest.approx(26.0)
    assert t["means"]["deform"]["psnr_std"] == pytest.approx(2 ** 0.5)
    assert t["means"]["deform"]["n_seeds"] == 2
    assert t["cells"]["deform"]["a"]["psnr_std"] == pytest.approx(8 ** 0.5)
    assert t["means"]["deform"]["num_gaussians_std"] == pytest.approx(0.0)
    assert "| 26.00 ± 1.41 |" in markdown(t)


def test_table_refuses_to_mix_different_configs():
    with pytest.raises(ValueError, match=r"differ in \['baseline.width'\]"):
        collect([_row("deform", "a", 30.0), _row("deform", "a", 31.0, seed=1, width=256)])


def _gap_module():
    import importlib.util
    ROOT = Path(__file__).resolve().parents[1]
    spec = importlib.util.spec_from_file_location("stdr_gap", ROOT / "scripts" / "stdr_gap.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _gap_run(folder, scene, psnr, lpips, n, iterations=2000):
    import json
    d = folder / scene
    d.mkdir(parents=True)
    (d / "metrics.json").write_text(json.dumps({"val": {"psnr": psnr, "lpips": lpips, "num_gaussians": n,
                                                        "iterations": iterations}}))


def test_stdr_gap_pairs_scenes_and_refuses_mixed_lengths(tmp_path):
    gap = _gap_module()
    _gap_run(tmp_path / "p", "a", 30.0, 0.10, 1000)
    _gap_run(tmp_path / "p", "b", 20.0, 0.20, 3000)
    _gap_run(tmp_path / "s", "a", 31.0, 0.12, 500)
    _gap_run(tmp_path / "s", "b", 19.0, 0.20, 3000)
    _gap_run(tmp_path / "p", "c", 25.0, 0.1, 10)  # only in the plain folder: listed, never averaged
    rows, missing = gap.point_rows("2k", tmp_path / "p", tmp_path / "s", "val")
    assert [r["scene"] for r in rows] == ["a", "b"] and [(m["scene"], m["has"]) for m in missing] == [("c", "plain")]
    assert rows[0]["d_psnr"] == pytest.approx(1.0) and rows[0]["g_ratio"] == pytest.approx(0.5)
    m = gap.mean_row("2k", rows)
    assert m["d_psnr"] == pytest.approx(0.0) and m["d_lpips"] == pytest.approx(0.01)
    _gap_run(tmp_path / "s2", "a", 31.0, 0.12, 500, iterations=5000)
    _gap_run(tmp_path / "p2", "a", 31.0, 0.12, 500, iterations=2000)
    with pytest.raises(SystemExit, match="plain trained 2000 iterations, STDR 5000"):
        gap.point_rows("x", tmp_path / "p2", tmp_path / "s2", "val")
    with pytest.raises(SystemExit, match="no 'test' entry"):
        gap.read(tmp_path / "p" / "a", "test")


def test_code_version_names_the_checkout():
    import re

    from stdr.eval.evaluate import code_version
    v = code_version()
    root = Path(__file__).resolve().parents[1]
    assert v["version"]
    if (root / ".git").exists():  # a clone: the commit is a full hash, dirty a bool
        assert re.fullmatch(r"[0-9a-f]{40}", v["commit"]) and isinstance(v["dirty"], bool)
    else:
        assert v["commit"] is None
