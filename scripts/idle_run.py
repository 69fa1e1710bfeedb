"""Run a command and record whether it had the machine to itself.

    python scripts/idle_run.py --out load.json -- CMD [ARGS...]

Writes {wall_s, child_cpu_s, machine_busy_cpu_s, foreign_cpu_s, foreign_share, cpus, idle} to
--out and exits with CMD's status. machine_busy_cpu_s is the CPU time every process on the
machine used meanwhile (/proc/stat: user, nice, system, irq, softirq, steal), child_cpu_s the
command's own (its process tree, getrusage); foreign = busy - child is what other jobs took, and
foreign_share = foreign / (wall x cpus) the share of the machine they had. Timings of a run with
foreign_share above --max-foreign (default 0.05) are not comparable: `idle` says so, and the
timed studies (studies/headline.py) redo such runs. Needs Linux /proc/stat.

One timed command at a time per machine: before it starts, the command waits for an exclusive
lock (--lock, default $STDR_IDLE_LOCK or <tmp>/stdr-idle-run.lock; `--lock none` for no lock),
so two timed queues on one machine take turns
instead of timing each other. The wait is not part of the measurement (`lock_wait_s`).
"""
from __future__ import annotations

import argparse
import contextlib
import fcntl
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def machine_busy_seconds() -> float:
    """CPU seconds all processes have used since boot (user + nice + system + irq + softirq + steal)."""
    fields = Path("/proc/stat").read_text().splitlines()[0].split()
    user, nice, system, _idle, _iowait, irq, softirq, steal = (int(x) for x in fields[1:9])
    return (user + nice + system + irq + softirq + steal) / os.sysconf("SC_CLK_TCK")


def children_cpu_seconds() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def default_lock() -> str:
    return os.environ.get("STDR_IDLE_LOCK") or str(Path(tempfile.gettempdir()) / "stdr-idle-run.lock")


@contextlib.contextmanager
def machine_lock(path: str):
    """Hold an exclusive flock on `path` (created if needed; "none": no lock); yields the seconds
    waited for it."""
    if path == "none":
        yield 0.0
        return
    with open(path, "a") as fh:
        t0 = time.perf_counter()
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield time.perf_counter() - t0
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--max-foreign", type=float, default=0.05)
    ap.add_argument("--lock", default=None, help="the machine's lock file (default: $STDR_IDLE_LOCK or "
                    "<tmp>/stdr-idle-run.lock); none: do not wait for other timed commands")
    ap.add_argument("cmd", nargs=argparse.REMAINDER)
    a = ap.parse_args(argv)
    cmd = a.cmd[1:] if a.cmd[:1] == ["--"] else a.cmd
    if not cmd:
        ap.error("no command (put it after --)")
    with machine_lock(a.lock or default_lock()) as waited:
        b0, c0, t0 = machine_busy_seconds(), children_cpu_seconds(), time.perf_counter()
        rc = subprocess.run(cmd).returncode
        wall = time.perf_counter() - t0
        busy, child = machine_busy_seconds() - b0, children_cpu_seconds() - c0
    cpus = os.cpu_count() or 1
    foreign = max(busy - child, 0.0)
    share = foreign / (wall * cpus) if wall > 0 else 0.0
    rec = {"wall_s": wall, "child_cpu_s": child, "machine_busy_cpu_s": busy, "foreign_cpu_s": foreign,
           "foreign_share": share, "cpus": cpus, "max_foreign": a.max_foreign, "idle": share <= a.max_foreign,
           "returncode": rc, "lock_wait_s": waited}
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(rec, indent=1))
    return rc


if __name__ == "__main__":
    sys.exit(main())
