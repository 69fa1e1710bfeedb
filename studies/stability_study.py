"""The degradation study of docs/stability.md through the run queue, breadth first and resumable.

    python -m studies.stability_study DNERF_ROOT [--out OUT] [--work WORK] [--presets PRESET:SEED ...]
        [--code CHECKOUT] [--dry-run] [-- STDR-TRAIN OVERRIDES]

Every registered baseline, plain and +STDR, on the sweep's D-NeRF scenes (stdr/configs/sweep/
stability.yaml), under each stress preset and seed, in the order that gives a readable table
soonest (GRID: the unstressed runs, level 3 of every stress, seeds 1-2 of the unstressed runs,
level 1, then level 2). A run is planned only if OUT/table.json (the committed table, runs of any
machine) lacks it, and it is skipped when WORK/<id> already holds its metrics.json, so stopping and
starting again, here or on another machine, loses only the run in progress. The runs go through
the one run queue (stdr.tools.runqueue.execute, one at a time; WORK/queue.json keeps their state),
each with the sweep's data and train keys, in WORK/<experiment>/<scene>/<stress>/s<seed>. Then the
table and chart (studies.stability) from OUT/table.json and WORK together, so a study spread over
machines adds up.

`--code CHECKOUT` trains with another checkout's stdr-train (its scripts/run.sh), e.g. a worktree
frozen at the study's commit, while the table comes from this one. `--dry-run` lists the planned
runs in order and trains nothing.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import yaml

from stdr.tools.runqueue import Queue, Run, execute
from studies.stability import RUN_KEY, load_records, missing_runs, study_grid
from studies.stability import main as stability_table

ROOT = Path(__file__).resolve().parents[1]

STRESSES = ("window", "fraction", "sparse", "pose", "jitter")
GRID = (["none:0"] + [f"{s}_3:0" for s in STRESSES] + ["none:1", "none:2"]
        + [f"{s}_{lv}:0" for lv in (1, 2) for s in STRESSES])
EST_S = 240.0  # a run at budget=cpu on 2 cores (the queue's estimate; no deadline here)


def command(code: Path) -> list[str]:
    """What each run executes: the checkout's stdr-train."""
    return [str(code.resolve() / "scripts" / "run.sh"), "python", "-m", "stdr.cli.train"]


def sweep_keys() -> list[str]:
    """The study sweep's own data and train keys as overrides (its data.path interpolation aside:
    each run gets its scene's path)."""
    from stdr.config import CONFIG_DIR
    sweep = yaml.safe_load((CONFIG_DIR / "sweep" / "stability.yaml").read_text())
    return [f"{section}.{k}={str(v).lower() if isinstance(v, bool) else v}"
            for section in ("data", "train") for k, v in (sweep.get(section) or {}).items() if k != "path"]


def plan(root: Path, presets: list[str], table: Path | None, work: Path, extra: list[str]) -> Queue:
    """The queue of the presets' runs that `table` lacks, in the presets' order; a run whose folder
    under `work` holds its metrics.json is done already."""
    for p in presets:
        stress, _, seed = p.partition(":")
        if not seed.isdigit() or not (ROOT / "stdr" / "configs" / "stress" / f"{stress}.yaml").is_file():
            raise SystemExit(f"[study] bad preset {p!r}: want <preset>:<seed> with stdr/configs/stress/<preset>.yaml")
    have = {tuple(r[k] for k in RUN_KEY) for r in load_records(table, "val")} if table else set()
    grid, keys, runs = study_grid(), sweep_keys(), []
    for p in presets:
        stress, _, seed = p.partition(":")
        lacking = missing_runs(have, grid, stress, int(seed))
        if not lacking:
            print(f"[study] {stress} seed {seed}: every run is in {table}")
        for exp, scene in lacking:
            rid = f"{exp}/{scene}/{stress}/s{seed}"
            run = Run(rid, [f"experiment={exp}", "budget=cpu", f"stress={stress}", f"seed={seed}",
                            f"data.path={root / scene}", f"data.name={scene}", *keys, *extra], EST_S)
            if (work / rid / "metrics.json").is_file():
                run.state = "done"
            runs.append(run)
    return Queue(runs)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m studies.stability_study", description=__doc__.splitlines()[0])
    ap.add_argument("dnerf", type=Path, help="a folder of the sweep's D-NeRF scenes")
    ap.add_argument("--out", type=Path, default=ROOT / "research" / "measurements" / "stability",
                    help="the study's folder: its table.json is read, the new table written there")
    ap.add_argument("--work", type=Path, default=Path("multirun") / "stability_queue", help="run folders")
    ap.add_argument("--presets", nargs="+", default=GRID, metavar="PRESET:SEED")
    ap.add_argument("--code", type=Path, default=ROOT, help="the checkout whose scripts/run.sh trains")
    ap.add_argument("--dry-run", action="store_true", help="list the planned runs and train nothing")
    argv = list(sys.argv[1:] if argv is None else argv)
    extra = argv[argv.index("--") + 1:] if "--" in argv else []  # after --: added to every stdr-train
    a = ap.parse_args(argv[:argv.index("--")] if "--" in argv else argv)
    if not (a.code / "scripts" / "run.sh").is_file():
        raise SystemExit(f"[study] --code {a.code}: no scripts/run.sh there")
    table = a.out / "table.json"
    work = a.work.resolve()
    q = plan(a.dnerf.resolve(), a.presets, table if table.is_file() else None, work, extra)
    if a.dry_run:
        for r in q.runs:
            print(r.state, r.id, " ".join(r.overrides))
        return 0
    failed = 0
    if any(r.state == "pending" for r in q.runs):
        execute(q, work, 1, None, command=command(a.code))
        q.save(work / "queue.json")
        failed = sum(r.state == "failed" for r in q.runs)
    inputs = [str(p) for p in (table, work) if p.exists()]
    table_error = None
    if inputs:
        try:
            stability_table([*inputs, "--split", "val", "--out", str(a.out)])
        except SystemExit as e:  # e.g. no unstressed run yet to chart against: the runs are kept
            table_error = e.code if e.code not in (None, 0) else None
    print(f"[study] {sum(r.state == 'done' for r in q.runs)} of {len(q.runs)} planned runs done, {failed} failed"
          + (f"; the table: {table_error}" if table_error else ""))
    return 1 if failed or table_error else 0


if __name__ == "__main__":
    raise SystemExit(main())
