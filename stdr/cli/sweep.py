"""Hydra callback for sweeps (stdr/configs/train.yaml: hydra.callbacks.sweep_report)."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig

from ..tools.runqueue import FAILURES

#: failed jobs of the last sweep this process ran (stdr-train -m exits 1 when there were any)
LAST_SWEEP = {"failed": 0}


class SweepReport(Callback):
    """At the start of a sweep, clear the previous failure list (its jobs run again unless they
    have finished since); at the end, list this sweep's failed jobs with their overrides and logs
    and say how to rerun them. Failed jobs do not stop the others (stdr.cli.train.sweep_job), but
    the sweep's command then exits 1, so that `stdr-train -m ... && stdr-eval ...` stops there."""

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        f = Path(config.hydra.sweep.dir) / FAILURES
        if f.is_file():
            f.rename(f.with_suffix(".previous.jsonl"))

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        sweep = Path(config.hydra.sweep.dir)
        f = sweep / FAILURES
        fails = [json.loads(line) for line in f.read_text().splitlines() if line.strip()] if f.is_file() else []
        LAST_SWEEP["failed"] = len(fails)
        if not fails:
            print(f"[stdr] sweep finished, no failed jobs: {sweep}  (stdr-eval {sweep} / stdr-chart {sweep})")
            return
        print(f"[stdr] sweep finished with {len(fails)} failed job(s) (details: {f}):")
        for r in fails:
            print(f"  {' '.join(r['overrides'])}\n    {r['error']}\n    log: {r['log']}")
        print("[stdr] rerun the same command: finished runs are skipped, the failed ones run again (exit code 1)")
