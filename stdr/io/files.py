"""A run's files, read and written safely: `read_yaml` and `read_json` (plain data, never code;
a damaged file is one error naming it), `write_atomic` (a reader never sees half a file, and a
failed write leaves the previous file and no temporary one)."""
from __future__ import annotations

from pathlib import Path
from typing import Any

import json
import os

import yaml
from omegaconf import OmegaConf

from ..errors import BadInput, MissingInput


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


def write_atomic(path: str | Path, data: str | bytes) -> None:
    """Write `data` to a temporary file beside `path`, flush it to the disk, then rename it over
    `path`. On any failure (a full disk, a read-only folder) the temporary file is removed and
    the previous `path` is untouched; the OSError goes on to the caller."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    raw = data.encode() if isinstance(data, str) else data
    try:
        with open(tmp, "wb") as f:
            f.write(raw)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            tmp.unlink()
        except OSError:
            pass
        raise
