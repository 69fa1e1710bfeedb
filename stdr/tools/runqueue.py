"""A resumable queue of training runs, several at once, in time-boxed calls (a GPU rented by the hour,
a Slurm job with a wall-clock limit).

    # plan a grid: every experiment x scene x seed, with overrides for all (a queue file)
    stdr-tool queue plan QUEUE.json --experiments dnerf_deform dnerf_deform_stdr --scenes DIR/jumpingjacks ... \
        --seeds 0 --est-seconds 90 -- budget=gpu device=cuda
    # one call: at most N runs at a time, none started that its estimate says would not end before
    # --budget seconds; every finished run's small files packed into OUT/runs.tgz, the queue's state
    # into OUT/queue.json (carry it back as QUEUE.json for the next call)
    stdr-tool queue run QUEUE.json --work WORK --out OUT --concurrent 8 --budget 540
    stdr-tool queue status QUEUE.json

A run is one `stdr-train` command (`python -m stdr.cli.train ... hydra.run.dir=WORK/<id>`), so a
run that a call's deadline stops resumes from its last checkpoint when the next call finds its
folder (a machine kept warm), and starts again where the folder is gone. A run is `done` when its
metrics.json exists; its metrics.json, config.yaml and train_profile.json then go into the archive
under `<id>/` (with its log's tail), the three files the result tables read. With N runs on one
GPU the CPU threads are split between them (`train.threads` = cores // N, at least 1).
"""
from __future__ import annotations

import argparse
import io
import json
import os
import shlex
import signal
import subprocess
import sys
import tarfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

FILES = ("metrics.json", "config.yaml", "train_profile.json")
STATES = ("pending", "running", "done", "failed")


@dataclass
class Run:
    id: str
    overrides: list[str]
    est_s: float
    state: str = "pending"
    tries: int = 0
    seconds: float = 0.0       # wall seconds over all tries
    error: str = ""


@dataclass
class Queue:
    runs: list[Run] = field(default_factory=list)
    calls: list[dict] = field(default_factory=list)  # one record per `run` call

    @staticmethod
    def load(path: Path) -> "Queue":
        d = json.loads(Path(path).read_text())
        return Queue([Run(**r) for r in d["runs"]], list(d.get("calls", [])))

    def save(self, path: Path) -> None:
        tmp = Path(path).with_suffix(".tmp")
        tmp.write_text(json.dumps({"runs": [asdict(r) for r in self.runs], "calls": self.calls}, indent=1) + "\n")
        tmp.replace(path)

    def counts(self) -> dict[str, int]:
        return {s: sum(r.state == s for r in self.runs) for s in STATES}


def run_id(experiment: str, scene: str | None, seed: int) -> str:
    return f"{experiment}__{Path(scene).name if scene else 'default'}__s{seed}"


def parse_variant(text: str) -> tuple[str, list[str]]:
    """'LABEL:KEY=V,KEY=V' -> (LABEL, [KEY=V, KEY=V]); 'LABEL:' is a variant with no overrides."""
    label, sep, rest = text.partition(":")
    if not sep or not label or not label.replace("_", "").replace("-", "").isalnum():
        raise ValueError(f"--variants {text!r}: write LABEL:KEY=VALUE[,KEY=VALUE...] (LABEL letters, digits, - or _)")
    return label, [o for o in rest.split(",") if o]


def plan(experiments, scenes, seeds, overrides, est_s: float, variants=(), order: str = "scene") -> Queue:
    """Every seed x scene x experiment (x variant), in that order: the methods of one scene and seed
    run next to each other, so a call that ends early leaves complete pairs, not one method's
    column. order="experiment": seed x experiment x scene instead, so the experiments named first
    (e.g. the table's main rows) are done on every scene before the next ones start. No scenes: the
    experiments' own data (e.g. the embedded scene). A relative scene path is kept as given: it is
    read from the folder `queue run` runs in (a queue planned here runs on another machine).
    variants: (label, overrides) pairs, each a run of its own with its label in the id (e.g. the
    torch forms and the speed keys side by side)."""
    if order not in ("scene", "experiment"):
        raise ValueError(f"--order {order!r}: scene or experiment")
    runs = []
    for seed in seeds:
        pairs = [(sc, e) for sc in scenes or [None] for e in experiments]
        if order == "experiment":
            pairs = [(sc, e) for e in experiments for sc in scenes or [None]]
        for scene, exp in pairs:
            data = [f"data.path={scene}", f"data.name={Path(scene).name}"] if scene else []
            for label, extra in variants or [("", [])]:
                rid = run_id(exp, scene, seed) + (f"__{label}" if label else "")
                runs.append(Run(rid, [f"experiment={exp}", *data, f"seed={seed}", *overrides, *extra], est_s))
    ids = [r.id for r in runs]
    if len(set(ids)) != len(ids):
        raise ValueError("two runs of the plan share an id (the same experiment, scene name and seed)")
    return Queue(runs)


def _command(r: Run, work: Path, threads: int) -> list[str]:
    return [sys.executable, "-m", "stdr.cli.train", *r.overrides, f"hydra.run.dir={work / r.id}",
            f"train.threads={threads}", "train.progress=false"]


