"""How many runs at once: a short slice of the queue's next run at several concurrency levels, and
the level whose runs finish in what is left of the call.

On one GPU without MPS the processes take turns on it. A launch-bound run keeps the GPU busy for
only part of each step, so a few runs at once raise the throughput; past some level each run only
gets slower, and a call whose runs all take longer than its budget finishes none of them (its
checkpoints stay on a machine that is handed back). So before the chunk, in the same call:

1. For each level N (levels above the number of pending runs are skipped), N copies of the next
   pending run train side by side for `slice_s` seconds in WORK/calibrate/n<N> (removed after).
   Each copy's steps per second is its steps over its loop's seconds (train_profile.json, written
   when the deadline stops it), so start-up is not counted.
2. The slowdown at N is the per-run rate alone over the per-run rate at N (level 1 is required),
   and a run's wall time at N is estimated as its time alone (`alone_s`) times that slowdown
   times a margin. The early steps of a run are not its average steps, so only the ratio of the
   slice's rates is used, never their absolute value.
3. The chosen level finishes the most runs in the seconds left: N x the waves of runs that fit,
   at most the pending runs; on a tie the larger N. If no level finishes a run in time, no chunk
   runs and the record says so (a later call can run with the full budget and the chosen N).

The record (each level's aggregate and per-run steps/s, slowdown and estimate, the choice and
why) goes into the call's entry of the queue file, so the throughput at each N is kept with the
runs it planned. The pure part, `choose`, is separate from the measuring part, `measure`.
"""
from __future__ import annotations

import json
import math
import shutil
import time
from pathlib import Path

from .runqueue import Queue, Run, execute

#: the slices' folder under WORK; removed after the calibration
FOLDER = "calibrate"
#: a run's estimated wall time at N is its time alone x the slowdown x this margin
MARGIN = 1.1


def copy_rate(run_dir: Path) -> float | None:
    """Steps per second of one copy's training loop (its train_profile.json: the steps it reached
    over the seconds of its steps), None when it did not reach the loop or left no profile."""
    f = run_dir / "train_profile.json"
    if not f.is_file():
        return None
    prof = json.loads(f.read_text())
    steps, secs = prof.get("iterations_timed", 0), sum(prof.get("seconds", {}).values())
    return steps / secs if steps > 0 and secs > 0 else None


def measure(run: Run, work: Path, levels, slice_s: float, cores=None, launcher=(), command=None,
            log=print) -> list[dict]:
    """N copies of `run` side by side for `slice_s` seconds at each level N: [{"n", "copies" (how
    many left a rate), "failed" (copies that failed), "steps_per_s" (all copies together),
    "per_run_steps_per_s"}]; a level none of whose copies left a rate has None for both rates."""
    out = []
    for n in levels:
        folder = Path(work) / FOLDER / f"n{n}"
        shutil.rmtree(folder, ignore_errors=True)
        copies = Queue([Run(f"c{i}", list(run.overrides), 0.0) for i in range(n)])
        execute(copies, folder, n, slice_s, cores, launcher, command, log=lambda m: None)
        rates = [r for r in (copy_rate(folder / c.id) for c in copies.runs) if r is not None]
        failed = [c.id for c in copies.runs if c.state == "failed"]
        total = sum(rates) if rates else None
        out.append({"n": n, "copies": len(rates), "failed": len(failed), "steps_per_s": total,
                    "per_run_steps_per_s": total / len(rates) if rates else None})
        log(f"[queue] calibration, {n} at once: " + (f"{total:.1f} steps/s in all, {total / len(rates):.1f} each "
                                                     f"({len(rates)} of {n} copies)" if rates else "no rate")
            + (f", {len(failed)} failed" if failed else ""))
    shutil.rmtree(Path(work) / FOLDER, ignore_errors=True)
    return out


def choose(levels: list[dict], left_s: float, alone_s: float, pending: int, margin: float = MARGIN) -> dict:
    """The level that finishes the most runs in `left_s` seconds (see the module's doc). Adds to
    each level its "slowdown", "est_run_s" and "runs_in_time"; returns {"chosen": N or None,
    "est_run_s": the chosen level's estimate, "why"}. A level with a failed copy or no rate is
    never chosen."""
    alone = next((lv for lv in levels if lv["n"] == 1), None)
    if alone is None or not alone["per_run_steps_per_s"]:
        raise ValueError("--calibrate needs level 1 with a measured rate (the slowdowns are relative to a run alone); "
                         "its copy reached no training step within --slice: give a longer slice, or build the "
                         "extension before the call (stdr-build)")
    best = None
    for lv in levels:
        usable = lv["per_run_steps_per_s"] and not lv["failed"]
        lv["slowdown"] = alone["per_run_steps_per_s"] / lv["per_run_steps_per_s"] if usable else None
        lv["est_run_s"] = alone_s * lv["slowdown"] * margin if usable else None
        lv["runs_in_time"] = min(pending, lv["n"] * math.floor(left_s / lv["est_run_s"])) if usable else 0
        if lv["runs_in_time"] > 0 and (best is None or (lv["runs_in_time"], lv["n"]) > (best["runs_in_time"], best["n"])):
            best = lv
    if best is None:
        return {"chosen": None, "est_run_s": None,
                "why": f"no level finishes a run in the {left_s:.0f} s left (a run alone: {alone_s:.0f} s)"}
    return {"chosen": best["n"], "est_run_s": best["est_run_s"],
            "why": f"{best['runs_in_time']} runs in the {left_s:.0f} s left, the most of any level"}


def calibrate(q: Queue, work: Path, levels, slice_s: float, budget_s: float, alone_s: float | None = None,
              cores=None, launcher=(), command=None, log=print) -> dict:
    """Measure the levels on the next pending run, then choose with the seconds left of
    `budget_s` (counted from this call's start). alone_s: a run's wall seconds alone on this
    machine (default: the run's estimate in the queue file). The record for the call's entry."""
    t0 = time.time()
    pending = [r for r in q.runs if r.state in ("pending", "running")]
    if not pending:
        return {"chosen": None, "est_run_s": None, "why": "no pending run", "levels": []}
    levels = sorted({int(n) for n in levels})
    if levels[0] < 1 or 1 not in levels:
        raise ValueError(f"--calibrate {' '.join(map(str, levels))}: the levels are counts of runs at once, 1 among them")
    use = [n for n in levels if n <= len(pending)]
    first = pending[0]
    alone_s = float(first.est_s if alone_s is None else alone_s)
    measured = measure(first, work, use, slice_s, cores, launcher, command, log)
    left = budget_s - (time.time() - t0)
    pick = choose(measured, left, alone_s, len(pending))
    rec = {"run": first.id, "slice_s": slice_s, "alone_s": alone_s, "margin": MARGIN, "levels": measured,
           "skipped_levels": [n for n in levels if n not in use], "left_s": round(left, 1),
           "wall_s": round(time.time() - t0, 1), **pick}
    log(f"[queue] calibration: {pick['why']}" + (f": {pick['chosen']} at once, about {pick['est_run_s']:.0f} s a run"
                                                   if pick["chosen"] else ""))
    return rec
