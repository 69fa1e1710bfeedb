"""One writer per run folder: `run_lock(run_dir, prog)`.

Every command that writes into a run folder (stdr-train, stdr-eval's re-evaluation, stdr-tool
pack and compact) holds an exclusive lock (flock(2)) on `RUN/.stdr.lock` while it writes. A
second writer is refused with a `RunLocked` error that names the holder (program, host, pid,
since when, Slurm job). Readers (the viewer, a table written elsewhere) take no lock.

Why a kernel lock and not a lock file made with O_EXCL: the kernel, or the file server, releases
it when its process ends, however it ends (SIGKILL, an out-of-memory kill, a preempted Slurm
job), so a killed run never leaves a lock that blocks its own resume; the holder's record in the
file only serves the message. On Linux, flock on NFS is sent to the server as a whole-file lock
(the NLM protocol for v3, the protocol itself for v4), so it holds between the nodes of a
cluster; a client that dies loses its locks when its lease expires. Lustre carries it when
mounted with `-o flock`, GPFS and BeeGFS do. A file system mounted without lock support answers
ENOLCK: the error says so, and `STDR_RUN_LOCK=off` runs without the lock (then nothing keeps two
writers apart). flock and not fcntl's record locks: a record lock is dropped when the process
closes any descriptor of the file, e.g. when it reads the holder's record.

The file is never removed (a removed file could be locked by one process while another creates a
new one): an empty file means nobody holds it. Re-entrant within a process: stdr-train's packing
step takes the lock its own training holds.
"""
from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import os
import socket
import time
from pathlib import Path
from typing import Iterator

from ..errors import UserError
from .files import failpoint

LOCK_NAME = ".stdr.lock"
ENV_SWITCH = "STDR_RUN_LOCK"  # "off": no lock (a file system without lock support)


class RunLocked(UserError, RuntimeError):
    """Another process writes into the run folder."""


_HELD: dict[str, list] = {}  # realpath of the lock file -> [file object, depth] (re-entrancy)


def holder_record(prog: str) -> dict:
    rec = {"prog": prog, "host": socket.gethostname(), "pid": os.getpid(),
           "since": time.strftime("%Y-%m-%d %H:%M:%S %z")}
    job = os.environ.get("SLURM_JOB_ID")
    if job:
        rec["slurm_job"] = job
    return rec


def describe(rec: dict) -> str:
    """'stdr-train, pid 123 on host gpu01 since 2026-12-01 10:00:00 +0000 (Slurm job 42)'."""
    if not rec:
        return "an unknown process"
    job = f" (Slurm job {rec['slurm_job']})" if rec.get("slurm_job") else ""
    return f"{rec.get('prog', '?')}, pid {rec.get('pid', '?')} on host {rec.get('host', '?')} since {rec.get('since', '?')}{job}"


def read_holder(run_dir: str | Path) -> dict:
    """The record in RUN/.stdr.lock ({} when empty, absent or unreadable): the holder, or the last
    holder if it was killed."""
    try:
        return _parse((Path(run_dir) / LOCK_NAME).read_text())
    except OSError:
        return {}


def _parse(text: str) -> dict:
    try:
        rec = json.loads(text) if text.strip() else {}
    except ValueError:
        return {}
    return rec if isinstance(rec, dict) else {}


@contextlib.contextmanager
def run_lock(run_dir: str | Path, prog: str) -> Iterator[None]:
    """Hold RUN/.stdr.lock exclusively for the body (the folder is created if needed). Raises
    RunLocked when another process holds it. A record left by a process that was killed is
    reported in one line and taken over."""
    run_dir = Path(run_dir)
    if os.environ.get(ENV_SWITCH, "").lower() == "off":
        yield
        return
    run_dir.mkdir(parents=True, exist_ok=True)
    path = run_dir / LOCK_NAME
    key = os.path.realpath(path)
    if key in _HELD:
        _HELD[key][1] += 1
        try:
            yield
        finally:
            _HELD[key][1] -= 1
        return
    fh = open(path, "a+")
    try:
        fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as e:
        fh.close()
        if e.errno in (errno.EACCES, errno.EAGAIN, errno.EWOULDBLOCK):
            raise RunLocked(f"{run_dir} is in use: {describe(read_holder(run_dir))} writes into it (lock "
                            f"{path}). One writer per run folder: wait until it ends, or give this command "
                            "another run folder (hydra.run.dir=...)") from None
        if e.errno in (errno.ENOLCK, errno.EOPNOTSUPP, errno.EINVAL):
            raise RunLocked(f"{path}: the file system does not support file locks ({os.strerror(e.errno)}); mount "
                            f"it with lock support (Lustre: -o flock), or set {ENV_SWITCH}=off to run without "
                            "the lock (then nothing keeps two writers of one run folder apart)") from None
        raise
    try:
        fh.seek(0)
        left = _parse(fh.read())
        if left:
            print(f"[stdr] {run_dir}: the lock was left by {describe(left)}, which is gone (killed or "
                  "preempted); taking it over", flush=True)
        fh.seek(0)
        fh.truncate()
        fh.write(json.dumps(holder_record(prog)))
        fh.flush()
        failpoint("lock", path)
    except BaseException:
        try:  # the record is not left behind as if a holder had been killed
            fh.seek(0)
            fh.truncate()
        except OSError:
            pass
        fh.close()  # closing its only descriptor releases the lock
        raise
    _HELD[key] = [fh, 1]
    try:
        yield
    finally:
        del _HELD[key]
        try:
            fh.seek(0)
            fh.truncate()  # nobody holds it now
            fh.flush()
        except OSError:
            pass  # a full or read-only disk: the record stays, and the next taker says it was left
        fh.close()
