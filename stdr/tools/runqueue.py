"""A resumable queue of training runs, several at once, in time-boxed calls (a GPU rented by the hour,
a Slurm job with a wall-clock limit): the library behind `stdr-tool queue` (stdr.tools.queue_tool,
its command line) and every study's runs.

A call is one Hydra multirun of `stdr-train` (`hydra/sweeper=stdr_queue` reads the pending runs
from the queue file; `hydra/launcher=joblib` runs N at once on this machine; `-- hydra/launcher=slurm ...`
sends them to a Slurm cluster instead). Each run is a job in WORK/<id>, trained in its own process
(a crash ends that run alone; its output is WORK/<id>/stdout.log). What the launchers do not do is
this thin layer: the call's deadline (every job gets `train.deadline`, where it checkpoints and
stops, and `train.start_by`, its estimate before the deadline, after which it is not started) and
the grid's state across calls (the queue file: a stopped run stays pending and resumes from its
checkpoint when the next call finds its folder, a machine kept warm, or starts again otherwise).
A run is `done` when its metrics.json exists; its metrics.json, config.yaml and train_profile.json
then go into the archive under `<id>/` (with its output's tail), the three files the result tables
read. With N runs at once the CPU threads are split between them (`train.threads` = cores // N,
at least 1).
"""
from __future__ import annotations

import contextlib
import fcntl
import io
import json
import os
import shlex
import signal
import subprocess
import sys
import tarfile
import threading
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

from ..errors import BadInput, MissingInput

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
        """The queue file at `path`; a missing, unreadable or malformed one is one error naming it."""
        path = Path(path)
        if not path.is_file():
            raise MissingInput(f"{path}: no queue file there (stdr-tool queue plan {path} ... makes one)")
        fix = "plan a new queue (stdr-tool queue plan), or restore the file from the run's copy (OUT/queue.json)"
        try:
            d = json.loads(path.read_text())
        except (UnicodeDecodeError, json.JSONDecodeError) as e:
            raise BadInput(f"{path}: not a queue file ({e}); {fix}") from None
        if not isinstance(d, dict) or not isinstance(d.get("runs"), list):
            raise BadInput(f"{path}: not a queue file (a JSON object with a 'runs' list); {fix}")
        try:
            return Queue([Run(**r) for r in d["runs"]], list(d.get("calls", [])))
        except TypeError as e:
            raise BadInput(f"{path}: a run entry is not one stdr-tool queue wrote ({e}); {fix}") from None

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


#: the Hydra app a queue's runs are jobs of
APP = [sys.executable, "-m", "stdr.cli.train"]
#: a sweep folder's record of its failed jobs, one line each (stdr.cli.train writes it; so does the
#: stdr_queue sweeper, for a job that does not compose)
FAILURES = "failures.jsonl"
#: a run folder's output when its sweep job trains in a process of its own (stdr.cli.train)
STDOUT = "stdout.log"


def sweep_command(queue_file: Path, work: Path, concurrent: int, threads: int, deadline: float | None,
                  launcher=(), command=None) -> list[str]:
    """The call as one Hydra multirun: the queue's pending runs (hydra/sweeper=stdr_queue), each in
    WORK/<id>, on joblib's local launcher with `concurrent` jobs (`launcher`: overrides after it,
    e.g. hydra/launcher=slurm hydra.launcher.partition=gpu). `command`: what each job runs instead
    of `python -m stdr.cli.train` ({run_dir}: its folder)."""
    extra = [] if deadline is None else [f"hydra.sweeper.deadline={deadline:.3f}"]
    if command:
        extra.append("hydra.sweeper.command=[" + ",".join(_quoted(a) for a in command) + "]")
    return [*APP, "-m", "hydra/sweeper=stdr_queue", f"hydra.sweeper.queue={queue_file}", *extra,
            f"hydra.sweep.dir={work}", "hydra/launcher=joblib", f"hydra.launcher.n_jobs={concurrent}",
            f"train.threads={threads}", "train.progress=false", *launcher]


