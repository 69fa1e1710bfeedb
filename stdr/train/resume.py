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

**Stop signals.** Ctrl+C (SIGINT) and SIGTERM (kill, docker stop, systemd) end training the same
way: the step in progress finishes, its checkpoint is written, one line says where the run stopped
and how to go on, and the process exits with 130 or 143. A second Ctrl+C stops at once.

**SIGTERM in a launcher's job.** In a Slurm job submitit holds SIGTERM (it ignores it: a
preemption may send SIGTERM before the warning signal). Slurm sends SIGTERM for `scancel`, at the
time limit and at a preemption, and SIGKILL some seconds later (KillWait, GraceTime). Training
takes the signal too, then passes it to the launcher's handler: the step in progress finishes and
is checkpointed, and the process then trains no further and writes nothing more. It waits for the cluster's
next signal: the warning signal goes to the launcher (submitit requeues the job from that
checkpoint), the kill ends it with every file whole; after TERM_WAIT_S seconds with neither it
exits with 143 itself.

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
PROCESS_KEYS = ("name", "train.stop_at", "train.deadline", "train.start_by", "train.threads", "train.progress",
                "train.log_every", "train.image_every", "train.checkpoint_every", "train.checkpoint_minutes",
                "train.skip_finished",
                "train.resume", "eval.")

#: where a run's data and caches are: edited in config.yaml when a run moves to another machine or
#: folder, which is not a change of its training (data.json's fingerprints check the data itself)
LOCATION_KEYS = ("data.path", "data.cache_dir", "data.undistort_cache")

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


def trained_config(run_dir: Path, trained: Optional[dict]) -> Optional[dict]:
    """The config the run's last checkpoint was trained with (its model entry's `trained`), as
    today's code reads it; None when there is none or it cannot be read here."""
    if trained is None:
        return None
    try:
        return OmegaConf.to_container(load_config(dict(trained), f"{run_dir}/checkpoints/last.pt"), resolve=False)
    except ConfigError:
        return None  # a config of another version or plug-in set: resume_changes names what it cannot read


def resume_changes(cfg, run_dir: Path, step: int, trained: Optional[dict] = None) -> tuple[dict, list]:
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
    ck = trained_config(run_dir, trained)
    edited = {k: v for k, v in config_diff(ck, old).items() if k not in LOCATION_KEYS} if ck is not None else {}
    if edited:  # config.yaml edited by hand: it no longer says how the checkpoint was trained
        if cfg.train.resume != "override":
            listed = "; ".join(f"{k}: {_show(a)} (trained) -> {_show(b)} (config.yaml)" for k, (a, b) in edited.items())
            raise ConfigError(f"{run_dir}/config.yaml differs from the config its checkpoint at iteration {step} was "
                              f"trained with, in {len(edited)} key(s) that change training: {listed}. Restore the "
                              "run's values in config.yaml, or add train.resume=override to continue with this "
                              "command's values (config.yaml then records the change)")
        old = ck  # the change recorded is from what trained to what this command trains
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


#: the signals a user or a system sends to stop a process (Ctrl+C; kill, docker stop, systemd)
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)
#: after a launcher's SIGTERM and the checkpoint, how long the process waits for the cluster's warning
#: signal or kill before it exits itself (STDR_TERM_WAIT_S; Slurm's KillWait is 30 s by default)
TERM_WAIT_ENV = "STDR_TERM_WAIT_S"
TERM_WAIT_S = 120.0


class StopNow(KeyboardInterrupt):
    """A second Ctrl+C while training stops for the first: the process ends at once, without the
    checkpoint of the step in progress (stdr-train prints one line and exits 130)."""