def execute(q: Queue, work: Path, concurrent: int, budget_s: float, cores: int | None = None,
            poll_s: float = 0.5, log=print) -> dict:
    """Run pending runs, at most `concurrent` at a time, starting one only when its estimate fits
    before the deadline; at the deadline the running ones are stopped (SIGTERM, then SIGKILL) and
    stay pending. Returns this call's record (also appended to q.calls)."""
    if concurrent < 1:
        raise ValueError(f"--concurrent must be at least 1, got {concurrent}")
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    deadline = t0 + budget_s
    threads = max(1, (cores or os.cpu_count() or 1) // concurrent)
    active: dict[str, tuple[subprocess.Popen, float, Run]] = {}
    started, finished, failed = [], [], []
    for r in q.runs:  # a run a killed call left as running is pending again
        if r.state == "running":
            r.state = "pending"
    while True:
        for rid, (proc, t_start, r) in list(active.items()):
            rc = proc.poll()
            if rc is None:
                continue
            del active[rid]
            r.seconds += time.monotonic() - t_start
            if rc == 0 and (work / rid / "metrics.json").is_file():
                r.state = "done"
                finished.append(rid)
            else:
                r.state, r.error = "failed", f"exit {rc}; see {work / (rid + '.log')}"
                failed.append(rid)
            log(f"[queue] {rid}: {r.state} ({r.seconds:.0f} s)")
        now = time.monotonic()
        pending = [r for r in q.runs if r.state == "pending"]
        while pending and len(active) < concurrent and now + pending[0].est_s <= deadline:
            r = pending.pop(0)
            r.state, r.tries = "running", r.tries + 1
            cmd = _command(r, work, threads)
            logf = open(work / f"{r.id}.log", "a")
            logf.write("$ " + shlex.join(cmd) + "\n")
            logf.flush()
            proc = subprocess.Popen(cmd, stdout=logf, stderr=subprocess.STDOUT, start_new_session=True,
                                    env={**os.environ, "OMP_NUM_THREADS": str(threads)})
            active[r.id] = (proc, time.monotonic(), r)
            started.append(r.id)
            log(f"[queue] {r.id}: started ({len(active)} running, {threads} threads each)")
        if not active:
            break
        if time.monotonic() >= deadline:
            for rid, (proc, t_start, r) in active.items():
                os.killpg(proc.pid, signal.SIGTERM)
            for rid, (proc, t_start, r) in active.items():
                try:
                    proc.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    os.killpg(proc.pid, signal.SIGKILL)
                    proc.wait()
                r.seconds += time.monotonic() - t_start
                r.state = "pending"  # resumes from its checkpoint where its folder is kept
                log(f"[queue] {rid}: stopped at the deadline; pending again")
            active.clear()
            break
        time.sleep(poll_s)
    rec = {"started": started, "finished": finished, "failed": failed, "wall_s": round(time.monotonic() - t0, 1),
           "concurrent": concurrent, "threads_each": threads, "budget_s": budget_s,
           "time": time.strftime("%Y-%m-%d %H:%M:%S %Z")}
    q.calls.append(rec)
    return rec


def pack(q: Queue, work: Path, out: Path) -> Path:
    """OUT/runs.tgz: <id>/{metrics.json, config.yaml, train_profile.json, log_tail.txt} of every done
    run whose folder is here (the runs of earlier calls are in their own archives)."""
    out.mkdir(parents=True, exist_ok=True)
    tmp = out / "runs.tgz.tmp"
    with tarfile.open(tmp, "w:gz") as tar:
        for r in q.runs:
            d = work / r.id
            if r.state not in ("done", "failed") or not d.is_dir():
                continue
            for name in FILES:
                if (d / name).is_file():
                    tar.add(d / name, arcname=f"{r.id}/{name}")
            logp = work / f"{r.id}.log"
            if logp.is_file():
                tail = "\n".join(logp.read_text(errors="replace").splitlines()[-40:]).encode()
                info = tarfile.TarInfo(f"{r.id}/log_tail.txt")
                info.size = len(tail)
                tar.addfile(info, io.BytesIO(tail))
    tmp.replace(out / "runs.tgz")
    return out / "runs.tgz"


def main(argv=None) -> None:
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
    r.add_argument("--concurrent", type=int, default=1)
    r.add_argument("--budget", type=float, default=540.0, help="seconds for this call")
    r.add_argument("--cores", type=int, default=None, help="CPU cores to split between the runs (default: all)")
    s = sub.add_parser("status", help="the queue's counts and runs")
    s.add_argument("queue", type=Path)
    argv = list(sys.argv[1:] if argv is None else argv)
    overrides = argv[argv.index("--") + 1:] if "--" in argv else []
    args = ap.parse_args(argv[:argv.index("--")] if "--" in argv else argv)
    args.overrides = overrides
    if args.cmd == "plan":
        if args.queue.exists():
            raise SystemExit(f"stdr-tool queue: {args.queue} exists; a plan never overwrites a queue's state")
        q = plan(args.experiments, args.scenes, args.seeds, args.overrides, args.est_seconds,
                 [parse_variant(v) for v in args.variants], args.order)
        q.save(args.queue)
        print(f"[queue] {args.queue}: {len(q.runs)} runs planned")
    elif args.cmd == "run":
        q = Queue.load(args.queue)
        rec = execute(q, args.work, args.concurrent, args.budget, args.cores)
        q.save(args.queue)
        args.out.mkdir(parents=True, exist_ok=True)
        q.save(args.out / "queue.json")
        pack(q, args.work, args.out)
        print(f"[queue] call done in {rec['wall_s']} s: {len(rec['finished'])} finished, {len(rec['failed'])} failed; "
              f"{q.counts()}; results in {args.out / 'runs.tgz'}, state in {args.out / 'queue.json'}")
    else:
        q = Queue.load(args.queue)
        print(json.dumps(q.counts()))
        for r in q.runs:
            print(f"{r.state:8s} {r.id}  tries {r.tries}  {r.seconds:.0f} s  {r.error}")


if __name__ == "__main__":
    main()
