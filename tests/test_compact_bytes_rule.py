"""The compact-bytes study's rule (studies/compact_bytes.py, research/measurements/compact_bytes/
protocol.md) on synthetic val records: each step as written, case by case."""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from studies.compact_bytes import BASELINES, EXPERIMENTS, GRID, MASK, SCENES, STEP1, decide_records  # noqa: E402

SIZE = {"default": 100, "q8m16": 60, "q8m16_vq4096": 40, "q8m16_vq1024": 30, "q8m16_vq256": 25,
        "q8m16_vq1024_ft": 30, "q8m16_vq256_ft": 25}


def _recs(delta, extra=None):
    """Records with candidate c's val delta = delta.get(c, 0)(experiment, scene); `extra` adds
    candidates name -> (bytes, delta function)."""
    out = []
    for exp in EXPERIMENTS:
        for sc in SCENES:
            cands = {c: {"bytes": SIZE[c], "delta_psnr": delta.get(c, lambda e, s: 0.0)(exp, sc)} for c in STEP1}
            for name, (b, f) in (extra or {}).items():
                if f(exp, sc) is not None:
                    cands[name] = {"bytes": b, "delta_psnr": f(exp, sc)}
            out.append({"experiment": exp, "scene": sc, "candidates": cands})
    return out


def test_step1_takes_the_smallest_candidate_within_both_bounds():
    bad = lambda e, s: -0.2  # noqa: E731
    d = decide_records(_recs({"q8m16_vq256": bad, "q8m16_vq256_ft": bad, "q8m16_vq1024": lambda e, s: -0.06}), {})
    # vq1024 (k-means) fails the mean bound, its fine-tuned form (delta 0) passes at the same bytes
    assert d["step1"] == "q8m16_vq1024_ft" and d["complete"] and "step2" not in d


def test_one_method_over_its_bound_rules_a_candidate_out_even_when_the_mean_passes():
    one = lambda e, s: -0.12 if e == "dnerf_spgs" else 0.0  # noqa: E731  mean -0.015, spgs -0.12
    d = decide_records(_recs({c: one for c in ("q8m16_vq256", "q8m16_vq256_ft", "q8m16_vq1024",
                                                "q8m16_vq1024_ft")}), {})
    assert d["step1"] == "q8m16_vq4096"


def test_equal_bytes_go_to_the_smaller_loss():
    d = decide_records(_recs({"q8m16_vq256": lambda e, s: -0.01, "q8m16_vq256_ft": lambda e, s: -0.03}), {})
    assert d["step1"] == "q8m16_vq256"


def test_steps_2_and_3_wait_for_a_stable_step_1_and_the_mask_must_pass_for_every_baseline():
    s1 = "q8m16_vq256"
    extra = {f"{s1}+{g}": (b, (lambda e, s, d=d: d if "4dgs" in e else None))
             for g, b, d in (("g16", 50, 0.0), ("g8", 30, -0.02), ("g4", 20, -0.3))}
    masks = {"m8": 10, "derived8": 6, "derived4": 4, "derivedvq": 3}
    for m, b in masks.items():
        for g in ("g16", "g8"):
            loss = {"derivedvq": -0.2, "derived4": -0.04, "derived8": -0.01}.get(m, 0.0)
            # derived4 fails for scgs+STDR only
            extra[f"{s1}+{g}+{m}"] = (b, (lambda e, s, m=m, g=g, loss=loss:
                                          None if not e.endswith("_stdr") or (g == "g8") != ("4dgs" in e)
                                          else (-0.2 if m == "derived4" and "scgs" in e else loss)))
    recs = _recs({}, extra)
    assert "step2" not in decide_records(recs, {})
    assert "step2" not in decide_records(recs, {"step1": "default"})
    d = decide_records(recs, {"step1": s1})
    assert d["step1"] == s1 and d["step2"] == "g8" and d["step3"] == "derived8"
    assert {r["name"]: r["passes"] for r in d["step3_rows"]} == {"m8": True, "derived8": True, "derived4": False,
                                                                 "derivedvq": False}
    assert set(GRID) == {"g16", "g8", "g4"} and set(MASK) == set(masks) and len(BASELINES) == 4


