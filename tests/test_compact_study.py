"""The contribution-pruning study's decision rule (studies/compact_prune.py, protocol.md), on
synthetic records: the rule as written, checked case by case."""
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from studies.compact_prune import EXPERIMENTS, SCENES, SCRATCH_VARIANTS, STDR_VARIANTS, VARIANTS, decide  # noqa: E402


def _recs(delta):
    """Records whose control PSNR is 30 everywhere and variant v's is 30 + delta[v](method)."""
    out = {}
    for exp in EXPERIMENTS:
        for s in SCENES:
            out[(exp, s, "control")] = {"psnr": 30.0}
            for v in [*VARIANTS, *(dict(STDR_VARIANTS, **SCRATCH_VARIANTS) if exp.endswith("_stdr") else {})]:
                if v != "control":
                    out[(exp, s, v)] = {"psnr": 30.0 + delta.get(v, lambda e: 0.0)(exp)}
    return out


def test_the_largest_admissible_share_wins_and_time_weight_needs_a_clear_margin():
    d = decide(_recs({"s30": lambda e: -0.02, "s30_tw1": lambda e: -0.01, "s50": lambda e: -0.08,
                      "s50_tw1": lambda e: -0.05}))
    assert d["choice"] == "s50" and all(d["admissible"].values())  # tw1 better by 0.03 < 0.05
    d = decide(_recs({"s30": lambda e: -0.02, "s30_tw1": lambda e: -0.01, "s50": lambda e: -0.09,
                      "s50_tw1": lambda e: -0.02}))
    assert d["choice"] == "s50_tw1"  # better by 0.07


def test_one_method_below_the_bar_rules_a_variant_out():
    worst = EXPERIMENTS[3]
    d = decide(_recs({"s30": lambda e: -0.05, "s30_tw1": lambda e: -0.06,
                      "s50": lambda e: -0.3 if e == worst else 0.0, "s50_tw1": lambda e: -0.2 if e == worst else 0.0}))
    assert not d["admissible"]["s50"] and not d["admissible"]["s50_tw1"] and d["choice"] == "s30"


def test_nothing_admissible_falls_back_to_the_better_s30():
    d = decide(_recs({"s30": lambda e: -0.3, "s30_tw1": lambda e: -0.2, "s50": lambda e: -0.5,
                      "s50_tw1": lambda e: -0.6}))
    assert d["choice"] == "s30_tw1" and "rule 3" in d["why"]


def test_incomplete_records_decide_nothing():
    recs = _recs({v: (lambda e: 0.0) for v in VARIANTS})
    del recs[(EXPERIMENTS[0], SCENES[0], "s50")]
    assert decide(recs)["choice"] is None


def test_the_8bit_mask_joins_only_without_a_measurable_loss():
    base = {"s30": lambda e: 0.0, "s30_tw1": lambda e: 0.0, "s50": lambda e: 0.0, "s50_tw1": lambda e: 0.0}
    assert decide(_recs({**base, "m8": lambda e: -0.01}))["mask_bits_8"] is True
    assert decide(_recs({**base, "m8": lambda e: -0.2 if e == "dnerf_4dgs_stdr" else 0.0}))["mask_bits_8"] is False


def test_time_bins_takes_the_fewest_columns_that_keep_every_stdr_method():
    base = {v: (lambda e: 0.0) for v in ("s30", "s30_tw1", "s50", "s50_tw1", "m8")}
    assert decide(_recs({**base, "tb25": lambda e: -0.05, "tb50": lambda e: 0.0}))["time_bins"] == 25
    # one +STDR method loses more than 0.1 dB with 25 columns: 50
    worst = "dnerf_spgs_stdr"
    assert decide(_recs({**base, "tb25": lambda e: -0.3 if e == worst else 0.0, "tb50": lambda e: -0.08}))["time_bins"] == 50
    d = decide(_recs({**base, "tb25": lambda e: -0.3, "tb50": lambda e: -0.2}))
    assert d["time_bins"] == 0 and d["time_bins_delta_psnr"]["tb50"][worst] == pytest.approx(-0.2)
    recs = _recs({**base, "tb25": lambda e: 0.0, "tb50": lambda e: 0.0})
    del recs[("dnerf_4dgs_stdr", SCENES[1], "tb25")]
    assert decide(recs)["time_bins"] is None  # incomplete: no decision


