"""A run folder's files, read and written safely: `read_yaml` and `read_json` (plain data, never
code; a damaged file is one error naming it), `write_atomic` and `atomic_path` (a reader never
sees half a file, and a failed write leaves the previous file and no temporary one),
`failpoint` (the tests' way to make one write site fail), and `run_lock` (one writer per run
folder).

**One writer per run folder.** Every command that writes into a run folder (stdr-train, stdr-eval's re-evaluation, stdr-tool
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

from pathlib import Path
from typing import Any, Iterator, Optional

import contextlib
import errno
import fcntl
import json
import os
import shutil
import socket
import time

import yaml
from omegaconf import OmegaConf

from ..errors import IO_FIXES, BadInput, IOFault, MissingInput, UserError, io_cause, io_fault


def read_yaml(path: str | Path) -> Any:
    """The file's content as plain Python data (OmegaConf's loader: the floats OmegaConf writes
    read back as floats). A tag that would build a Python object (`!!python/...`) is refused, as
    is a file that is not YAML: one error naming the file, never code run from it."""
    path = Path(path)
    if not path.is_file():
        raise MissingInput(f"{path} not found")
    try:
        node = OmegaConf.load(path)
    except yaml.YAMLError as e:
        first = " ".join(str(e).split())[:300]
        raise BadInput(f"{path} is not a config stdr can read ({type(e).__name__}: {first}); stdr reads plain "
                       "YAML and never builds objects from tags such as !!python/...: restore the file the run "
                       "wrote, or rerun the run") from None
    except UnicodeDecodeError as e:
        raise BadInput(f"{path} is not a text file ({e.reason}): restore the config.yaml the run wrote") from None
    return OmegaConf.to_container(node)


def read_json(path: str | Path, what: str = "file") -> Any:
    """A JSON file a run wrote (metrics.json, table.json, ...); a damaged or empty one is one
    error naming it and what to do."""
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise MissingInput(f"{path} not found") from None
    except UnicodeDecodeError as e:
        raise BadInput(f"{path} is damaged: not text ({e.reason}); restore it, or re-evaluate the run "
                       f"(stdr-eval {path.parent}) to write the {what} again") from None
    try:
        return json.loads(text)
    except ValueError as e:
        why = "empty" if not text.strip() else f"not valid JSON ({e})"
        raise BadInput(f"{path} is damaged: {why}; restore it, or re-evaluate the run (stdr-eval {path.parent}) to "
                       f"write the {what} again") from None


#: the environment variable that makes one write site fail (tests of the fault paths): SITE or
#: SITE:ERRNO_NAME, e.g. STDR_FAILPOINT=checkpoint:ENOSPC (default ENOSPC)
FAILPOINT_ENV = "STDR_FAILPOINT"

#: the write sites a failpoint can name, each a kind of file the commands write
SITES = ("config", "checkpoint", "metrics", "history", "profile", "ply", "compact", "pack", "tensorboard", "renders",
         "table", "chart", "camera_path", "video", "download", "capture", "frames", "cache", "lock")


def failpoint(site: str, path: str | Path) -> None:
    """Raise the OSError the environment asks for at `site` (STDR_FAILPOINT), as the disk would;
    nothing otherwise. Called by every write site after its bytes are written to the temporary
    file and before it replaces the previous one, where a full disk strikes."""
    spec = os.environ.get(FAILPOINT_ENV)
    if not spec:
        return
    name, _, code = spec.partition(":")
    if name == site:
        num = getattr(errno, code or "ENOSPC")
        raise OSError(num, os.strerror(num), str(path))


def leftover_temporaries(folder: str | Path) -> list[Path]:
    """The temporary files (temporary_beside, a checkpoint's previous-copy link) a process killed
    mid-write left in `folder` and its checkpoints/ (SIGKILL runs no clean-up)."""
    folder = Path(folder)
    return [p for d in (folder, folder / "checkpoints") if d.is_dir() for p in d.iterdir()
            if p.is_file() and p.name.startswith(".") and (".tmp." in p.name or p.name.endswith((".tmp", ".link")))]


def temporary_beside(path: Path) -> Path:
    """`.<stem>.tmp<suffix>` beside `path` (the suffix kept: writers that pick a format by it)."""
    return path.with_name(f".{path.stem}.tmp{path.suffix}")


@contextlib.contextmanager
def atomic_path(path: str | Path, site: str) -> Iterator[Path]:
    """Yield a temporary path beside `path` for the body to write; then rename it over `path`.
    On any failure the temporary file is removed and the previous `path` is untouched, and an
    OSError a user can fix (a full or read-only disk, ...) becomes an IOFault naming `path`."""
    path = Path(path)
    tmp = temporary_beside(path)
    try:
        yield tmp
        failpoint(site, path)
        os.replace(tmp, path)
    except BaseException as e:
        with contextlib.suppress(OSError):
            tmp.unlink()
        fault = _fault_behind(e, path)
        if fault is not None:
            raise fault from None
        raise


@contextlib.contextmanager
def writing(path: str | Path, site: str) -> Iterator[None]:
    """A write that cannot be atomic (a log appended to, a folder of renders): an OSError a user
    can fix becomes an IOFault naming `path`; STDR_FAILPOINT can make it fail."""
    try:
        failpoint(site, path)
        yield
    except Exception as e:
        fault = _fault_behind(e, path)
        if fault is None:
            raise
        raise fault from None


def _fault_behind(e: BaseException, path: Path | str) -> Optional[IOFault]:
    """The IOFault naming `path` for an OSError a user can fix (IO_FIXES) that is `e` or lies
    behind it: a library may wrap it (torch's zip writer raises a RuntimeError over the OSError
    of a full disk or `ulimit -f`, with no path). None for anything else, and for an IOFault
    already made (it names its own path)."""
    if not isinstance(e, Exception) or isinstance(e, IOFault):
        return None
    cause = io_cause(e)
    if cause is None or isinstance(cause, IOFault):
        return None
    return io_fault(cause, path)


def make_folder(path: str | Path) -> Path:
    """mkdir -p `path`; a read-only disk, a permission or a file in the way is one IOFault naming it."""
    path = Path(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        if e.errno not in IO_FIXES:
            raise
        raise io_fault(e, path) from None
    return path


def write_atomic(path: str | Path, data: str | bytes, site: str = "metrics") -> None:
    """Write `data` to a temporary file beside `path`, flush it to the disk, then rename it over
    `path` (atomic_path): a reader never sees half a file, and a failed write leaves the previous
    file and no temporary one."""
    raw = data.encode() if isinstance(data, str) else data
    with atomic_path(path, site) as tmp:
        with open(tmp, "wb") as f:
            f.write(raw)
            f.flush()
            os.fsync(f.fileno())


def write_png(path: str | Path, pixels, site: str = "renders") -> None:
    """`pixels` (uint8 or uint16 [H, W, C], OpenCV's BGR(A) order) as a PNG at `path`: encoded in
    memory, then written by write_atomic, so a full disk or a file-size limit is one IOFault naming
    `path` (cv2.imwrite would answer False, and libpng print to stderr) and no half image is left."""
    import cv2
    ok, buf = cv2.imencode(".png", pixels)
    if not ok:
        raise ValueError(f"{path}: OpenCV cannot encode an image of shape {tuple(pixels.shape)} as PNG")
    write_atomic(path, buf.tobytes(), site)


# ---------------------------------------------------------------- one writer per run folder
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
        return _parse((Path(run_dir) / LOCK_NAME).read_text(errors="replace"))
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
    fh = open(path, "a+", errors="replace")  # a damaged record (any bytes) is replaced, never a traceback
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


# ---------------------------------------------------------------- a run started over
#: a run folder's entries that are not results of its training: what this command writes anew or
#: reads (config, Hydra's record, the lock, the job's log, the viewer's camera paths) and the results
#: set aside before
NOT_RESULTS = frozenset({"config.yaml", ".hydra", LOCK_NAME, "train.log", "stdout.log", "camera_paths", "previous"})


def set_aside_results(run_dir: str | Path, when: Optional[str] = None) -> Optional[Path]:
    """A run started over (train.resume=false) in a folder that holds an earlier run's results:
    move them (checkpoints, metrics.json, history.json, the PLY, the compact file, renders, videos,
    TensorBoard's events, ...) into run_dir/previous/<time>/ with a copy of that run's config.yaml,
    so no file of the earlier run stands beside the new one as if it were its result. Returns the
    folder they went to, or None when there was nothing to move."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        return None
    found = sorted(p for p in run_dir.iterdir() if p.name not in NOT_RESULTS and not p.name.startswith("."))
    if not found:
        return None
    stamp = when or time.strftime("%Y%m%d-%H%M%S")
    dest = run_dir / "previous" / stamp
    n = 1
    while dest.exists():
        n += 1
        dest = run_dir / "previous" / f"{stamp}-{n}"
    make_folder(dest)
    with writing(dest, "config"):
        if (run_dir / "config.yaml").is_file():
            shutil.copy2(run_dir / "config.yaml", dest / "config.yaml")
        for p in found:
            os.replace(p, dest / p.name)
    return dest
