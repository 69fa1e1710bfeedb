"""Atomic checkpoints that resume exactly."""
from __future__ import annotations

import contextlib
import hashlib
import shutil
import io
import os
import pickle
import random
import re
import warnings
from pathlib import Path
from typing import Any, Optional

import numpy as np
import torch

from ..errors import MissingInput, UserError
from .files import atomic_path

#: a run's last checkpoint, under its run folder
CKPT = "checkpoints/last.pt"


def rng_state() -> dict[str, Any]:
    """Global RNG states as tensors and plain numbers (loadable with weights_only=True): the CPU
    generator, one per visible CUDA device (splits and dropout draw on the device of their
    tensors), numpy's and Python's."""
    name, keys, pos, has_gauss, cached = np.random.get_state()
    version, internal, gauss_next = random.getstate()
    return {"torch": torch.get_rng_state(),
            "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else [],
            "numpy": [name, torch.from_numpy(keys.astype(np.int64)), int(pos), int(has_gauss), float(cached)],
            "python": [version, list(internal), gauss_next]}


def set_rng_state(s: dict[str, Any]) -> None:
    torch.set_rng_state(s["torch"])
    cuda = s.get("cuda", [])
    if cuda and torch.cuda.is_available():
        n = torch.cuda.device_count()
        if len(cuda) != n:
            warnings.warn(f"checkpoint has RNG states for {len(cuda)} CUDA device(s), this machine {n}: random "
                          "draws after the resume will not repeat the uninterrupted run", RuntimeWarning, stacklevel=2)
        for i, st in enumerate(cuda[:n]):
            torch.cuda.set_rng_state(st, i)
    name, keys, pos, has_gauss, cached = s["numpy"]
    np.random.set_state((name, keys.numpy().astype(np.uint32), pos, has_gauss, cached))
    version, internal, gauss_next = s["python"]
    random.setstate((version, tuple(internal), gauss_next))


ENVELOPE = "stdr-checkpoint-v2"  # {"envelope", "sha256", "data": uint8 bytes of the torch.save'd payload}


class CheckpointError(UserError, RuntimeError):
    """A checkpoint that cannot be used: unreadable, truncated, corrupted or missing entries."""


def previous_path(path: str | Path) -> Path:
    """Where save_checkpoint(..., keep_previous=True) keeps the checkpoint it replaces."""
    path = Path(path)
    return path.with_name(f"{path.stem}.previous{path.suffix}")


def _keep_as_previous(path: Path) -> None:
    """previous_path(path) becomes a copy of `path` while `path` stays where it is (a hard link,
    or a copy where the file system has none), so that last.pt exists at every moment."""
    prev = previous_path(path)
    side = prev.with_name(f".{prev.name}.link")
    with contextlib.suppress(FileNotFoundError):
        side.unlink()
    try:
        os.link(path, side)
    except OSError:
        shutil.copyfile(path, side)
    os.replace(side, prev)


