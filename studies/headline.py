"""The D-NeRF headline table, rerun at one commit: 4 baselines x {plain, +STDR} x the four shared
scenes x seeds 0 and 1 (64 runs, budget=cpu, test split; seed 2 left the plan when the trained
table at cpu_long took its compute), breadth first (every method and scene at seed 0, then seed
1), resumable (research/measurements/dnerf_headline_cpu).

    python -m studies.headline DNERF_ROOT [--work WORK] [--code CHECKOUT] [--seeds 0 1] [--dry-run]

The runs go through the project's run queue (`stdr-tool queue`, one at a time), each timed by
scripts/idle_run.py around the --code checkout's stdr-train (a worktree frozen at the table's
commit; default: this checkout). A finished run's records (config.yaml, metrics.json,
history.json, train_profile.json, load.json; no checkpoint) are copied to
research/measurements/dnerf_headline_cpu/runs/<experiment>/<scene>/s<seed>/, and a run whose records
are there already is not planned, so the study goes on from the committed records on any machine.
A run that shared the machine (other jobs took more than 5 % of it) is not recorded and is run
again, up to three sweeps over its seed, before the next seed starts. Then studies/results.py
rebuilds docs/results.md and the README's table.

Run it on an otherwise idle machine: train seconds and FPS are reported. `touch WORK/pause` (or
any WORK/pause.<name>) holds the queue between runs; one call at a time runs on a WORK folder.
"""
from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
from pathlib import Path

from stdr.eval.evaluate import code_version
from stdr.tools.runqueue import Queue, Run, execute

ROOT = Path(__file__).resolve().parents[1]

RECORDS = ROOT / "research" / "measurements" / "dnerf_headline_cpu" / "runs"
SCENES = ("bouncingballs", "hellwarrior", "jumpingjacks", "standup")
EXPERIMENTS = tuple(f"dnerf_{b}{s}" for b in ("deform", "scgs", "spgs", "4dgs") for s in ("", "_stdr"))
KEEP = ("config.yaml", "metrics.json", "history.json", "train_profile.json", "load.json")
SWEEPS = 3


def plan_seed(root: Path, seed: int, records: Path) -> Queue:
    """The seed's runs without records, scene by scene, every method of a scene together; the id is
    the run's place under WORK and under the records (<experiment>/<scene>/s<seed>)."""
    runs = [Run(f"{exp}/{scene}/s{seed}", [f"experiment={exp}", "budget=cpu", f"seed={seed}",
                                           f"data.path={root / scene}", f"data.name={scene}", "data.eval_split=test"], 0.0)
            for scene in SCENES for exp in EXPERIMENTS if not (records / exp / scene / f"s{seed}" / "metrics.json").is_file()]
    return Queue(runs)


def command(code: Path) -> list[str]:
    """What each run executes: the frozen checkout's stdr-train under the idle check. Its stdr is
    the checkout's: on PYTHONPATH, and `python -P` keeps the caller's working directory (another
    checkout, whose stdr would be imported first) off the module path."""
    return [sys.executable, str(ROOT / "scripts" / "idle_run.py"), "--out", "{run_dir}/load.json", "--",
            str(code / "scripts" / "run.sh"), "env", f"PYTHONPATH={code}", "python", "-P", "-m", "stdr.cli.train"]


def checkout_commit(code: Path) -> str | None:
    """The commit the --code checkout has checked out (None outside a git checkout: not checked)."""
    return code_version(root=code)["commit"]


def trained_by(run_dir: Path) -> str:
    """The commit a finished run's metrics.json says trained it ('' when it names none)."""
    m = json.loads((run_dir / "metrics.json").read_text())
    return (next(iter(m.values())) if "code" not in m else m).get("code", {}).get("commit", "")


def book(q: Queue, work: Path, records: Path, commit: str | None = None) -> tuple[list[str], list[str]]:
    """Copy each finished run that had the machine to itself, and was trained by `commit` (the
    --code checkout's; None: any), into the records. Returns (shared, failed): runs to do again
    (their folder removed, so the next sweep trains them from the start) and runs that failed,
    among them a run whose metrics.json names another commit."""
    shared, failed = [], []
    for r in q.runs:
        d = work / r.id
        if r.state == "done" and commit is not None and trained_by(d) != commit:
            r.state, r.error = "failed", (f"trained by code {trained_by(d)[:7] or '(none named)'}, not the --code "
                                          f"checkout's {commit[:7]}: not recorded")
        if r.state == "failed":
            failed.append(r.id)
            print(f"[headline] FAILED {r.id}: {r.error}", file=sys.stderr, flush=True)
        elif r.state == "done":
            load = json.loads((d / "load.json").read_text()) if (d / "load.json").is_file() else {"idle": False}
            if load["idle"]:
                (records / r.id).mkdir(parents=True, exist_ok=True)
                for f in KEEP:
                    if (d / f).is_file():
                        shutil.copy2(d / f, records / r.id / f)
            else:
                print(f"[headline] SHARED {r.id}: other jobs used the machine ({d / 'load.json'}); run again",
                      file=sys.stderr, flush=True)
                shutil.rmtree(d)
                shared.append(r.id)
    return shared, failed


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("dnerf", type=Path, help="a folder of the four D-NeRF scenes")
    ap.add_argument("--work", type=Path, default=ROOT / "outputs" / "headline", help="run folders")
    ap.add_argument("--code", type=Path, default=ROOT, help="the checkout whose scripts/run.sh trains")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--records", type=Path, default=RECORDS)
    ap.add_argument("--dry-run", action="store_true", help="list the runs the next call would train")
    ap.add_argument("--no-results", action="store_true", help="do not rebuild docs/results.md at the end")
    args = ap.parse_args(argv)
    root, code = args.dnerf.resolve(), args.code.resolve()
    for s in SCENES:
        if not (root / s / "transforms_train.json").is_file():
            raise SystemExit(f"[headline] {root / s}: not a D-NeRF scene (no transforms_train.json)")
    if not (code / "scripts" / "run.sh").is_file():
        raise SystemExit(f"[headline] --code {code}: no scripts/run.sh there")
    failed, left = [], []
    for seed in args.seeds:
        if args.dry_run:
            for r in plan_seed(root, seed, args.records).runs:
                print(r.id, " ".join(r.overrides))
            continue
        for _ in range(SWEEPS):
            q = plan_seed(root, seed, args.records)
            q.runs = [r for r in q.runs if r.id not in failed]
            if not q.runs:
                break
            execute(q, args.work, 1, None, command=command(code))
            shared, bad = book(q, args.work, args.records, checkout_commit(code))
            failed += bad
            if not shared:
                break
        left += [r.id for r in plan_seed(root, seed, args.records).runs if r.id not in failed]
    if args.dry_run:
        return 0
    if not args.no_results:
        subprocess.run([str(ROOT / "scripts" / "run.sh"), "python", "-m", "studies.results"], cwd=ROOT, check=True)
    print(f"[headline] done; {len(failed)} failed, {len(left)} not recorded (shared the machine in all {SWEEPS} sweeps)")
    return 1 if failed or left else 0


if __name__ == "__main__":
    raise SystemExit(main())
