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
    # val at 10: a s0 -1.00, b s1 -1.00; one scene a seed; sd 0
    assert ("Val Δ at 10, pair by pair: a s0 -1.00, b s1 -1.00. By seed: seed 0: -1.00 (n = 1); "
            "seed 1: -1.00 (n = 1), standard deviation over the pairs 0.00 dB.") in text
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


def _three(tmp, scene, seed, plain, default, variant, secs=(10.0, 10.0)):
    """plain / default +STDR / nogate val PSNR at the last step (train and test equal val)."""
    for method, v in (("deform", plain), ("deform_stdr", default), ("deform_stdr__nogate", variant)):
        if v is not None:
            _rec(tmp, scene, seed, method, {5: (v, v, v), 10: (v, v, v)})
    for method, s in zip(("deform_stdr", "deform_stdr__nogate"), secs):
        p = tmp / "records" / method / f"{scene}_s{seed}.json"
        if p.is_file():
            r = json.loads(p.read_text())
            r["final_test"]["train_seconds"] = s
            p.write_text(json.dumps(r))


def test_the_decision_needs_both_rules_and_every_scene_and_seed(tmp_path):
    _three(tmp_path, "a", 0, 30.0, 29.0, 30.2)
    _three(tmp_path, "b", 1, 20.0, 20.5, 20.4)
    by = lb.by_run(lb.load_records(tmp_path))
    d = lb.decide(by, "deform_stdr__nogate")
    # raises +1.2 and -0.1: mean +0.55; worst -0.1; level: (+0.2, +0.4) -> +0.30
    assert d["triples"] == ["a s0", "b s1"] and abs(d["mean"] - 0.55) < 1e-9 and abs(d["worst"] + 0.1) < 1e-9
    assert d["r1"] and d["r2"] and d["coverage"] and abs(d["level"] - 0.30) < 1e-9 and d["adopt"]
    assert "**Adopt as the default: yes.**" in lb.table(tmp_path)
    _three(tmp_path, "c", 0, 25.0, None, 25.1)  # a scene without default +STDR: coverage fails
    d = lb.decide(lb.by_run(lb.load_records(tmp_path)), "deform_stdr__nogate")
    assert not d["coverage"] and not d["adopt"] and d["pairs"] == 3


def test_the_decision_refuses_a_worse_triple_or_a_slower_variant(tmp_path):
    _three(tmp_path, "a", 0, 30.0, 29.0, 31.0)
    _three(tmp_path, "a", 1, 30.0, 30.0, 29.6)  # raise +2.0 and -0.4: mean +0.8 but worst < -0.3
    d = lb.decide(lb.by_run(lb.load_records(tmp_path)), "deform_stdr__nogate")
    assert d["r1"] and not d["r2"] and not d["adopt"]
    slow = tmp_path / "slow"
    _three(slow, "a", 0, 30.0, 29.0, 31.0, secs=(10.0, 12.0))
    _three(slow, "a", 1, 30.0, 29.0, 31.0, secs=(10.0, 12.0))  # 1.2x the default's training time
    d = lb.decide(lb.by_run(lb.load_records(slow)), "deform_stdr__nogate")
    assert d["r2"] and not d["r1"] and not d["adopt"]


def test_an_ablation_queued_after_the_change_is_read_against_nogate(tmp_path):
    _three(tmp_path, "a", 0, 30.0, 28.0, 30.5)  # plain, former default, nogate
    _rec(tmp_path, "a", 0, "deform_stdr__fop", {5: (30.2,) * 3, 10: (30.2,) * 3})
    d = lb.decide(lb.by_run(lb.load_records(tmp_path)), "deform_stdr__fop")
    # against nogate (30.5): -0.30, not against the former default (28.0): +2.20
    assert d["reference"] == "deform_stdr__nogate" and abs(d["raise"][0] + 0.3) < 1e-9
    assert not d["coverage"] and not d["adopt"]
    text = lb.table(tmp_path)
    assert "## Decision: does `fop` replace nogate?" in text and "Triples (plain, nogate, fop): 1 (a s0)" in text
    assert "## Decision: does `nogate` replace default +STDR?" in text


