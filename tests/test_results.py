"""Tables the studies generate. studies/results.py's headline table from the rerun's records: shown
only once every method has every scene at one seed, averaging only seeds that are complete over
the whole grid. studies/ops_per_step.py's comparison of operator counts (the counts themselves
are measured; this pins how they are put side by side)."""
import json
import sys
from pathlib import Path

import pytest
import yaml
from helpers import load_script

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from studies.ops_per_step import compare, main  # noqa: E402


def _results():
    return load_script(ROOT / "studies" / "results.py", "results_script")


def _record(root: Path, baseline: str, stdr: bool, scene: str, seed: int, psnr: float, gaussians: int = 1000,
            train_s: float = 100.0, fps: float = 50.0, idle=None, machine: str = "test machine"):
    d = root / f"dnerf_{baseline}{'_stdr' if stdr else ''}" / scene / f"s{seed}"
    d.mkdir(parents=True)
    cfg = {"seed": seed, "baseline": {"name": baseline}, "stdr": {"enabled": stdr},
           "data": {"name": scene, "path": f"/data/{scene}"}, "render": {"backend": "cpu"}}
    (d / "config.yaml").write_text(yaml.safe_dump(cfg))
    m = {"psnr": psnr, "ssim": 0.9, "lpips": 0.05, "fps": fps, "num_gaussians": gaussians, "train_seconds": train_s,
         "conventions": {"machine": machine}, "code": {"commit": "abcdef0123", "dirty": False}}
    (d / "metrics.json").write_text(json.dumps({"test": m}))
    if idle is not None:  # scripts/idle_run.py's record of the run
        (d / "load.json").write_text(json.dumps({"idle": idle}))


def test_headline_waits_for_a_complete_seed_and_averages_only_complete_seeds(tmp_path):
    r = _results()
    runs, bases, scenes = tmp_path / "runs", ("deform", "scgs"), ("a", "b")
    for b in bases:
        for stdr in (False, True):
            _record(runs, b, stdr, "a", 0, 20.0 + stdr)
    means, recorded = r.headline_from_records(runs, bases, scenes)
    assert means is None and recorded == 4  # scene b missing everywhere: no table yet
    for b in bases:
        for stdr in (False, True):
            _record(runs, b, stdr, "b", 0, 30.0 + stdr, gaussians=3000)
    _record(runs, "deform", False, "a", 1, 99.0)  # seed 1 has one cell only: left out
    means, prov = r.headline_from_records(runs, bases, scenes)
    assert set(means) == {"deform", "deform+STDR", "scgs", "scgs+STDR"}
    assert means["deform"]["psnr"] == pytest.approx(25.0) and means["deform+STDR"]["psnr"] == pytest.approx(26.0)
    assert means["scgs"]["num_gaussians"] == pytest.approx(2000)
    assert means["deform"]["n_seeds"] == 1 and means["deform"]["psnr_std"] is None
    assert prov["seeds"] == "seed 0" and f"9 of the {r.HEADLINE_PLANNED} planned" in prov["runs"] and prov["runs"].startswith("8 ")
    assert prov["code"] == "abcdef0 (8 runs)" and prov["machine"] == "test machine (8 runs)"
    for b in bases:  # seed 1 complete: two seeds, with a spread over their scene means
        for stdr in (False, True):
            for sc in scenes:
                if not (b == "deform" and not stdr and sc == "a"):
                    _record(runs, b, stdr, sc, 1, (20.0 if sc == "a" else 30.0) + stdr + 1.0)
    means, prov = r.headline_from_records(runs, bases, scenes)
    assert prov["seeds"] == "seeds 0, 1"
    # deform plain: seed 0 scene mean 25, seed 1 scene mean (99 + 31) / 2 = 65
    assert means["deform"]["psnr"] == pytest.approx(45.0) and means["deform"]["n_seeds"] == 2
    assert means["deform"]["psnr_std"] == pytest.approx(((25 - 45) ** 2 + (65 - 45) ** 2) ** 0.5)
    assert means["scgs+STDR"]["psnr"] == pytest.approx(26.5)
    # the mean Δ of each seed alone: seed 0: +1 for both baselines; seed 1: deform+STDR (22 + 32) / 2 = 27
    # against plain 65 (-38), scgs +1
    assert prov["delta_by_seed"] == pytest.approx({0: 1.0, 1: (-38.0 + 1.0) / 2})
    assert r._by_seed(prov) == "; by seed: +1.00 (seed 0), -18.50 (seed 1)"