def _quoted(text: str) -> str:
    """One element of a Hydra override list, as a quoted string (paths, {run_dir}, '--')."""
    return "'" + str(text).replace("\\", "\\\\").replace("'", "\\'") + "'"


@contextlib.contextmanager
def work_lock(work: Path):
    """One call at a time on a work folder: a second would train the same runs into the same
    folders. Raises QueueBusy when another call holds WORK/.queue.lock."""
    with open(work / ".queue.lock", "a") as fh:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise QueueBusy(f"another queue call is running on {work} (it holds {work / '.queue.lock'})") from None
        yield


class QueueBusy(RuntimeError):
    pass


def _failures_since(work: Path, offset: int) -> dict[str, dict]:
    """{run id (its folder under WORK): its failure record} of the lines written to
    WORK/failures.jsonl after `offset` bytes."""
    path = work / FAILURES
    if not path.is_file():
        return {}
    with open(path, "rb") as f:
        f.seek(offset)
        recs = [json.loads(line) for line in f.read().decode().splitlines() if line.strip()]
    return {Path(r["run_dir"]).resolve().relative_to(work).as_posix(): r for r in recs}


def _stop(proc: subprocess.Popen) -> None:
    """End the sweep and everything it started (its own process group): SIGTERM, then SIGKILL."""
    with contextlib.suppress(ProcessLookupError):
        os.killpg(proc.pid, signal.SIGTERM)
    try:
        proc.wait(timeout=10)
    except subprocess.TimeoutExpired:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()


def execute(q: Queue, work: Path, concurrent: int, budget_s: float | None, cores: int | None = None,
            launcher=(), command=None, grace_s: float = 30.0, log=print, est_s: float | None = None) -> dict:
    """Run the pending runs as one sweep on Hydra's launcher, at most `concurrent` at a time. Every
    job gets the call's deadline: a run stops there with a checkpoint and stays pending (it resumes
    where its folder is kept), and a run whose estimate does not fit before it is not started. The
    sweep is killed `grace_s` after the deadline. budget_s None: no deadline. Books each run (done:
    metrics.json; failed: a line in WORK/failures.jsonl; else pending) and returns this call's
    record (also in q.calls). One call at a time per WORK (QueueBusy). est_s: every run's estimate
    for this call's start-by check instead of its own (a calibrated one, stdr.tools.concurrency)."""
    if concurrent < 1:
        raise ValueError(f"--concurrent must be at least 1, got {concurrent}")
    work = Path(work).resolve()
    work.mkdir(parents=True, exist_ok=True)
    main = threading.current_thread() is threading.main_thread()
    prev = signal.signal(signal.SIGTERM, _exit_on_term) if main else None  # SIGTERM stops the sweep too
    try:
        with work_lock(work):
            return _execute(q, work, concurrent, budget_s, cores, launcher, command, grace_s, log, est_s)
    finally:
        if main:
            signal.signal(signal.SIGTERM, prev)


def _exit_on_term(signum, frame):
    raise SystemExit(128 + signum)


