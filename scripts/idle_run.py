"""Run a command and record whether it had the machine to itself.

    python scripts/idle_run.py --out load.json -- CMD [ARGS...]

Writes {wall_s, child_cpu_s, machine_busy_cpu_s, foreign_cpu_s, foreign_share, cpus, idle} to
--out and exits with CMD's status. machine_busy_cpu_s is the CPU time every process on the
machine used meanwhile (/proc/stat: user, nice, system, irq, softirq, steal), child_cpu_s the
command's own (its process tree, getrusage); foreign = busy - child is what other jobs took, and
foreign_share = foreign / (wall x cpus) the share of the machine they had. Timings of a run with
foreign_share above --max-foreign (default 0.05) are not comparable: `idle` says so, and the
timed studies (scripts/headline_table.sh) redo such runs. Needs Linux /proc/stat.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
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


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--max-foreign", type=float, default=0.05)
    ap.add_argument("cmd", nargs=argparse.REMAINDER)
    a = ap.parse_args(argv)
    cmd = a.cmd[1:] if a.cmd[:1] == ["--"] else a.cmd
    if not cmd:
        ap.error("no command (put it after --)")
    b0, c0, t0 = machine_busy_seconds(), children_cpu_seconds(), time.perf_counter()
    rc = subprocess.run(cmd).returncode
    wall = time.perf_counter() - t0
    busy, child = machine_busy_seconds() - b0, children_cpu_seconds() - c0
    cpus = os.cpu_count() or 1
    foreign = max(busy - child, 0.0)
    share = foreign / (wall * cpus) if wall > 0 else 0.0
    rec = {"wall_s": wall, "child_cpu_s": child, "machine_busy_cpu_s": busy, "foreign_cpu_s": foreign,
           "foreign_share": share, "cpus": cpus, "max_foreign": a.max_foreign, "idle": share <= a.max_foreign,
           "returncode": rc}
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(rec, indent=1))
    return rc


if __name__ == "__main__":
    sys.exit(main())
