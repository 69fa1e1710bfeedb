"""The compactness studies' decision rules on synthetic records, checked case by case as written:
the contribution-pruning study (studies/compact_prune.py, protocol.md) and the compact-grid study
(studies/compact_grid.py, research/measurements/compact_grid/protocol.md: adopt only when every
run is measured and each 4DGS method's mean file PSNR stays within the bound of the 32-channel
file's)."""
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import studies.compact_grid as grid  # noqa: E402
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


# ----------------------------------------------------------------- the compact-grid study
def _grid_case(delta, scenes=grid.SCENES):
    """records whose file PSNR is the reference's + delta(exp, scene), at half the bytes"""
    ref = {(e, s): {"file_psnr": 30.0, "file_bytes": 1000} for e in grid.EXPERIMENTS for s in grid.SCENES}
    recs = [{"experiment": e, "scene": s, "file": {"psnr": 30.0 + delta(e, s)}, "file_bytes": 500}
            for e in grid.EXPERIMENTS for s in scenes]
    return grid.decide_records(recs, ref)


def test_both_methods_within_the_bound_adopt_the_grid():
    d = _grid_case(lambda e, s: grid.BOUND + 0.01 if s == grid.SCENES[0] else 0.0)  # one scene just inside, mean well inside
    assert d["complete"] and d["adopt"]
    assert d["per_method"][grid.EXPERIMENTS[0]]["bytes_ratio"] == pytest.approx(0.5)
    assert d["per_method"][grid.EXPERIMENTS[0]]["delta_worst"] == pytest.approx(grid.BOUND + 0.01)


def test_one_method_past_the_bound_refuses_it_even_when_the_other_gains():
    d = _grid_case(lambda e, s: 0.5 if e == grid.EXPERIMENTS[0] else 1.2 * grid.BOUND)
    assert d["complete"] and not d["adopt"]
    assert d["per_method"][grid.EXPERIMENTS[1]]["delta_mean"] == pytest.approx(1.2 * grid.BOUND)


def test_a_partial_measurement_adopts_nothing():
    d = _grid_case(lambda e, s: 0.0, scenes=grid.SCENES[:3])
    assert not d["complete"] and not d["adopt"] and d["per_method"][grid.EXPERIMENTS[0]]["runs"] == 3


def test_the_grid_runs_are_compact_bytes_command_plus_the_grid(tmp_path, monkeypatch):
    """protocol.md: the compact_bytes runs' command, plus the candidate grid and pack.enabled=false."""
    import argparse

    from studies import compact_bytes, compact_grid
    cmds = []  # each run's overrides, as the run queue gets them
    monkeypatch.setattr(compact_bytes, "run_one", lambda overrides, rd, threads=1, log=None: cmds.append(overrides))
    args = argparse.Namespace(work=tmp_path, dnerf=tmp_path, experiments=["dnerf_4dgs"], scenes=["standup"], threads=1)
    compact_bytes.train(args)
    compact_grid.train(args)
    assert cmds[1] == cmds[0] + ["pack.enabled=false", "baseline.hexplane.channels=16"]
    assert "compact=on" in cmds[0] and f"seed={compact_bytes.SEED}" in cmds[0] and "budget=cpu" in cmds[0]