def _queue(tmp_path, monkeypatch, scenes, step_of):
    """studies.compact_prune.run_queue with the training and checkpoint reads replaced: `step_of(scene)`
    is the step of a trunk's last.previous.pt; each branch 'trains' by writing its metrics.json."""
    import argparse

    import studies.compact_prune as c
    monkeypatch.setattr(c, "SCENES", scenes)
    calls = []

    def fake_branch(args, code, exp, scene, name, keys, src, point):
        calls.append((exp, scene, name, src))
        rec = Path(args.records) / exp / scene / name
        rec.mkdir(parents=True)
        (rec / "metrics.json").write_text("{}")
        return "recorded"
    monkeypatch.setattr(c, "branch_once", fake_branch)
    monkeypatch.setattr(c, "branch_point", lambda ck: {"from_step": step_of(ck.parent.parent.parent.name),
                                                       "train_seconds_at_branch": 1.0})
    args = argparse.Namespace(headline=str(tmp_path / "headline"), seed=2, follow=False, work=str(tmp_path / "work"),
                              code=str(tmp_path), experiments=["dnerf_deform"], dnerf=str(tmp_path),
                              records=str(tmp_path / "records"), variants=None, hold=False, poll=60.0,
                              scratch=False, scenes=None)
    return c, args, calls


def _trunk(tmp_path, scene, seed, finished=True):
    """A headline run folder with its checkpoints, and its metrics.json once it has finished."""
    d = tmp_path / "headline" / "dnerf_deform" / scene / f"s{seed}" / "checkpoints"
    d.mkdir(parents=True, exist_ok=True)
    for f in ("last.pt", "last.previous.pt"):
        (d / f).write_bytes(b"")
    if finished:
        (d.parent / "metrics.json").write_text("{}")


def test_the_queue_branches_the_chosen_seeds_trunks_at_step_1500_only(tmp_path, monkeypatch):
    c, args, calls = _queue(tmp_path, monkeypatch, ("a", "b", "c"), lambda scene: 1000 if scene == "b" else 1500)
    _trunk(tmp_path, "a", 2)
    _trunk(tmp_path, "b", 2)  # its step-1500 checkpoint is not there: skipped, never branched
    _trunk(tmp_path, "c", 0)  # another seed's trunk: not this queue's
    assert c.run_queue(args) == 1  # b and c are not recorded
    assert {(scene, name) for _, scene, name, _ in calls} == {("a", v) for v in VARIANTS}
    assert all(src.parent.name == "s2" for *_, src in calls)
    calls.clear()
    assert c.run_queue(args) == 1 and calls == []  # resumable: recorded cells are skipped


def test_follow_waits_for_trunks_the_headline_queue_has_yet_to_train(tmp_path, monkeypatch):
    # a trunk still training has an earlier checkpoint as last.previous.pt (step 1000 while it runs 1500-2000)
    done = lambda scene: (tmp_path / "headline" / "dnerf_deform" / scene / "s2" / "metrics.json").is_file()  # noqa: E731
    c, args, calls = _queue(tmp_path, monkeypatch, ("a", "b"), lambda scene: 1500 if done(scene) else 1000)
    args.follow = True
    _trunk(tmp_path, "a", 2)
    _trunk(tmp_path, "b", 2, finished=False)  # still training: its last.previous.pt is not step 1500 yet
    sleeps = []

    def sleep(s):  # while the queue waits, the headline queue finishes scene b's trunk
        sleeps.append(s)
        if len(sleeps) == 2:
            _trunk(tmp_path, "b", 2)
        assert len(sleeps) < 5
    monkeypatch.setattr(c.time, "sleep", sleep)
    assert c.run_queue(args) == 0
    assert len(calls) == 2 * len(VARIANTS) and [n for _, s, n, _ in calls if s == "b"] == list(VARIANTS)


