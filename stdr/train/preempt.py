"""A cluster's warning signal ends a run with a checkpoint of the step it reached.

A Slurm job near its time limit, or about to be preempted, is sent a signal ahead of the kill
(submitit's `signal_delay_s`: SIGUSR2 unless SUBMITIT_PREEMPT_SIGNAL names another). Training
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
from typing import Iterator, Optional

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