def _grid(runs: Path, idle_plain_a=True, machine_plain_a="test machine", idle_plain_b=True):
    """deform on scenes a and b, seed 0: +STDR trains 1.5x as long and renders at 0.5x the FPS."""
    for stdr in (False, True):
        for sc in ("a", "b"):
            plain_a, plain_b = not stdr and sc == "a", not stdr and sc == "b"
            _record(runs, "deform", stdr, sc, 0, 20.0 + stdr, train_s=100.0 * (1.5 if stdr else 1.0),
                    fps=40.0 * (0.5 if stdr else 1.0),
                    idle=idle_plain_a if plain_a else idle_plain_b if plain_b else True,
                    machine=machine_plain_a if plain_a else "test machine")


@pytest.mark.parametrize("case", ["idle", "shared", "no record", "two machines", "none alone"])
def test_time_ratios_come_only_from_pairs_timed_alone_on_one_machine(tmp_path, case):
    """A (scene, seed) pair's +STDR / plain time ratio counts only when both runs had their machine
    to themselves (load.json) and ran on the same machine; the cell says how many pairs it used,
    and reads "–" (the README sentence points to the results page) when none qualifies."""
    r = _results()
    _grid(tmp_path, idle_plain_a={"idle": True, "shared": False, "no record": None, "two machines": True,
                                  "none alone": False}[case],
          machine_plain_a="other machine" if case == "two machines" else "test machine",
          idle_plain_b=case != "none alone")
    means, prov = r.headline_from_records(tmp_path, ("deform",), ("a", "b"))
    row = r.headline_table(means, prov["ratios"])[2].split("|")
    ratios = [c.strip() for c in row[-3:-1]]
    if case == "idle":
        assert ratios == ["1.50", "0.50"] and prov["ratios"]["deform"]["pairs"] == 2
        assert "training 1.50-1.50x as long, rendering at 0.50-0.50x the FPS" in r.stdr_cost(prov["ratios"])
    elif case == "none alone":
        assert ratios == ["–", "–"] and prov["ratios"]["deform"]["pairs"] == 0
        assert "see the results page" in r.stdr_cost(prov["ratios"])
    else:  # scene a's pair is left out, scene b's counts
        assert ratios == ["1.50 (1 of 2 pairs)", "0.50 (1 of 2 pairs)"]


def test_time_ratios_are_geometric_means_of_per_pair_ratios(tmp_path):
    """+STDR twice as slow to train on one scene and twice as fast on the other is no change (a
    ratio of the means, (200 + 50) / (100 + 100), would say 1.25x), and a plain run 10x slower
    than its +STDR pair on the other machine cannot tip it."""
    r = _results()
    for sc, plain_s, stdr_s in (("a", 100.0, 200.0), ("b", 100.0, 50.0)):
        _record(tmp_path, "deform", False, sc, 0, 20.0, train_s=plain_s, fps=40.0, idle=True)
        _record(tmp_path, "deform", True, sc, 0, 20.0, train_s=stdr_s, fps=10.0 if sc == "a" else 40.0, idle=True)
    means, prov = r.headline_from_records(tmp_path, ("deform",), ("a", "b"))
    got = prov["ratios"]["deform"]
    assert got["train_seconds"] == pytest.approx(1.0) and got["fps"] == pytest.approx(0.5)
    assert (got["pairs"], got["of"]) == (2, 2)
    for stdr, train_s in ((False, 1000.0), (True, 100.0)):  # seed 1 on scene a: plain and +STDR on two machines
        _record(tmp_path, "deform", stdr, "a", 1, 20.0, train_s=train_s, idle=True,
                machine="other machine" if stdr else "test machine")
    for stdr in (False, True):
        _record(tmp_path, "deform", stdr, "b", 1, 20.0, train_s=100.0, fps=40.0, idle=True)
    means, prov = r.headline_from_records(tmp_path, ("deform",), ("a", "b"))
    got = prov["ratios"]["deform"]
    assert (got["pairs"], got["of"]) == (3, 4) and got["train_seconds"] == pytest.approx(1.0)
    assert "(3 of 4 pairs)" in r.headline_table(means, prov["ratios"])[2]