def test_hold_pauses_the_headline_queue_only_while_branches_are_runnable(tmp_path, monkeypatch):
    """--hold: WORK/pause.compact exists while a branch trains, is gone while the queue waits for
    the next trunk, and is removed when the queue ends."""
    c, args, calls = _queue(tmp_path, monkeypatch, ("a", "b"), lambda scene: 1500)
    args.follow, args.hold = True, True
    hold = tmp_path / "headline" / "pause.compact"
    _trunk(tmp_path, "a", 2)
    seen = []
    inner = c.branch_once

    def branch(*a):
        seen.append(("branch", hold.exists()))
        return inner(*a)
    monkeypatch.setattr(c, "branch_once", branch)

    def sleep(s):
        seen.append(("wait", hold.exists()))
        _trunk(tmp_path, "b", 2)
    monkeypatch.setattr(c.time, "sleep", sleep)
    assert c.run_queue(args) == 0
    assert seen == [("branch", True)] * len(VARIANTS) + [("wait", False)] + [("branch", True)] * len(VARIANTS)
    assert not hold.exists()


def test_scratch_runs_train_from_nothing_and_only_while_no_trunk_waits(tmp_path, monkeypatch):
    """--scratch: the time_bins variants (+STDR methods only) train without a trunk, one at a time,
    after the branches of every trunk that is there; without --scratch they never run."""
    c, args, calls = _queue(tmp_path, monkeypatch, ("a",), lambda scene: 1500)
    args.experiments = ["dnerf_deform", "dnerf_deform_stdr"]
    _trunk(tmp_path, "a", 2)
    assert c.run_queue(args) == 1  # deform_stdr's trunk is not there: its cells wait
    assert {n for *_, n, _ in calls} == set(VARIANTS)
    calls.clear()
    args.scratch = True
    assert c.run_queue(args) == 1
    assert [(e, n, src) for e, _, n, src in calls] == [("dnerf_deform_stdr", v, None) for v in SCRATCH_VARIANTS]


def _decision(m8: float):
    base = {"s30": lambda e: -0.02, "s30_tw1": lambda e: -0.03, "s50": lambda e: -0.4, "s50_tw1": lambda e: -0.4}
    return decide(_recs({**base, "m8": lambda e: m8}))


def test_the_compact_run_is_the_chosen_variant_or_a_preset_branch_with_8_bits():
    from studies.compact_prune import preset_of
    d = _decision(-0.01)  # rule 5 admits 8 bits: +STDR methods need a branch no val variant has
    assert d["choice"] == "s30" and d["mask_bits_8"] is True
    assert preset_of(d, "dnerf_scgs") == ("s30", VARIANTS["s30"])
    assert preset_of(d, "dnerf_scgs_stdr") == ("preset", [*VARIANTS["s30"], "stdr.mask_bits=8"])
    d = _decision(-0.3)
    assert preset_of(d, "dnerf_scgs_stdr") == ("s30", VARIANTS["s30"])


def _test_stage(tmp_path, monkeypatch, m8: float):
    """studies.compact_prune.run_test over val records of one decision, with training and evaluation
    replaced by writers of their records."""
    import argparse
    import json

    import studies.compact_prune as c
    recs = _recs({"s30": lambda e: -0.02, "s30_tw1": lambda e: -0.03, "s50": lambda e: -0.4,
                  "s50_tw1": lambda e: -0.4, "m8": lambda e: m8})
    monkeypatch.setattr(c, "load_records", lambda root: recs)
    trained, evaluated = [], []

    def fake_branch(args, code, exp, scene, name, keys, src, point):
        trained.append((exp, scene, name, tuple(keys)))
        (Path(args.records) / exp / scene / name).mkdir(parents=True)
        (Path(args.records) / exp / scene / name / "metrics.json").write_text("{}")
        return "recorded"

    def fake_eval(args, code, run, out, meta):
        evaluated.append((meta["experiment"], meta["scene"], meta["role"], run.name))
        out.mkdir(parents=True)
        (out / "metrics.json").write_text(json.dumps({"test": {}}))
        return "recorded"
    monkeypatch.setattr(c, "branch_once", fake_branch)
    monkeypatch.setattr(c, "evaluate_once", fake_eval)
    monkeypatch.setattr(c, "branch_point", lambda ck: {"from_step": 1500, "train_seconds_at_branch": 1.0})
    for exp in EXPERIMENTS:
        for scene in SCENES:
            d = tmp_path / "h" / exp / scene / "s2" / "checkpoints"
            d.mkdir(parents=True)
            (d / "last.previous.pt").write_bytes(b"")
    args = argparse.Namespace(headline=str(tmp_path / "h"), seed=2, work=str(tmp_path / "work"), code=str(tmp_path),
                              experiments=None, dnerf=str(tmp_path), records=str(tmp_path / "records"),
                              test_records=str(tmp_path / "test"))
    return c, args, trained, evaluated


