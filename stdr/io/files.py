"""A run's files, read and written safely: `read_yaml` and `read_json` (plain data, never code;
a damaged file is one error naming it), `write_atomic` (a reader never sees half a file, and a
failed write leaves the previous file and no temporary one)."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Iterator

import contextlib
import errno
import json
import os

import yaml
from omegaconf import OmegaConf

from ..errors import IO_FIXES, BadInput, IOFault, MissingInput, io_fault


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
                       f"(stdr-eval RUN) to write the {what} again") from None
    try:
        return json.loads(text)
    except ValueError as e:
        why = "empty" if not text.strip() else f"not valid JSON ({e})"
        raise BadInput(f"{path} is damaged: {why}; restore it, or re-evaluate the run (stdr-eval RUN) to write "
                       f"the {what} again") from None


#: the environment variable that makes one write site fail (tests of the fault paths): SITE or
#: SITE:ERRNO_NAME, e.g. STDR_FAILPOINT=checkpoint:ENOSPC (default ENOSPC)
FAILPOINT_ENV = "STDR_FAILPOINT"

#: the write sites a failpoint can name, each a kind of file the commands write
SITES = ("config", "checkpoint", "metrics", "history", "profile", "ply", "compact", "pack", "tensorboard", "renders",
         "table", "video", "download", "capture", "lock")


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
        if isinstance(e, OSError) and not isinstance(e, IOFault) and e.errno in IO_FIXES:
            raise io_fault(e, path) from None
        raise


@contextlib.contextmanager
def writing(path: str | Path, site: str) -> Iterator[None]:
    """A write that cannot be atomic (a log appended to, a folder of renders): an OSError a user
    can fix becomes an IOFault naming `path`; STDR_FAILPOINT can make it fail."""
    try:
        failpoint(site, path)
        yield
    except OSError as e:
        if isinstance(e, IOFault) or e.errno not in IO_FIXES:
            raise
        raise io_fault(e, path) from None


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
