"""The user-facing error: bad input (a key, a value, a file, a download) that a command reports
in one line, exit code 2, without a traceback. Every error class whose message tells the user
what to change derives from it; anything else reaching a command's top is a bug and keeps its
traceback."""
from __future__ import annotations

import sys
from contextlib import contextmanager
from typing import Iterator

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


class MissingKey(UserError, KeyError):
    """A file the user handed over that lacks an entry it needs."""

    def __str__(self) -> str:  # KeyError quotes its message; this one is a sentence
        return str(self.args[0]) if self.args else ""


@contextmanager
def reported(prog: str) -> Iterator[None]:
    """Run a command's body; a UserError ends it with `<prog>: error: <message>` on stderr, one
    line (the message's own line breaks folded), and exit code 2."""
    try:
        yield
    except UserError as e:
        msg = " ".join(str(e).split())
        print(f"{prog}: error: {msg}", file=sys.stderr, flush=True)
        raise SystemExit(USAGE_EXIT) from None