def test_a_form_measured_on_some_runs_only_is_no_decision_yet():
    """A cheaper candidate (or mask form) with good numbers on the runs measured so far does not
    win while any run of its methods lacks it; once every run has it, the rule reads it."""
    s1 = "q8m16_vq256"
    recs = _recs({"q8m16_vq256_ft": lambda e, s: -0.2})  # the fine-tuned form fails: vq256 is the smallest
    assert decide_records(recs, {})["step1"] == s1
    for r in recs:
        if r["scene"] not in SCENES[:2]:
            del r["candidates"][s1]  # measured on two scenes of each method only
    d = decide_records(recs, {})
    assert d["step1"] == "q8m16_vq1024"  # the next smallest measured everywhere
    assert {r["name"]: (r["runs"], r["of"]) for r in d["step1_rows"]}[s1] == (2 * len(EXPERIMENTS), len(recs))
    extra = {f"{s1}+{g}": (b, (lambda e, s: 0.0 if "4dgs" in e else None)) for g, b in (("g16", 50), ("g8", 30), ("g4", 20))}
    for m, b in {"m8": 10, "derived8": 6, "derived4": 4, "derivedvq": 3}.items():
        for g in ("g16", "g4"):  # step 2 picks g4 (all pass): 4dgs+STDR reads its masks on g4
            extra[f"{s1}+{g}+{m}"] = (b, (lambda e, s, g=g: None if not e.endswith("_stdr") or (g == "g4") != ("4dgs" in e)
                                          or (s != SCENES[0] and "deform" in e) else 0.0))
    d = decide_records(_recs({}, extra), {"step1": s1})
    assert d["step2"] == "g4" and d["step3"] is None and not d["step3_measured"]
    assert all(r["runs"] == 3 * len(SCENES) + 1 and not r["passes"] for r in d["step3_rows"])


def test_the_test_table_reports_each_target_with_its_value_and_draws_the_chart(tmp_path):
    import json

    from studies.compact_bytes import table
    full, n = {}, 0
    for exp, mib, fbytes in (("dnerf_deform", 4.0, 0.5), ("dnerf_deform_stdr", 10.0, 0.7)):
        for sc in SCENES[:2]:
            full[(exp, sc)] = {"psnr": 30.0, "ssim": 0.95, "lpips": 0.08, "fps": 50.0, "model_mb": mib}
            full[(exp, sc, "compact")] = {"psnr": 29.99, "model_mb": mib / 2}
            rec = {"experiment": exp, "scene": sc, "codecs": "q8m16_vq256_ft", "bytes": fbytes * 2**20,
                   "load_s": 0.2 if sc == SCENES[0] else 0.4,
                   "model_bytes": mib / 2 * 2**20, "code": "abc", "machine": "m",
                   "model": {"psnr": 29.98, "ssim": 0.95, "lpips": 0.08, "fps": 90.0, "num_gaussians": 100},
                   "file": {"psnr": 29.95 if exp == "dnerf_deform" else 29.8, "ssim": 0.95, "lpips": 0.08,
                            "fps": 91.0 if sc == SCENES[0] else 89.0, "num_gaussians": 100}}
            (tmp_path / "records" / "test").mkdir(parents=True, exist_ok=True)
            (tmp_path / "records" / "test" / f"{exp}__{sc}.json").write_text(json.dumps(rec))
            n += 1
    text = table(tmp_path, full)
    rows = {tuple(c.strip() for c in line.split("|")[1:3]): line for line in text.splitlines()
            if line.startswith("| dnerf_") and ("<=" in line or ">=" in line or "(reported)" in line)}
    # paired: (file / this model) x (old compact / old full) = (0.5 / 2) x 0.5; PSNR (29.95 - 29.98) + (29.99 - 30)
    assert "| 0.125 | **no** |" in rows[("dnerf_deform", "file bytes / full model bytes (paired)")]  # bound 0.10
    assert "| 0.070 | yes |" in rows[("dnerf_deform_stdr", "file bytes / full model bytes (paired)")]
    assert "| -0.040 | yes |" in rows[("dnerf_deform", "PSNR file - full, dB (paired)")]
    assert "| -0.190 | **no** |" in rows[("dnerf_deform_stdr", "PSNR file - full, dB (paired)")]
    assert "| -0.050 | – |" in rows[("dnerf_deform", "PSNR file - full, dB (unpaired)")]
    assert "| 1.400 | **no** |" in rows[("dnerf_deform_stdr", "+STDR file / plain file bytes")]  # 0.7 / 0.5
    assert "| (reported) | 1.000 | – |" in rows[("dnerf_deform", "FPS file / compact=on")]  # sqrt(91 * 89) / 90, per method
    fps = next(x for x in text.splitlines() if x.startswith("| all | FPS file / compact=on, geometric mean over the 4 runs"))
    assert f"| >= 1 | {(91 * 89) ** 0.5 / 90:.3f} | **no** |" in fps  # below 1 in the fourth digit
    assert "Loading the file (`load_model`, median of 3 reads" in text and "0.200 to 0.400 s over 4 runs" in text
    assert (tmp_path / "charts" / "size_accuracy_bytes.png").is_file() and n == 4
    # `where` records (the same models counted in a later file format) add the ratio of their totals
    for exp, per in (("dnerf_deform", 40), ("dnerf_deform_stdr", 44)):
        for sc in SCENES[:2]:
            (tmp_path / "records" / "where").mkdir(parents=True, exist_ok=True)
            (tmp_path / "records" / "where" / f"{exp}__{sc}.json").write_text(json.dumps(
                {"experiment": exp, "scene": sc, "num_gaussians": 1000, "params": {"means": per * 1000},
                 "deform": 9000, "plugins": {}, "other": 1000, "code": "def"}))
    text = table(tmp_path, full)
    row = next(x for x in text.splitlines() if "format of def" in x)
    assert row.startswith("| dnerf_deform_stdr |") and f"| {54000 / 50000:.3f} | yes |" in row
    assert "(`where`, code def:" in text
    assert f"all 4 runs: {89 / 90:.3f} to {91 / 90:.3f} (geometric mean {(91 * 89 * 91 * 89) ** 0.25 / 90:.3f})" in text
    assert "as many Gaussians as the run's" in text


