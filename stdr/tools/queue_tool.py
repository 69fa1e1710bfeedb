"""A resumable queue of runs, several at once, in time-boxed calls: plan a grid, run it call by call, show its state.

    # plan a grid: every experiment x scene x seed, with overrides for all (a queue file)
    stdr-tool queue plan QUEUE.json --experiments dnerf_deform dnerf_deform_stdr --scenes DIR/jumpingjacks ... \\
        --seeds 0 --est-seconds 90 -- budget=gpu device=cuda
    # one call: at most N runs at a time (default: one per core, one thread each), none started that its estimate says would not end before
    # --budget seconds; every finished run's small files packed into OUT/runs.tgz, the queue's state
    # into OUT/queue.json (carry it back as QUEUE.json for the next call)
    stdr-tool queue run QUEUE.json --work WORK --out OUT --concurrent 8 --budget 540
    # the same, with N chosen in the call: a slice of the next run at 1, 4, 8 and 16 at once first,
    # then the chunk at the level that finishes the most runs in what is left (stdr.tools.concurrency)
    stdr-tool queue run QUEUE.json --work WORK --out OUT --calibrate 1 4 8 16 --slice 75 --budget 540
    stdr-tool queue status QUEUE.json

The queue itself (plan, execute, pack) is stdr.tools.runqueue.
"""
from __future__ import annotations

import argparse
import difflib
import json
import os
import shlex
import sys
import time
from pathlib import Path

from ..errors import ConfigError
from ..store import experiment_names
from .concurrency import calibrate
from .runqueue import Queue, QueueBusy, execute, pack, parse_variant, plan


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="stdr-tool queue", description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("plan", help="a queue file of experiment x scene x seed runs")
    p.add_argument("queue", type=Path)
    p.add_argument("--experiments", nargs="+", required=True)
    p.add_argument("--scenes", nargs="*", default=[], help="scene folders (none: the experiments' own data)")
    p.add_argument("--seeds", type=int, nargs="+", default=[0])
    p.add_argument("--est-seconds", type=float, required=True, help="a run's expected wall seconds (concurrent)")
    p.add_argument("--variants", nargs="*", default=[], help="LABEL:KEY=V,KEY=V ... each a run of its own")
    p.add_argument("--order", choices=("scene", "experiment"), default="scene",
                   help="scene: the methods of one scene next to each other; experiment: each experiment on every "
                   "scene before the next")
    p.epilog = "After --: the overrides every run gets (e.g. -- budget=gpu device=cuda)."
    r = sub.add_parser("run", help="run pending runs until the budget; pack the results")
    r.add_argument("queue", type=Path)
    r.add_argument("--work", type=Path, required=True)
    r.add_argument("--out", type=Path, required=True)
    r.add_argument("--concurrent", type=int, default=None,
                   help="runs at once (default: one per core, one thread each: the results are the same bits on any "
                   "thread count; --concurrent 1 where the runs' timings are the record; not with --calibrate)")
    r.add_argument("--calibrate", type=int, nargs="+", default=None, metavar="N",
                   help="levels to measure before the chunk (1 among them), e.g. 1 4 8 16: the chunk runs at the one "
                   "that finishes the most runs in the budget left")
    r.add_argument("--slice", type=float, default=75.0, help="seconds of each calibration level (default 75)")
    r.add_argument("--alone-seconds", type=float, default=None,
                   help="a run's wall seconds alone on this machine, for --calibrate's estimates (default: its "
                   "estimate in the queue file)")
    r.add_argument("--budget", type=float, default=540.0, help="seconds for this call")
    r.add_argument("--cores", type=int, default=None, help="CPU cores to split between the runs (default: all)")
    r.add_argument("--command", default=None, help="what each run executes instead of `python -m stdr.cli.train`, "
                   "e.g. 'python scripts/idle_run.py --out {run_dir}/load.json -- CHECKOUT/scripts/run.sh stdr-train'")
    r.epilog = "After --: Hydra overrides for the sweep (e.g. -- hydra/launcher=slurm hydra.launcher.partition=gpu)."
    s = sub.add_parser("status", help="the queue's counts, runs and calls (with their calibrations)")
    s.add_argument("queue", type=Path)
    return ap


def default_concurrency(cores: int | None) -> int:
    """Runs at once when the call names none: one per core (`--cores`, else the machine's), each on
    one thread. Training gives the same bits on any thread count (docs/performance.md,
    "Determinism"), so a study that records results and no timings loses nothing and finishes in
    about half the time on two cores; timing records run with --concurrent 1 and say so."""
    return max(1, cores or os.cpu_count() or 1)