def test_by_run_takes_each_run_through_every_point_and_records_it_before_the_next(tmp_path, monkeypatch):
    """--by-run: run A to 2500, 5000, the end, its record; then run B; a run with a record is skipped.
    The training and evaluation of a segment are replaced here by what they leave behind."""
    import argparse
    events = []

    def segment(cells, stop, args):
        assert len(cells) == 1
        c = cells[0]
        step = stop or args.iterations
        events.append((c["id"], step))
        c["state"]["points"].append({"step": step})
        run = args.work / c["id"]
        run.mkdir(parents=True, exist_ok=True)
        (run / "metrics.json").write_text(json.dumps({"test": {"psnr": 30.0, "precision": "bf16", "fps": 9.0}}))

    def recorded():
        return sorted(p.parent.name + "/" + p.stem for p in (tmp_path / "out" / "records").rglob("*.json"))

    monkeypatch.setattr(lb, "_segment", segment)
    real = lb._record
    monkeypatch.setattr(lb, "_record", lambda c, a, t0: (events.append((c["id"], "record", recorded())), real(c, a, t0)))
    args = argparse.Namespace(root=tmp_path / "dnerf", work=tmp_path / "work", seeds=[0], scenes=["a", "b"],
                              methods=["deform"], points=[2500, 5000], threads=1, concurrent=1,
                              records=tmp_path / "out", iterations=10000, extra=[], label="", by_run=True)
    lb.run_queue(args)
    assert events == [("deform__a__s0", 2500), ("deform__a__s0", 5000), ("deform__a__s0", 10000),
                      ("deform__a__s0", "record", []),
                      ("deform__b__s0", 2500), ("deform__b__s0", 5000), ("deform__b__s0", 10000),
                      ("deform__b__s0", "record", ["deform/a_s0"])]
    rec = json.loads((tmp_path / "out" / "records" / "deform" / "b_s0.json").read_text())
    assert [p["step"] for p in rec["points"]] == [2500, 5000, 10000]
    assert rec["final_test"]["precision"] == "bf16" and rec["final_test"]["fps"] == 9.0
    events.clear()
    lb.run_queue(args)  # both recorded: nothing runs
    assert events == []


# ------------------------------------------------------------ the trained table's cap (studies/trained_table.py)
def _cap_study(tmp: Path, delta: dict, at_cap: set = frozenset(), missing=()) -> Path:
    """Seed-0 records at both caps for every baseline and scene: val at step 10,000 is 30 at 20k and
    30 + delta[baseline] at 40k; the runs named in `at_cap` end at 40,000 Gaussians."""
    from studies import trained_table as tt
    for b in tt.BASELINES:
        for s in tt.SCENES:
            for label, val, g in (("", 30.0, 19_900), ("cap40k", 30.0 + delta[b], 40_000 if (b, s) in at_cap else 30_000)):
                if (b, s, label) in missing:
                    continue
                rec = {"scene": s, "seed": 0, "method": f"{b}__{label}" if label else b, "code": "abc1234", "machine": "M",
                       "points": [{"step": 10_000, "val": {"psnr": val}}],
                       "final_test": {"num_gaussians": g, "train_seconds": 100.0}}
                p = tmp / "records" / rec["method"] / f"{s}_s0.json"
                p.parent.mkdir(parents=True, exist_ok=True)
                p.write_text(json.dumps(rec))
    return tmp