def test_headline_runs_of_the_former_stdr_default_are_its_stdr_rows():
    """Runs trained with stdr.mask_after_freeze=true (the former default) carry its row tag
    now; the headline reads them as its +STDR rows (and says so), and leaves every other label."""
    results = _results()
    assert results._headline_label("deform+STDR" + results.GATED_TAG) == "deform+STDR"
    assert results._headline_label("deform+STDR w/o spatial_reg") == "deform+STDR w/o spatial_reg"
    assert results._headline_label("deform") == "deform"
    assert "mask_after_freeze=true" in results.GATED_NOTE


def test_the_rerun_with_todays_defaults_replaces_the_former_table_once_one_seed_is_complete(tmp_path, monkeypatch):
    """headline(): until the rerun (RERUN) has every method on every scene at one seed, the former
    rerun's table is shown and says how many of the new runs exist; then the new one is shown."""
    r = _results()
    folders = {r.RERUN: tmp_path / "rerun", "runs": tmp_path / "former"}
    monkeypatch.setattr(r, "records_dir", lambda study, sub: folders[sub])
    cells = [(b, stdr, sc) for b in r.BASELINES for stdr in (False, True) for sc in r.HEADLINE_SCENES]
    for b, stdr, sc in cells:
        _record(folders["runs"], b, stdr, sc, 0, 20.0 + stdr)
    _record(folders[r.RERUN], "deform", True, r.HEADLINE_SCENES[0], 0, 30.0)
    means, prov = r.headline()
    assert means["deform+STDR"]["psnr"] == pytest.approx(21.0)
    assert f"has 1 of its {r.HEADLINE_PLANNED} runs, the rest queued" in prov["runs"]
    for b, stdr, sc in cells[1:]:
        if (b, stdr, sc) != ("deform", True, r.HEADLINE_SCENES[0]):
            _record(folders[r.RERUN], b, stdr, sc, 0, 30.0 + stdr)
    _record(folders[r.RERUN], "deform", False, r.HEADLINE_SCENES[0], 0, 30.0)
    means, prov = r.headline()
    assert means["deform+STDR"]["psnr"] == pytest.approx((30.0 + 3 * 31.0) / 4) and "replaces this table" not in prov["runs"]
    assert prov["runs"] == f"32 (seed 0 complete; 32 of the {r.HEADLINE_PLANNED} planned recorded, the rest queued)"
    assert prov["source"].startswith(f"{r.RERUN}/ in ") and f"--code <a worktree at {r.RERUN_CODE}>" in prov["command"]


# ----------------------------------------------------------------- studies/ops_per_step.py
def _res(label, rows):
    return {"label": label, "code": {"commit": label * 5, "dirty": False}, "scene": "/x/jumpingjacks",
            "rows": [{"experiment": e, "ops": o, "compute_ops": c} for e, o, c in rows]}


def test_each_later_count_is_set_against_the_first():
    a = _res("before", [("dnerf_deform", 500, 300), ("dnerf_4dgs", 1900, 1400)])
    b = _res("after", [("dnerf_deform", 450, 285), ("dnerf_4dgs", 700, 480)])
    c = _res("fused", [("dnerf_deform", 350, 147)])  # 4dgs not counted: its row is left out
    text = compare(a, b, c)
    lines = [ln for ln in text.splitlines() if ln.startswith("| dnerf")]
    assert lines == ["| dnerf_deform | 500 | 450 (0.90) | 350 (0.70) | 300 | 285 (0.95) | 147 (0.49) |"]
    assert "Ratios are to before" in text
    assert "| dnerf_4dgs | 1900 | 700 (0.37) | 1400 | 480 (0.34) |" in compare(a, b)


def test_compare_needs_two_counts(tmp_path, capsys):
    p = tmp_path / "a.json"
    p.write_text("{}")
    with pytest.raises(SystemExit):
        main(["--compare", str(p)])
    assert "at least two" in capsys.readouterr().err