def save_checkpoint(path: str | Path, payload: dict[str, Any], keep_previous: bool = False,
                    site: str = "checkpoint") -> dict[str, Any]:
    """Write `payload` with a SHA-256 of its bytes (torch's own format does not notice a flipped
    byte: it loads wrong values) to a temporary file in the same folder, fsync, then rename over
    `path` (stdr.io.files.atomic_path: a failed write leaves the previous file and no temporary
    one, and names the path). keep_previous: the file being replaced is kept as
    `previous_path(path)` first, and `path` exists at every moment, so a damaged last one leaves
    the one before. site: the failpoint's name (stdr.io.files.failpoint). Returns the file's identity
    (checkpoint_identity)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    buf = io.BytesIO()
    torch.save(payload, buf)
    raw = buf.getbuffer()
    sha = hashlib.sha256(raw).hexdigest()
    envelope = {"envelope": ENVELOPE, "sha256": sha, "step": payload_step(payload),
                "data": torch.frombuffer(bytearray(raw), dtype=torch.uint8)}
    # a full disk, a file-size limit, a kill: no half file is left, and the previous checkpoint stays
    with atomic_path(path, site) as tmp:
        with open(tmp, "wb") as f:
            torch.save(envelope, f)
            f.flush()
            os.fsync(f.fileno())
        if keep_previous and path.is_file():
            _keep_as_previous(path)
    return {"step": envelope["step"], "sha256": sha}


def _damaged(path: Path, why: str) -> CheckpointError:
    prev = previous_path(path)
    hint = ""
    if prev.is_file() and prev != path:
        try:
            step = load_checkpoint(prev).get("model", {}).get("step")
            hint = (f" The previous checkpoint {prev} is intact (iteration {step}): move it to {path} to resume "
                    "from it, or set train.resume=false to start over.")
        except CheckpointError:
            hint = f" The previous checkpoint {prev} is damaged too: set train.resume=false to start over."
    return CheckpointError(f"checkpoint {path} is damaged: {why} (a write cut short, a full disk or a bad copy)."
                           + hint)


ZIP_MAGIC = b"PK\x03\x04"


def _torch_load(src, path: Path) -> Any:
    """torch.load with weights_only=True (never code from a file). A pickle of objects other
    than tensors and containers is another program's file, not a damaged one of ours: say so
    (and never pass on torch's advice to load it with weights_only=False)."""
    try:
        return torch.load(src, map_location="cpu", weights_only=True)  # no code from a file
    except pickle.UnpicklingError as e:
        text = str(e)
        if "Weights only load failed" in text or "Unsupported global" in text:
            found = re.search(r"Unsupported global: GLOBAL ([\w.]+)", text)
            what = f"objects of {found.group(1)}" if found else "objects other than tensors"
            raise CheckpointError(f"{path} is not an stdr checkpoint or model file: it holds pickled {what}, which "
                                  "the stdr package never loads (it runs no code from a file)") from None
        raise _damaged(path, f"it cannot be read (UnpicklingError: {text.splitlines()[0][:200]})") from None
    except Exception as e:  # noqa: BLE001 - truncated zip, bad record, ...: a damaged file
        raise _damaged(path, f"it cannot be read ({type(e).__name__}: {str(e).splitlines()[0][:200]})") from None


def payload_step(payload: Any) -> Optional[int]:
    """The training step a checkpoint payload holds (a training checkpoint's or a model file's)."""
    if not isinstance(payload, dict):
        return None
    model = payload.get("model")
    step = model.get("step") if isinstance(model, dict) else payload.get("step")
    return None if step is None else int(step)


def checkpoint_identity(path: str | Path) -> Optional[dict[str, Any]]:
    """{"step", "sha256"} of a checkpoint file: the SHA-256 its envelope was written with and the
    step it holds, read without loading the payload (the file is memory-mapped). What the results
    of a run (metrics.json, history.json, pack.json, videos, exports) record as their source, and
    what readers compare with the run's last checkpoint. None: no file, or one from before the
    checksum (nothing to compare)."""
    path = Path(path)
    if not path.is_file():
        return None
    try:
        ck = torch.load(path, map_location="cpu", weights_only=True, mmap=True)
    except Exception:  # noqa: BLE001 - unreadable: load_checkpoint names the damage where it matters
        return None
    if not (isinstance(ck, dict) and ck.get("envelope") == ENVELOPE):
        return None
    step = ck.get("step")
    if step is None:  # written before the envelope named its step
        step = payload_step(_torch_load(io.BytesIO(ck["data"].numpy().tobytes()), path))
    return {"step": step, "sha256": ck["sha256"]}


def source_line(identity: Optional[dict[str, Any]]) -> str:
    """The one-line form of a checkpoint identity that a PLY header or a video's metadata carries:
    'stdr checkpoint step=N sha256=...'; '' for an unknown source."""
    if not identity or not identity.get("sha256"):
        return ""
    return f"stdr checkpoint step={identity.get('step')} sha256={identity['sha256']}"


def load_checkpoint(path: str | Path, require: tuple[str, ...] = ()) -> dict[str, Any]:
    """The payload saved by save_checkpoint (also files written before the checksum: plain
    payloads, not verified). `require`: top-level entries that must be present. Never runs code
    from the file (weights_only). Errors name the file and, when damaged, the previous one."""
    path = Path(path)
    if not path.is_file():
        raise MissingInput(f"checkpoint not found: {path}")
    with open(path, "rb") as f:
        head = f.read(4)
    if head != ZIP_MAGIC:  # every file torch.save writes (and so every file of the stdr package) is a zip archive
        raise CheckpointError(f"{path} is not an stdr checkpoint or model file: it is not a file torch.save writes "
                              f"(it starts with {head!r}); pass a run folder, its checkpoints/last.pt or a "
                              "model.stdrc")
    ck = _torch_load(path, path)
    if isinstance(ck, dict) and ck.get("envelope") == ENVELOPE:
        data = ck.get("data")
        if not torch.is_tensor(data) or data.dtype != torch.uint8:
            raise _damaged(path, "its envelope has no payload")
        raw = data.numpy().tobytes()
        if hashlib.sha256(raw).hexdigest() != ck.get("sha256"):
            raise _damaged(path, "its SHA-256 does not match the one written with it")
        ck = _torch_load(io.BytesIO(raw), path)
    if not isinstance(ck, dict):
        raise CheckpointError(f"checkpoint {path} holds a {type(ck).__name__}, not a stdr checkpoint")
    missing = [k for k in require if k not in ck]
    if missing:
        raise CheckpointError(f"checkpoint {path} has no {', '.join(missing)}: it is not a training checkpoint "
                              "of stdr-train (a model-only file from DynamicGaussians.save cannot resume training)")
    return ck