def _run(args) -> None:
    if args.calibrate and args.concurrent is not None:
        raise SystemExit("stdr-tool queue run: give --concurrent N or --calibrate N ..., not both")
    q = Queue.load(args.queue)
    command = shlex.split(args.command) if args.command else None
    t0, cal, est = time.time(), None, None
    concurrent = args.concurrent or default_concurrency(args.cores)
    try:
        if args.calibrate:
            cal = calibrate(q, args.work, args.calibrate, args.slice, args.budget, args.alone_seconds, args.cores,
                            args.overrides, command)
            concurrent, est = cal["chosen"], cal["est_run_s"]
        if concurrent:
            rec = execute(q, args.work, concurrent, args.budget - (time.time() - t0), args.cores, launcher=args.overrides,
                          command=command, est_s=est)
        else:  # calibrated, and no level finishes a run in the time left
            rec = {"started": [], "finished": [], "failed": [], "wall_s": 0.0, "concurrent": 0, "sweep_exit": 0,
                   "budget_s": args.budget, "time": time.strftime("%Y-%m-%d %H:%M:%S %Z")}
            q.calls.append(rec)
    except (QueueBusy, ValueError) as e:
        raise SystemExit(f"stdr-tool queue: {e}") from None
    if cal is not None:  # the call's entry: the calibration, the chunk's own seconds and the call's in all
        rec["calibration"], rec["chunk_wall_s"], rec["wall_s"] = cal, rec["wall_s"], round(time.time() - t0, 1)
    q.save(args.queue)
    args.out.mkdir(parents=True, exist_ok=True)
    q.save(args.out / "queue.json")
    pack(q, args.work, args.out)
    if rec["sweep_exit"] != 0:
        tail = (args.work / "queue.log").read_text(errors="replace").splitlines()[-15:]
        print("\n".join(["[queue] the sweep itself failed (exit {}); the end of {}:".format(
            rec["sweep_exit"], args.work / "queue.log"), *tail]), file=sys.stderr)
    print(f"[queue] call done in {rec['wall_s']} s: {len(rec['finished'])} finished, {len(rec['failed'])} failed; "
          f"{q.counts()}; results in {args.out / 'runs.tgz'}, state in {args.out / 'queue.json'}")


def status_lines(q: Queue) -> list[str]:
    """The counts, each run, and each call: its runs, and its calibration's steps/s by level."""
    out, by_id = [json.dumps(q.counts())], {r.id: r for r in q.runs}
    out += [f"{r.state:8s} {r.id}  tries {r.tries}  {r.seconds:.0f} s  {r.error}" for r in q.runs]
    for i, c in enumerate(q.calls, 1):
        out.append(f"call {i} ({c.get('time', '?')}): {c.get('concurrent')} at once, {len(c.get('finished', []))} finished, "
                   f"{len(c.get('failed', []))} failed in {c.get('wall_s')} s")
        cal = c.get("calibration")
        for lv in (cal or {}).get("levels", []):
            rate = lv.get("steps_per_s")
            out.append(f"  calibration {lv['n']:>3} at once: " + (
                f"{rate:.1f} steps/s in all, {lv['per_run_steps_per_s']:.1f} each, slowdown {lv['slowdown']:.2f}, "
                f"about {lv['est_run_s']:.0f} s a run" if rate and lv.get("slowdown") else "no rate")
                + (f", {lv['failed']} copies failed" if lv.get("failed") else ""))
        if cal:
            out.append(f"  chosen: {cal['chosen']} ({cal['why']}; {cal['slice_s']:.0f} s slices of {cal['run']}, "
                       f"a run alone {cal['alone_s']:.0f} s)")
            secs = sorted(by_id[i].seconds for i in c.get("finished", []) if i in by_id and by_id[i].tries == 1)
            if secs and cal.get("est_run_s"):
                out.append(f"  chunk: {len(secs)} runs of one try took {secs[0]:.0f}-{secs[-1]:.0f} s each "
                           f"(estimate {cal['est_run_s']:.0f} s)")
    return out


def main(argv=None) -> None:
    argv = list(sys.argv[1:] if argv is None else argv)
    overrides = argv[argv.index("--") + 1:] if "--" in argv else []
    args = _parser().parse_args(argv[:argv.index("--")] if "--" in argv else argv)
    args.overrides = overrides
    if args.cmd == "plan":
        if args.queue.exists():
            raise SystemExit(f"stdr-tool queue: {args.queue} exists; a plan never overwrites a queue's state")
        known = set(experiment_names())
        unknown = [e for e in args.experiments if e not in known]
        if unknown:
            hints = [f"{e} (did you mean {m[0]}?)" if (m := difflib.get_close_matches(e, sorted(known), 1)) else e
                     for e in unknown]
            raise ConfigError(f"stdr-tool queue plan: no such experiment: {', '.join(hints)}; `stdr-train --help` "
                              "lists the experiment options")
        q = plan(args.experiments, args.scenes, args.seeds, args.overrides, args.est_seconds,
                 [parse_variant(v) for v in args.variants], args.order)
        q.save(args.queue)
        print(f"[queue] {args.queue}: {len(q.runs)} runs planned")
    elif args.cmd == "run":
        _run(args)
    else:
        print("\n".join(status_lines(Queue.load(args.queue))))


if __name__ == "__main__":
    main()
