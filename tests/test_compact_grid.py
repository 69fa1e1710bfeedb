"""The compact-grid study's rule (studies/compact_grid.py, research/measurements/compact_grid/
protocol.md) on synthetic records: adopt only when every run is measured and each 4DGS method's
mean file PSNR stays within the bound of the 32-channel file's."""
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from studies.compact_grid import BOUND, EXPERIMENTS, SCENES, decide_records  # noqa: E402


def _case(delta, scenes=SCENES):
    """records whose file PSNR is the reference's + delta(exp, scene), at half the bytes"""
    ref = {(e, s): {"file_psnr": 30.0, "file_bytes": 1000} for e in EXPERIMENTS for s in SCENES}
    recs = [{"experiment": e, "scene": s, "file": {"psnr": 30.0 + delta(e, s)}, "file_bytes": 500}
            for e in EXPERIMENTS for s in scenes]
    return decide_records(recs, ref)


def test_both_methods_within_the_bound_adopt_the_grid():
    d = _case(lambda e, s: BOUND + 0.01 if s == SCENES[0] else 0.0)  # one scene just inside, mean well inside
    assert d["complete"] and d["adopt"]
    assert d["per_method"][EXPERIMENTS[0]]["bytes_ratio"] == pytest.approx(0.5)
    assert d["per_method"][EXPERIMENTS[0]]["delta_worst"] == pytest.approx(BOUND + 0.01)


def test_one_method_past_the_bound_refuses_it_even_when_the_other_gains():
    d = _case(lambda e, s: 0.5 if e == EXPERIMENTS[0] else 1.2 * BOUND)
    assert d["complete"] and not d["adopt"]
    assert d["per_method"][EXPERIMENTS[1]]["delta_mean"] == pytest.approx(1.2 * BOUND)


def test_a_partial_measurement_adopts_nothing():
    d = _case(lambda e, s: 0.0, scenes=SCENES[:3])
    assert not d["complete"] and not d["adopt"] and d["per_method"][EXPERIMENTS[0]]["runs"] == 3


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