def test_the_test_stage_trains_only_the_missing_preset_branches_and_evaluates_full_and_compact(tmp_path, monkeypatch):
    c, args, trained, evaluated = _test_stage(tmp_path, monkeypatch, m8=-0.01)
    assert c.run_test(args) == 0
    stdr = [e for e in EXPERIMENTS if e.endswith("_stdr")]
    assert sorted(trained) == sorted((e, s, "preset", (*VARIANTS["s30"], "stdr.mask_bits=8"))
                                     for e in stdr for s in SCENES)
    assert len(evaluated) == len(EXPERIMENTS) * len(SCENES) * 2
    for exp, scene, role, run in evaluated:
        assert run == ("control" if role == "full" else "preset" if exp in stdr else "s30")
    trained.clear(), evaluated.clear()
    assert c.run_test(args) == 0 and trained == [] and evaluated == []  # resumable


def test_a_missing_trunk_fails_its_preset_cell_only(tmp_path, monkeypatch):
    c, args, trained, evaluated = _test_stage(tmp_path, monkeypatch, m8=-0.01)
    (tmp_path / "h" / "dnerf_scgs_stdr" / SCENES[0] / "s2" / "checkpoints" / "last.previous.pt").unlink()
    assert c.run_test(args) == 1  # reported, not recorded
    assert ("dnerf_scgs_stdr", SCENES[0], "preset") not in {t[:3] for t in trained}
    assert ("dnerf_scgs_stdr", SCENES[0], "compact", "preset") not in evaluated  # never evaluated without its run
    assert len(trained) == 4 * len(SCENES) - 1


def test_the_test_stage_refuses_an_undecided_study(tmp_path, monkeypatch):
    c, args, trained, evaluated = _test_stage(tmp_path, monkeypatch, m8=-0.01)
    full = c.load_records(None)
    monkeypatch.setattr(c, "load_records", lambda root: {k: v for k, v in full.items() if k[2] != "m8"})
    with pytest.raises(SystemExit, match="incomplete"):
        c.run_test(args)
    assert trained == [] and evaluated == []


def test_the_test_table_checks_each_target_on_per_scene_ratios(tmp_path, monkeypatch):
    import json

    import studies.compact_prune as c
    monkeypatch.setattr(c, "SCENES", ("a", "b"))
    root = tmp_path / "test"
    # per scene: (psnr, gaussians, fps, model_mb, train_seconds), full then compact
    rows = {"full": {"a": (30.0, 1000, 10.0, 4.0, 100.0), "b": (28.0, 2000, 20.0, 8.0, 200.0)},
            "compact": {"a": (29.8, 400, 40.0, 1.0, 100.0), "b": (28.1, 1200, 10.0, 4.0, 200.0)}}
    for exp in EXPERIMENTS:
        for role, per in rows.items():
            for scene, (p, n, fps, mb, ts) in per.items():
                d = root / exp / scene / role
                d.mkdir(parents=True)
                (d / "metrics.json").write_text(json.dumps({"test": {
                    "psnr": p, "ssim": 0.9, "lpips": 0.1, "fps": fps, "num_gaussians": n, "seen_per_frame": 0.5,
                    "model_mb": mb * (2 if exp.endswith("_stdr") else 1), "train_seconds": ts}}))
                (d / "source.json").write_text(json.dumps({"decision": "s30", "mask_bits_8": True}))
    args = type("A", (), {"test_records": str(root)})()
    assert c.test_table(args) == 0
    t = {(x["method"], x["target"]): x for x in json.loads((tmp_path / "table_test.json").read_text())["targets"]}
    psnr = t[("dnerf_deform", "mean PSNR, compact - full (dB)")]
    assert psnr["value"] == pytest.approx((-0.2 + 0.1) / 2) and psnr["met"] is True
    g = t[("dnerf_deform", "Gaussians, compact / full")]  # ratios 0.4 and 0.6: geometric mean sqrt(0.24) = 0.49 <= 0.5
    assert g["value"] == pytest.approx(0.24 ** 0.5) and g["met"] is True
    f = t[("dnerf_deform", "render FPS, compact / full")]  # 4.0 and 0.5: geometric mean 1.41 (the arithmetic 2.25 would pass)
    assert f["value"] == pytest.approx(2 ** 0.5) and f["met"] is False
    m = t[("dnerf_deform_stdr", "model bytes, +STDR / plain (both compact)")]  # 2x everywhere
    assert m["value"] == pytest.approx(2.0) and m["met"] is False
    assert "| deform | +STDR compact | 2 |" in (tmp_path / "table_test.md").read_text()