def _execute(q: Queue, work: Path, concurrent: int, budget_s: float | None, cores, launcher, command, grace_s,
             log, est_s) -> dict:
    t0 = time.time()
    deadline = None if budget_s is None else t0 + budget_s
    threads = max(1, (cores or os.cpu_count() or 1) // concurrent)
    for r in q.runs:  # a run a killed call left as running is pending again
        if r.state == "running":
            r.state = "pending"
    batch = [r for r in q.runs if r.state == "pending"]
    fails = work / FAILURES
    offset = fails.stat().st_size if fails.is_file() else 0
    rc = 0
    if batch:
        call = q if est_s is None else Queue([replace(r, est_s=est_s) for r in q.runs])
        call.save(work / "queue_call.json")  # what the sweeper reads
        cmd = sweep_command(work / "queue_call.json", work, concurrent, threads, deadline, launcher, command)
        with open(work / "queue.log", "a") as logf:
            logf.write(f"$ {shlex.join(cmd)}\n")
            logf.flush()
            proc = subprocess.Popen(cmd, stdout=logf, stderr=subprocess.STDOUT, start_new_session=True,
                                    env={**os.environ, "OMP_NUM_THREADS": str(threads)})
            log(f"[queue] {len(batch)} runs, {concurrent} at a time, {threads} threads each; log {work / 'queue.log'}")
            try:
                rc = proc.wait(timeout=None if deadline is None else max(1.0, deadline + grace_s - time.time()))
            except subprocess.TimeoutExpired:
                _stop(proc)
                rc = "killed"
                log(f"[queue] the sweep ran {grace_s:.0f} s past the deadline: stopped")
            except BaseException:  # interrupted (Ctrl-C, SIGTERM): the sweep's runs stop too, not run on orphaned
                _stop(proc)
                raise
    failed_now = _failures_since(work, offset)
    started, finished, failed = [], [], []
    now = time.time()
    for r in batch:
        d = work / r.id
        began = (d / "config.yaml").is_file() and (d / "config.yaml").stat().st_mtime >= t0 - 1
        if began:
            ends = [p.stat().st_mtime for p in (d / "metrics.json", d / "checkpoints" / "last.pt") if p.is_file()]
            r.tries += 1
            r.seconds += max([e for e in ends if e >= t0] or [now]) - (d / "config.yaml").stat().st_mtime
            started.append(r.id)
        if (d / "metrics.json").is_file():
            r.state = "done"
            finished.append(r.id)
        elif r.id in failed_now:
            f = failed_now[r.id]
            r.state, r.error = "failed", f"{f['error']}; log {f.get('log') or work / 'queue.log'}"
            failed.append(r.id)
        else:
            r.state = "pending"  # stopped at the deadline or not started: resumes in a later call
        if r.id in finished or r.id in failed:
            log(f"[queue] {r.id}: {r.state} ({r.seconds:.0f} s)")
    rec = {"started": started, "finished": finished, "failed": failed, "wall_s": round(time.time() - t0, 1),
           "concurrent": concurrent, "threads_each": threads, "budget_s": budget_s, "sweep_exit": rc,
           "time": time.strftime("%Y-%m-%d %H:%M:%S %Z")}
    q.calls.append(rec)
    return rec


def run_one(overrides: list[str], run_dir: Path, threads: int = 1, log=print) -> Run:
    """One run in `run_dir` through the queue (a sweep of one job, no deadline), for a study's
    steps that must follow each other (a trunk, then its branches). A run stopped by
    `train.stop_at` comes back pending; one that failed raises RuntimeError with its error."""
    run_dir = Path(run_dir).resolve()
    q = Queue([Run(run_dir.name, list(overrides), 0.0)])
    execute(q, run_dir.parent, 1, None, cores=threads, log=log)
    if q.runs[0].state == "failed":
        raise RuntimeError(f"{run_dir}: {q.runs[0].error}")
    return q.runs[0]


def _tail(src: Path, lines: int) -> bytes:
    return "\n".join(src.read_text(errors="replace").splitlines()[-lines:]).encode()


def pack(q: Queue, work: Path, out: Path) -> Path:
    """OUT/runs.tgz: <id>/{metrics.json, config.yaml, train_profile.json, log_tail.txt (the end of
    its output)} of every done or failed run whose folder is here (the runs of earlier calls are in
    their own archives); nothing else, so that a reader may refuse any other member. The end of the
    sweep's log goes beside it, OUT/queue_log_tail.txt."""
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
            if (d / STDOUT).is_file():
                tail = _tail(d / STDOUT, 40)
                info = tarfile.TarInfo(f"{r.id}/log_tail.txt")
                info.size = len(tail)
                tar.addfile(info, io.BytesIO(tail))
    tmp.replace(out / "runs.tgz")
    if (work / "queue.log").is_file():
        (out / "queue_log_tail.txt").write_bytes(_tail(work / "queue.log", 200))
    return out / "runs.tgz"
