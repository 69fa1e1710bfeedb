"""The user-facing error: bad input (a key, a value, a file, a download) that a command reports
in one line, exit code 2, without a traceback. Every error class whose message tells the user
what to change derives from it; anything else reaching a command's top is a bug and keeps its
traceback."""
from __future__ import annotations

import errno
import io
import os
import sys
from contextlib import contextmanager
from typing import Iterator, Optional

#: the exit code of a command stopped by bad input (argparse's, for the same reason)
USAGE_EXIT = 2


class UserError(Exception):
    """Bad input; the message names the key or file, the value and what is allowed."""


class ConfigError(UserError, ValueError):
    """A config key or value that a run cannot use (unknown key, out-of-range value, wrong path)."""


class BadInput(UserError, ValueError):
    """A file or value the user handed over with a bad field (a scene's JSON, a camera, an image)."""


class MissingInput(UserError, FileNotFoundError):
    """A file or folder the user named that is not there, or not of the kind needed."""


class RegistrationError(UserError, TypeError, ValueError):
    """A baseline, plug-in or strategy declared so that it cannot work (a hook without the step's
    context, a capability without what backs it, a name taken twice): raised at registration, in
    the package that declares it, and reported in one line that names the class, the hook or
    argument, and the fix."""


class MissingKey(UserError, KeyError):
    """A file the user handed over that lacks an entry it needs."""

    def __str__(self) -> str:  # KeyError quotes its message; this one is a sentence
        return str(self.args[0]) if self.args else ""


class IOFault(UserError, OSError):
    """The machine refused a write (a read-only or full disk, a file-size limit, a permission, a
    path through a file): the message names the path, the cause and what to do."""

    def __str__(self) -> str:  # the sentence, without OSError's "[Errno N]"
        return str(self.strerror)


#: the causes of an I/O fault a user can do something about, and what
IO_FIXES = {
    errno.EROFS: "the file system is mounted read-only: write somewhere else",
    errno.ENOSPC: "the disk is full: free space, or write somewhere else",
    errno.EDQUOT: "the disk quota is used up: free space, or write somewhere else",
    errno.EFBIG: "the file would exceed the file-size limit (ulimit -f) or the file system's largest file",
    errno.EACCES: "no permission to write there: write somewhere else, or change its permissions",
    errno.EPERM: "the operation is not permitted there: write somewhere else, or change its permissions",
    errno.ENOTDIR: "a part of the path is a file, not a folder",
    errno.EISDIR: "it is a folder, where a file is needed",
    errno.EEXIST: "a file is in the way of a folder of that name",
    errno.ENAMETOOLONG: "a name in the path is longer than the file system allows (255 bytes a folder or file "
                        "name, 4096 the whole path): choose a shorter one",
}


def io_fault(e: OSError, path=None) -> IOFault:
    """The IOFault of OSError `e` at `path` (default: the path the error names; else the file a
    frame of its traceback was writing)."""
    where = path if path is not None else (e.filename if e.filename is not None else _file_in_traceback(e))
    return IOFault(e.errno, f"cannot write {where}: {os.strerror(e.errno)} ({IO_FIXES.get(e.errno, 'an I/O error')})")


def _file_in_traceback(e: BaseException) -> str:
    """The name of the open file the innermost frame of `e`'s traceback holds: an OSError raised
    by a write or close (a full disk, `ulimit -f`) names no path, but the frame that wrote still
    holds the file object (e.g. Hydra's .hydra/config.yaml). "a file" where no frame holds one."""
    frames = []
    tb = e.__traceback__
    while tb is not None:
        frames.append(tb.tb_frame)
        tb = tb.tb_next
    for frame in reversed(frames):
        for v in frame.f_locals.values():
            if isinstance(v, io.IOBase) and isinstance(getattr(v, "name", None), str):
                return v.name
    return "a file"


def io_cause(e: BaseException) -> Optional[OSError]:
    """The OSError of a user-fixable cause (IO_FIXES) behind `e` (itself, or its cause or context:
    e.g. logging's 'Unable to configure handler' over a read-only folder), else None."""
    seen = set()
    while e is not None and id(e) not in seen:
        seen.add(id(e))
        if isinstance(e, OSError) and e.errno in IO_FIXES:
            return e
        e = e.__cause__ or e.__context__
    return None


@contextmanager
def reported(prog: str) -> Iterator[None]:
    """Run a command's body; a UserError ends it with `<prog>: error: <message>` on stderr, one
    line (the message's own line breaks folded), and exit code 2. So does an I/O fault the user
    can fix (a read-only or full disk, a permission, ...: IO_FIXES), named by its path."""
    try:
        yield
    except UserError as e:
        _one_line(prog, str(e))
    except Exception as e:  # noqa: BLE001 - an I/O fault is reported, anything else is a bug
        cause = io_cause(e)
        if cause is None:
            raise
        _one_line(prog, str(io_fault(cause)) if not isinstance(cause, IOFault) else str(cause))


def _one_line(prog: str, message: str) -> None:
    msg = " ".join(message.split())
    print(f"{prog}: error: {msg}", file=sys.stderr, flush=True)
    raise SystemExit(USAGE_EXIT) from None