def test_the_cap_rule_keeps_takes_or_probes_as_written(tmp_path):
    from studies import trained_table as tt
    level = {"deform": 0.05, "scgs": -0.05, "spgs": 0.08, "4dgs": 0.0}
    assert "**Verdict: keep 20,000.**" in tt.cap_table(_cap_study(tmp_path / "a", level))
    # one baseline held back by more than 0.3 dB while the mean stays level: kept, and that one is named
    text = tt.cap_table(_cap_study(tmp_path / "b", {"deform": 0.35, "scgs": -0.02, "spgs": -0.02, "4dgs": -0.02}))
    assert "**Verdict: keep 20,000.**" in text and "a cap of their own follows: deform." in text
    up = {"deform": 0.4, "scgs": 0.3, "spgs": 0.2, "4dgs": 0.1}
    all_scenes = {(b, s) for b in tt.BASELINES for s in tt.SCENES}
    four = set(sorted(all_scenes)[:4])
    assert "**Verdict: take 40,000.**" in tt.cap_table(_cap_study(tmp_path / "c", up, at_cap=four))
    five = set(sorted(all_scenes)[:5])  # more than 4 of 16 end at the doubled cap: not settled
    assert "**Verdict: not settled: probe 80,000" in tt.cap_table(_cap_study(tmp_path / "d", up, at_cap=five))
    down = {b: -0.2 for b in up}  # a worse model with more Gaussians is not taken
    assert "**Verdict: not settled: probe 80,000" in tt.cap_table(_cap_study(tmp_path / "e", down))


def test_the_cap_table_gives_no_verdict_before_all_16_pairs(tmp_path):
    from studies import trained_table as tt
    text = tt.cap_table(_cap_study(tmp_path, {b: 0.0 for b in tt.BASELINES}, missing={("4dgs", "standup", "cap40k")}))
    assert "Verdict" not in text and "missing 1: 4dgs/standup" in text
    assert text.count("| scgs |") == 4 and "| 4dgs | standup |" not in text


def test_the_stdr_table_gives_each_baselines_delta_with_its_interval_and_names_what_is_missing(tmp_path):
    from scipy import stats

    from studies import trained_table as tt
    deltas = {("bouncingballs", 0): 0.5, ("bouncingballs", 1): 0.25, ("standup", 0): -0.25, ("standup", 1): 0.5}
    for (scene, seed), d in deltas.items():
        for method, psnr in (("deform", 30.0), ("deform_stdr", 30.0 + d)):
            rec = {"scene": scene, "seed": seed, "method": method, "code": "abc1234", "machine": "M",
                   "points": [{"step": s, "val": {"psnr": psnr}, "test": {"psnr": psnr - (10_000 - s) / 1000 * (method == "deform")}}
                              for s in (5_000, 10_000)],
                   "final_test": {"psnr": psnr, "ssim": 0.9, "lpips": 0.1, "num_gaussians": 1000,
                                  "train_seconds": 100.0 if method == "deform" else 130.0, "fps": 20.0, "model_mb": 5.0}}
            p = tmp_path / "records" / method / f"{scene}_s{seed}.json"
            p.parent.mkdir(parents=True, exist_ok=True)
            p.write_text(json.dumps(rec))
    ds = list(deltas.values())
    half = stats.t.ppf(0.975, len(ds) - 1) * stats.tstd(ds) / len(ds) ** 0.5
    lo, hi = tt.interval(ds)
    assert abs(lo - (0.25 - half)) < 1e-3 and abs(hi - (0.25 + half)) < 1e-3
    text = tt.stdr_table(tmp_path)
    row = next(ln for ln in text.splitlines() if ln.startswith("| deform |"))
    assert row.startswith(f"| deform | 4 | +0.25 | {0.25 - half:+.2f} to {0.25 + half:+.2f} | 1: standup s0 (-0.25) |")
    assert "| 1.30x |" in row and "| scgs | 0 |" in text
    assert "Runs in: 8 of 64" in text and "scgs/bouncingballs_s0" in text and "deform/hellwarrior_s1" in text
    # the chart: at step 5,000 plain is 5 dB behind, so STDR's Δ there is 5 + the final Δ
    assert [p["delta"] for p in tt.stdr_pairs(tt._records(tmp_path), "deform", step=5_000)] == [5.5, 5.25, 4.75, 5.5]
    assert tt.delta_chart(tmp_path, tmp_path / "charts" / "d.png") and (tmp_path / "charts" / "d.png").stat().st_size > 1000
    assert not tt.delta_chart(tmp_path / "none", tmp_path / "none.png") and not (tmp_path / "none.png").exists()