def test_a_run_of_stdrs_former_default_is_refused_by_name(tmp_path):
    """Protocol amendment 3: +STDR runs trained with stdr.mask_after_freeze=true are moved aside,
    never measured as the preset's."""
    import pytest
    from studies.compact_bytes import _refuse_a_former_default
    rd = tmp_path / "dnerf_deform_stdr" / "standup"
    rd.mkdir(parents=True)
    (rd / "config.yaml").write_text("stdr:\n  enabled: true\n  mask_after_freeze: true\n")
    with pytest.raises(SystemExit, match="mask_after_freeze=true.*amendment 3.*gated"):
        _refuse_a_former_default(rd)
    (rd / "config.yaml").write_text("stdr:\n  enabled: true\n  mask_after_freeze: false\n")
    _refuse_a_former_default(rd)  # the current default: measured
    _refuse_a_former_default(tmp_path / "not_trained")  # no folder yet: trained by the queue


def test_where_splits_the_stdr_over_plain_ratio_into_count_and_added_bytes():
    from studies.compact_bytes import where_rows, where_section
    recs = []
    for sc in SCENES[:2]:  # plain: 1000 Gaussians x 40 B + 10 KiB; +STDR: 1200 x (40 + 2) B + 12 KiB
        recs.append({"experiment": "dnerf_deform", "scene": sc, "num_gaussians": 1000,
                     "params": {"means": 6000, "shN": 34000}, "deform": 10240, "plugins": {}})
        recs.append({"experiment": "dnerf_deform_stdr", "scene": sc, "num_gaussians": 1200,
                     "params": {"means": 7200, "shN": 40800, "stdr_cond": 2400}, "deform": 10240,
                     "plugins": {"stdr": 2048}})
    rows = {r["experiment"]: r for r in where_rows(recs)}
    assert rows["dnerf_deform"]["per_gaussian"] == 40.0 and rows["dnerf_deform_stdr"]["per_gaussian"] == 42.0
    assert rows["dnerf_deform_stdr"]["fixed"] == 12288 and rows["dnerf_deform_stdr"]["by_table"]["stdr_cond"] == 2.0
    line = next(x for x in where_section(list(rows.values())) if x.startswith("| deform |"))
    # (1200 * 42 + 12288) / (1000 * 40 + 10240) = 62688 / 50240
    assert line == f"| deform | {62688 / 50240:.3f} | 1.200 | +2.0 | +2.0 |"


def test_where_bytes_add_up_to_the_compact_files_bytes(tmp_path):
    """where_bytes' parts sum to what write_compact reports for the same model and codecs."""
    import numpy as np
    import torch

    from stdr.compact.pack import write_compact
    from stdr.model import build_model
    from stdr.testing import make_cfg
    from studies.compact_bytes import where_bytes
    cfg = make_cfg(["experiment=dnerf_4dgs"])
    torch.manual_seed(0)
    model = build_model(cfg, np.linspace(0, 1, 8), torch.zeros(3), torch.device("cpu"), torch.rand(300, 3), torch.rand(300, 3))
    spec = {"means": "q16", "shN": "vq:64", "*": "q8", "state": "f16", "state:grids": "q8"}
    w = where_bytes(model, {**spec, "finetune": 500})  # the fine-tune changes no byte: left out
    total = sum(w["params"].values()) + w["deform"] + sum(w["plugins"].values()) + w["other"]
    assert w["num_gaussians"] == 300 and total == write_compact(model, tmp_path / "m.stdrc", spec)["bytes"]
    assert w["params"]["means"] >= 300 * 3 * 2 and w["deform"] > 0 and 0 <= w["other"] < 1024
