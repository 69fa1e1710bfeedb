"""The contribution-pruning study's decision rule (studies/compact.py, protocol.md), on
synthetic records: the rule as written, checked case by case."""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from studies.compact import EXPERIMENTS, SCENES, STDR_VARIANTS, VARIANTS, decide  # noqa: E402


def _recs(delta):
    """Records whose control PSNR is 30 everywhere and variant v's is 30 + delta[v](method)."""
    out = {}
    for exp in EXPERIMENTS:
        for s in SCENES:
            out[(exp, s, "control")] = {"psnr": 30.0}
            for v in [*VARIANTS, *(STDR_VARIANTS if exp.endswith("_stdr") else {})]:
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