def test_follow_with_scratch_goes_on_to_the_scratch_runs_after_the_last_branches(tmp_path, monkeypatch):
    """The pass that runs the last branches must not end the queue while scratch runs wait."""
    c, args, calls = _queue(tmp_path, monkeypatch, ("a",), lambda scene: 1500)
    args.experiments, args.follow, args.scratch = ["dnerf_deform_stdr"], True, True
    d = tmp_path / "headline" / "dnerf_deform_stdr" / "a" / "s2" / "checkpoints"
    d.mkdir(parents=True)
    for f in ("last.pt", "last.previous.pt"):
        (d / f).write_bytes(b"")
    (d.parent / "metrics.json").write_text("{}")
    monkeypatch.setattr(c.time, "sleep", lambda s: pytest.fail("nothing to wait for"))
    assert c.run_queue(args) == 0
    assert [n for *_, n, _ in calls] == [*VARIANTS, *STDR_VARIANTS, *SCRATCH_VARIANTS]


def test_the_bytes_split_recovers_a_fixed_part_and_per_gaussian_bytes():
    from studies.compact_prune import bytes_split
    mib = 2 ** 20

    def rec(n, mask_bytes_per_g):  # 0.5 MiB fixed, 236 bytes a Gaussian, the mask on top
        return {"num_gaussians": n, "model_mb": 0.5 + (236 + mask_bytes_per_g) * n / mib,
                "stdr": {"mask_bytes": mask_bytes_per_g * n}}
    recs = {("dnerf_deform_stdr", "full"): {s: rec(10000 + i, 600) for i, s in enumerate(SCENES)},
            ("dnerf_deform_stdr", "compact"): {s: rec(4900 + i, 150) for i, s in enumerate(SCENES)}}
    b = bytes_split(recs)["dnerf_deform_stdr"]
    assert b["fixed_mib"] == pytest.approx(0.5) and b["bytes_per_gaussian"] == pytest.approx(236)
    assert b["mask_mib_compact"] == pytest.approx(_mean_n(4900, 150) / mib)


def _mean_n(n0, per):
    return sum((n0 + i) * per for i in range(len(SCENES))) / len(SCENES)


def test_time_bins_is_decided_once_one_complete_method_rules_both_variants_out():
    base = {v: (lambda e: 0.0) for v in ("s30", "s30_tw1", "s50", "s50_tw1", "m8")}
    recs = _recs({**base, "tb25": lambda e: -0.3 if e == "dnerf_scgs_stdr" else 0.0,
                  "tb50": lambda e: -0.2 if e == "dnerf_scgs_stdr" else 0.0})
    for s in SCENES:  # two other methods not run yet: they cannot bring scgs+STDR's mean back
        for v in ("tb25", "tb50"):
            del recs[("dnerf_4dgs_stdr", s, v)], recs[("dnerf_spgs_stdr", s, v)]
    d = decide(recs)
    assert d["time_bins"] == 0 and d["time_bins_state"] == {"tb25": "out", "tb50": "out"}
    # tb25 out, tb50 still open: no decision yet
    recs = _recs({**base, "tb25": lambda e: -0.3 if e == "dnerf_scgs_stdr" else 0.0, "tb50": lambda e: 0.0})
    del recs[("dnerf_4dgs_stdr", SCENES[0], "tb50")]
    assert decide(recs)["time_bins"] is None
    # tb25 still open: tb50 admitted is not enough (25 would win if it passes)
    recs = _recs({**base, "tb25": lambda e: 0.0, "tb50": lambda e: 0.0})
    del recs[("dnerf_4dgs_stdr", SCENES[0], "tb25")]
    assert decide(recs)["time_bins"] is None
