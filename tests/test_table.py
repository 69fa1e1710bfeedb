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


def _gap_run(folder, scene, psnr, lpips, n, iterations=2000):
    import json
    d = folder / scene
    d.mkdir(parents=True)
    (d / "metrics.json").write_text(json.dumps({"val": {"psnr": psnr, "lpips": lpips, "num_gaussians": n,
                                                        "iterations": iterations}}))


def test_stdr_gap_pairs_scenes_and_refuses_mixed_lengths(tmp_path):
    from studies import gap
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


def _run_dir(folder, scene, psnr, seed=0, backend="cpu", stdr=None, split="test"):
    import json

    import yaml
    d = folder / scene
    d.mkdir(parents=True)
    cfg = {"seed": seed, "data": {"name": scene}, "baseline": {"name": "deform"}, "render": {"backend": "auto"},
           "stdr": {"enabled": stdr is not None}}
    (d / "config.yaml").write_text(yaml.safe_dump(cfg))
    m = {"psnr": psnr, "ssim": 0.9, "lpips": 0.1, "fps": 10.0, "num_gaussians": 1000, "train_seconds": 60.0,
         "conventions": {"render_backend": backend}, **({"stdr": stdr} if stdr else {})}
    (d / "metrics.json").write_text(json.dumps({split: m}))
    return d


def test_runs_tool_groups_seeds_and_applies_the_screening_rule(tmp_path, capsys):
    import json

    from stdr.cli.tool import main as tool
    runs = [_run_dir(tmp_path / f"s{s}", "a", 30.0 + s, seed=s) for s in range(3)]
    tool(["runs", *map(str, runs), "--group-by", "scene", "backend", "--out", str(tmp_path / "t")])
    data = json.loads((tmp_path / "t.json").read_text())
    (g,) = data["groups"]
    assert g["group"] == {"scene": "a", "backend": "cpu"} and g["n_runs"] == 3
    assert g["stats"]["psnr"]["mean"] == pytest.approx(31.0) and g["stats"]["psnr"]["std"] == pytest.approx(1.0)
    assert "31.00 ± 1.00" in (tmp_path / "t.md").read_text()
    assert "mask+Adam" not in (tmp_path / "t.md").read_text()  # no STDR run, no STDR columns
    # candidates laid out as <candidate>/<scene>: the rule's verdict per candidate
    ref = [_run_dir(tmp_path / "ref", sc, p) for sc, p in (("a", 30.0), ("b", 20.0))]
    good = [_run_dir(tmp_path / "good", sc, p, stdr={"K": 50}) for sc, p in (("a", 30.5), ("b", 20.4))]
    bad = [_run_dir(tmp_path / "bad", sc, p) for sc, p in (("a", 31.5), ("b", 19.0))]  # +0.25 mean, -1 on b
    tool(["runs", *map(str, ref + good + bad), "--label", "--rule", "ref"])
    out = capsys.readouterr().out
    verdicts = {ln.split("|")[1].strip(): ln.split("|")[-2].strip() for ln in out.splitlines()
                if ln.startswith("| ") and ln.split("|")[1].strip() in ("ref", "good", "bad")
                and ln.count("|") == 8}
    assert verdicts == {"ref": "reference", "good": "passes", "bad": "fails"}
    assert "mask+Adam" in out  # an STDR run brings the STDR columns
    with pytest.raises(SystemExit):
        tool(["runs", str(ref[0]), "--rule", "ref"])  # the rule needs --label
    with pytest.raises(SystemExit) as e:  # a missing split: one line naming the file, exit 2
        tool(["runs", str(ref[0]), "--split", "val"])
    assert e.value.code == 2 and "has no 'val' entry" in capsys.readouterr().err


def test_tool_dispatcher_lists_every_tool_and_rejects_unknown_names(capsys):
    from stdr.cli.tool import main as tool
    from stdr.tools import TOOLS
    tool([])
    out = capsys.readouterr().out
    assert all(name in out for name in TOOLS)
    with pytest.raises(SystemExit, match="no tool 'nope'"):
        tool(["nope"])


def test_table_json_writes_a_nan_as_null_so_that_any_json_reader_parses_it(tmp_path):
    import json
    import math

    from stdr.eval.table import json_text, write_outputs

    def strict(text):  # JSON has no NaN or Infinity: a reader that follows it refuses them
        return json.loads(text, parse_constant=lambda c: (_ for _ in ()).throw(ValueError(c)))
    data = {"rows": [{"psnr": float("nan"), "ssim": 0.9, "fps": math.inf, "n": 3}], "mean": [float("-inf"), 1.0]}
    assert strict(json_text(data)) == {"rows": [{"psnr": None, "ssim": 0.9, "fps": None, "n": 3}], "mean": [None, 1.0]}
    write_outputs(tmp_path / "t", "| x |", data)
    assert strict((tmp_path / "t.json").read_text())["rows"][0]["psnr"] is None
