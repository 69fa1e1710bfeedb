"""A run that continues in another process: the resume keeps its run's record, and a cluster's
warning signal ends a job with a checkpoint of the step it reached.

**The record.** A run resumed from its checkpoint must be trained by the config its first steps were trained by,
or the record (config.yaml) no longer says how the model came to be. `resume_changes` compares
the two; a key that changes training is refused, naming each key with both values, unless the
command says `train.resume=override`. Then training goes on with the new values and config.yaml
keeps what changed at which step (its top-level `config_changes` list), which metrics.json repeats.

Keys that only steer the process (when it stops, how many threads, what it prints and logs,
how often it checkpoints) and the final evaluation's keys (`eval.*`: they change no training
step) may differ freely: PROCESS_KEYS, listed in docs/outputs.md.

**The warning signal.** A Slurm job near its time limit, or about to be preempted, is sent a
signal ahead of the kill (submitit's `signal_delay_s`: SIGUSR2 unless SUBMITIT_PREEMPT_SIGNAL names another). Training
holds that signal while it runs (`preemption()`): the step in progress finishes, the checkpoint of
that step is written, and then the signal goes on to whoever handled it before — submitit, which
requeues the job; the requeued job resumes from that checkpoint, so no step is lost and the run
ends bit-identical to one trained without interruption. Without a handler before (a run outside
submitit), the process exits with 128 + the signal's number after the checkpoint, as the signal's
default action would, but with nothing lost.
"""
from __future__ import annotations

import contextlib
import os
import signal
import threading
import time
from pathlib import Path
from typing import Any, Iterator, Optional

from omegaconf import OmegaConf

from ..store import CHANGES_KEY, load_config
from ..errors import ConfigError
from ..io.files import read_yaml

#: keys a resume may change without train.resume=override: prefixes end with "."
PROCESS_KEYS = ("train.stop_at", "train.deadline", "train.start_by", "train.threads", "train.progress",
                "train.log_every", "train.image_every", "train.checkpoint_every", "train.skip_finished",
                "train.resume", "eval.")

#: derived from other keys (a change there shows in the keys it is derived from)
DERIVED = ("schedule",)


def flatten(node: Any, prefix: str = "") -> dict[str, Any]:
    """{'optim.iterations': 1500, ...}: a nested mapping's leaves by dotted key (lists are leaves)."""
    out: dict[str, Any] = {}
    if isinstance(node, dict):
        for k, v in node.items():
            key = f"{prefix}{k}"
            if isinstance(v, dict) and v:
                out.update(flatten(v, key + "."))
            else:
                out[key] = v
    return out


def is_process_key(key: str) -> bool:
    return any(key == p or (p.endswith(".") and key.startswith(p)) for p in PROCESS_KEYS)


def config_diff(old: dict, new: dict) -> dict[str, tuple[Any, Any]]:
    """{key: (old value, new value)} for every key that changes training (absent: '<unset>')."""
    a = {k: v for k, v in flatten(old).items() if k.split(".")[0] not in (*DERIVED, CHANGES_KEY)}
    b = {k: v for k, v in flatten(new).items() if k.split(".")[0] not in (*DERIVED, CHANGES_KEY)}
    missing = "<unset>"
    return {k: (a.get(k, missing), b.get(k, missing)) for k in sorted(set(a) | set(b))
            if a.get(k, missing) != b.get(k, missing) and not is_process_key(k)}


def saved_config(run_dir: Path) -> dict | None:
    """The run's config.yaml as a plain dict (None when there is none)."""
    path = Path(run_dir) / "config.yaml"
    if not path.is_file():
        return None
    raw = read_yaml(path)
    return raw if isinstance(raw, dict) else None


def resume_changes(cfg, run_dir: Path, step: int) -> tuple[dict, list]:
    """For a run about to resume at `step`: (the config to write as config.yaml, the list of
    changes recorded so far, this resume's included). Raises ConfigError naming every changed
    key with both values unless cfg.train.resume == "override"."""
    new = OmegaConf.to_container(cfg, resolve=True)
    raw = saved_config(run_dir)
    history = list((raw or {}).get(CHANGES_KEY) or [])
    if raw is None:
        return new, history
    # the run's config as today's code reads it (stdr-eval rebuilds the run the same way): a key
    # renamed or added since the run was trained is not a change this command makes
    old = OmegaConf.to_container(load_config(Path(run_dir) / "config.yaml"), resolve=False)
    diff = config_diff(old, new)
    if diff:
        listed = "; ".join(f"{k}: {_show(a)} (the run's) -> {_show(b)} (this command's)" for k, (a, b) in diff.items())
        if cfg.train.resume != "override":
            raise ConfigError(
                f"{run_dir}: this command would resume the run at iteration {step} with other values than "
                f"its config.yaml in {len(diff)} key(s) that change training: {listed}. Run it with the "
                "run's own values, use another hydra.run.dir for a new run, or add train.resume=override "
                "to continue this run with the new values (config.yaml then records the change)")
        history.append({"step": int(step), "time": time.strftime("%Y-%m-%d %H:%M:%S %z"),
                        "keys": {k: [a, b] for k, (a, b) in diff.items()}})
        print(f"[stdr] {run_dir}: resuming at iteration {step} with changed keys (train.resume=override): {listed}",
              flush=True)
    return new, history


def _show(v: Any) -> str:
    return repr(v) if isinstance(v, str) else str(v)


# ---------------------------------------------------------------- the warning signal
#: submitit's name for the signal (its default: USR2)
SIGNAL_ENV = "SUBMITIT_PREEMPT_SIGNAL"


def warning_signal() -> signal.Signals:
    name = os.environ.get(SIGNAL_ENV, "USR2").upper()
    return getattr(signal, name if name.startswith("SIG") else f"SIG{name}", signal.SIGUSR2)


class Preemption:
    """Set by the warning signal; `hand_over` passes it on once the checkpoint is written."""

    def __init__(self, signum: signal.Signals, previous):
        self.signum = signum
        self.previous = previous
        self.frame = None
        self.requested = False

    def _caught(self, signum, frame) -> None:
        self.requested, self.frame = True, frame
        print(f"[stdr] {signal.Signals(signum).name}: the cluster stops this job soon; the step in progress "
              "finishes and is checkpointed", flush=True)

    def hand_over(self) -> None:
        """The signal to its earlier handler (submitit: requeue and exit); without one, exit as the
        signal would have ended the process."""
        signal.signal(self.signum, self.previous)
        if callable(self.previous):
            self.previous(self.signum, self.frame)
        if self.previous != signal.SIG_IGN:
            raise SystemExit(128 + int(self.signum))


@contextlib.contextmanager
def preemption() -> Iterator[Optional[Preemption]]:
    """Hold the warning signal while the body trains (the main thread only: elsewhere, None)."""
    if threading.current_thread() is not threading.main_thread():
        yield None
        return
    signum = warning_signal()
    previous = signal.getsignal(signum)
    p = Preemption(signum, previous)
    signal.signal(signum, p._caught)
    try:
        yield p
    finally:
        if signal.getsignal(signum) == p._caught:
            signal.signal(signum, previous)