class Preemption:
    """What stopped the loop: the cluster's warning signal (`hand_over` passes it on once the
    checkpoint is written) or a stop signal (SIGINT, SIGTERM: `hand_over` exits with 128 + its
    number, as the signal would have ended the process, with nothing lost)."""

    def __init__(self, signum: signal.Signals, previous, stops: Optional[dict] = None,
                 launcher_term=None):
        self.signum = signum
        self.previous = previous
        self.stops = stops or {}  # {stop signal: its handler before}
        self.launcher_term = launcher_term  # a launcher's SIGTERM handler, taken over too (submitit's)
        self.term_wait_s = term_wait_s()
        self.frame = None
        self.requested = False
        self.warned = False  # the warning signal arrived
        self.stopped_by: Optional[signal.Signals] = None  # the stop signal that arrived, if one did

    def _caught(self, signum, frame) -> None:
        self.requested, self.warned, self.frame = True, True, frame
        print(f"[stdr] {signal.Signals(signum).name}: the cluster stops this job soon; the step in progress "
              "finishes and is checkpointed", flush=True)

    def _stop(self, signum, frame) -> None:
        signum = signal.Signals(signum)
        if self.stopped_by is not None and signum == signal.SIGINT:  # a second Ctrl+C: at once
            raise StopNow
        self.requested, self.frame = True, frame
        self.stopped_by = self.stopped_by or signum
        print(f"[stdr] {signum.name}: stopping after the step in progress, with a checkpoint "
              "(Ctrl+C again stops at once, without one)", flush=True)

    def _launcher_stop(self, signum, frame) -> None:
        """SIGTERM in a launcher's job: stop after the step in progress, and pass it on."""
        self.requested, self.frame = True, frame
        self.stopped_by = self.stopped_by or signal.SIGTERM
        print("[stdr] SIGTERM: stopping after the step in progress, with a checkpoint; then waiting for the "
              "cluster", flush=True)
        self.launcher_term(signum, frame)

    def restore(self) -> None:
        for s, h in self.stops.items():
            if signal.getsignal(s) == self._stop:
                signal.signal(s, h)
        if self.launcher_term is not None and signal.getsignal(signal.SIGTERM) == self._launcher_stop:
            signal.signal(signal.SIGTERM, self.launcher_term)

    def hand_over(self) -> None:
        """A stop signal: exit with 128 + its number. The warning signal: to its earlier handler
        (submitit: requeue and exit); without one, exit as the signal would have ended the process.
        A launcher's SIGTERM: wait for the cluster's warning signal (to the launcher) or its kill,
        at most TERM_WAIT_S seconds, then exit with 143."""
        self.restore()
        if self.stopped_by is not None and not self.warned:
            if self.launcher_term is not None and self.stopped_by == signal.SIGTERM:
                self._wait_for_the_cluster()
            raise SystemExit(128 + int(self.stopped_by))
        signal.signal(self.signum, self.previous)
        if callable(self.previous):
            self.previous(self.signum, self.frame)
        if self.previous != signal.SIG_IGN:
            raise SystemExit(128 + int(self.signum))


    def _wait_for_the_cluster(self) -> None:
        """Sleep, writing nothing, until the warning signal (its earlier handler runs: submitit requeues
        and exits) or the kill, or TERM_WAIT_S seconds."""
        signal.signal(self.signum, self.previous)
        wait = self.term_wait_s
        print(f"[stdr] checkpoint written; waiting up to {wait:.0f} s for the cluster's warning signal "
              "(a requeue) or its kill", flush=True)
        end = time.monotonic() + wait
        while time.monotonic() < end:
            time.sleep(min(1.0, max(end - time.monotonic(), 0.0)))


def term_wait_s() -> float:
    """STDR_TERM_WAIT_S (seconds, >= 0), else TERM_WAIT_S; read when training starts, so that a bad
    value is one line before any step, not a traceback after the checkpoint."""
    text = os.environ.get(TERM_WAIT_ENV)
    if text is None:
        return TERM_WAIT_S
    try:
        value = float(text)
    except ValueError:
        value = -1.0
    if not value >= 0:
        raise ConfigError(f"{TERM_WAIT_ENV}={text!r}: give the seconds to wait after a launcher's SIGTERM, a number >= 0 "
                          f"(unset: {TERM_WAIT_S:.0f})")
    return value


def _takes(signum: signal.Signals, handler) -> bool:
    """Whether training may take a stop signal over: only from the interpreter's own default
    (SIGINT's KeyboardInterrupt, SIGTERM's termination). A launcher's handler (submitit bypasses
    SIGTERM in a Slurm job, whose warning signal comes first) or an ignored signal stays as it is."""
    return handler is signal.default_int_handler if signum == signal.SIGINT else handler == signal.SIG_DFL


@contextlib.contextmanager
def preemption() -> Iterator[Optional[Preemption]]:
    """Hold the warning signal and the stop signals while the body trains (the main thread only:
    elsewhere, None): each ends the loop after the step in progress, which is checkpointed."""
    if threading.current_thread() is not threading.main_thread():
        yield None
        return
    signum = warning_signal()
    previous = signal.getsignal(signum)
    stops = {s: signal.getsignal(s) for s in STOP_SIGNALS if s != signum and _takes(s, signal.getsignal(s))}
    term = signal.getsignal(signal.SIGTERM)
    launcher_term = term if signum != signal.SIGTERM and signal.SIGTERM not in stops and callable(term) else None
    p = Preemption(signum, previous, stops, launcher_term)
    signal.signal(signum, p._caught)
    for s in stops:
        signal.signal(s, p._stop)
    if launcher_term is not None:
        signal.signal(signal.SIGTERM, p._launcher_stop)
    try:
        yield p
    finally:
        if signal.getsignal(signum) == p._caught:
            signal.signal(signum, previous)
        p.restore()
