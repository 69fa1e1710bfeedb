"""The state of a run as one object: everything its checkpoint holds.

`RunState` is what a training run has that a rendered model does not: the per-Gaussian and the
networks' optimizers, the densification strategy's statistics, the camera sampler, the guard, the
training seconds and the learning curve (`history`), the contribution-pruning events. The trainer
owns one; the guard (stdr.train.guard), the final evaluation (stdr.eval.evaluate.evaluate_run) and
`stdr-eval`'s re-evaluation take `(model, state)` — `state.model` — and a `RunLog`, never the
trainer. A state is either live (built by the trainer; `payload()` is its checkpoint) or loaded
(`RunState.from_checkpoint`: what a saved run recorded, enough to report and evaluate it, no
optimizers).

    payload = state.payload()                 # the checkpoint's dict (PAYLOAD_KEYS and the records)
    state.restore(payload, "guard snapshot")  # a live state back to a payload (optimizers rebuilt)
    state.save()                              # run_dir/checkpoints/last.pt, atomically
    RunState.from_checkpoint(ck, model, run_dir)  # a saved run's state, for stdr-eval
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Optional

import torch
from torch import Tensor

from .optim import clear_grads
from ..io.checkpoint import CKPT, checkpoint_identity, rng_state, save_checkpoint, set_rng_state
from ..errors import io_cause
from ..io.files import writing
from .guard import Guard
from ..syncs import host_only
from ..model import model_entry

# what a checkpoint a run resumes from must hold (the model entry, then the optimization's state)
PAYLOAD_KEYS = ("model", "optimizers", "net_opt", "strategy_state", "sampler", "rng", "train_seconds")


class CameraSampler:
    """Training frames drawn without replacement per epoch, from its own generator."""

    def __init__(self, n: int, seed: int):
        self.n = n
        self.gen = torch.Generator().manual_seed(seed)
        self.stack: list[int] = []

    def next(self) -> int:
        if not self.stack:
            with host_only():  # a CPU generator's permutation: host work, no device to wait for
                self.stack = torch.randperm(self.n, generator=self.gen, device="cpu").tolist()
        return self.stack.pop()

    def state_dict(self):
        return {"gen": self.gen.get_state(), "stack": list(self.stack)}

    def load_state_dict(self, s):
        self.gen.set_state(s["gen"])
        self.stack = list(s["stack"])


class RunLog:
    """A run's TensorBoard events (run_dir/tb), opened at the first scalar or image: the one
    logger the trainer, the guard and the evaluations write to."""

    def __init__(self, run_dir: str | Path):
        self.dir = Path(run_dir) / "tb"
        self.writer = None

    def open(self):
        """The SummaryWriter, opened at the first use. Its writes go to the disk from a thread of
        its own, whose errors surface at a later call: every call here is under `writing`, so a
        full or read-only disk is one error naming run_dir/tb."""
        if self.writer is None:
            from torch.utils.tensorboard import SummaryWriter
            _quiet_writer_thread()
            with writing(self.dir, "tensorboard"):
                self.writer = SummaryWriter(str(self.dir))
        return self.writer

    def scalar(self, tag: str, value, step: int) -> None:
        with writing(self.dir, "tensorboard"):
            self.open().add_scalar(tag, value, step)

    def scalar_if_open(self, tag: str, value, step: int) -> None:
        """Only into a log that is already open (an evaluation outside training opens none)."""
        if self.writer is not None:
            with writing(self.dir, "tensorboard"):
                self.writer.add_scalar(tag, value, step)

    def flush(self) -> None:
        """Everything written so far on the disk (the end of training): a fault says so here."""
        if self.writer is not None:
            with writing(self.dir, "tensorboard"):
                self.writer.flush()

    def step_scalars(self, it: int, logs: dict[str, Any], dt: float, state: "RunState", device) -> None:
        """A training step's scalars: losses, PSNR, Gaussian counts, seconds, memory, learning
        rates and the densification's counts (`logs`: Trainer.train_step's result)."""
        with writing(self.dir, "tensorboard"):
            self._step_scalars(self.open(), it, logs, dt, state, device)

    @staticmethod
    def _step_scalars(tb, it: int, logs: dict[str, Any], dt: float, state: "RunState", device) -> None:
        for k in ("loss", "l1", "dssim"):
            tb.add_scalar(f"loss/{k}", logs[k], it)
        tb.add_scalar("train/psnr", logs["psnr"], it)
        tb.add_scalar("gaussians/count", state.model.num_gaussians, it)
        tb.add_scalar("gaussians/rendered", logs["active"], it)  # after temporal culling (render.cull=train)
        tb.add_scalar("time/seconds_per_iteration", dt, it)
        mb = state.guard.note_memory(device)
        if mb is not None:
            tb.add_scalar("memory/mb", mb, it)  # docs/stability.md: the process's memory (CUDA: peak allocated)
        for k, o in state.optimizers.items():
            tb.add_scalar(f"lr/{k}", o.param_groups[0]["lr"], it)
        for g in state.net_opt.param_groups:
            tb.add_scalar(f"lr/{g.get('name', 'deform')}", g["lr"], it)
        for k, v in logs["densify"].items():
            tb.add_scalar(f"densify/{k}", v, it)
        for k, v in logs["losses"].items():
            tb.add_scalar(f"loss/{k}", v, it)

    def render_and_truth(self, it: int, img: Tensor, gt: Tensor, tag: str = "train/render_gt_error") -> None:
        """The render, the ground truth and 4x their error side by side ([H, 3W, 3])."""
        err = (img - gt).abs().mean(-1, keepdim=True).expand(-1, -1, 3)
        grid = torch.cat([img.clamp(0, 1), gt, (err * 4).clamp(0, 1)], 1)
        with writing(self.dir, "tensorboard"):
            self.open().add_image(tag, grid, it, dataformats="HWC")


def _quiet_writer_thread() -> None:
    """TensorBoard's writer thread re-raises a fault of the disk (full, `ulimit -f`, read-only),
    which Python prints as a traceback; the same fault surfaces at RunLog's next call as one line
    naming run_dir/tb. So such a fault of that thread is not printed (threading.excepthook,
    wrapped once; everything else is printed as before)."""
    import threading
    from tensorboard.summary.writer.event_file_writer import _AsyncWriterThread
    if getattr(threading.excepthook, "_quiets_disk_faults", False):
        return
    printed = threading.excepthook

    def hook(args):
        if isinstance(args.thread, _AsyncWriterThread) and io_cause(args.exc_value) is not None:
            return
        printed(args)

    hook._quiets_disk_faults = True
    threading.excepthook = hook


@dataclass
class RunState:
    """A run's state (module docstring). `model` is the `DynamicGaussians` being trained;
    `make_optimizers` rebuilds the per-Gaussian optimizers from the model's current parameters
    (the trainer's learning-rate schedule; None for a loaded state)."""

    model: Any
    run_dir: Path
    guard: Optional[Guard] = None  # None: a loaded run from before the guard
    optimizers: dict[str, torch.optim.Optimizer] = field(default_factory=dict)
    net_opt: Optional[torch.optim.Optimizer] = None
    strategy_state: dict[str, Any] = field(default_factory=dict)
    sampler: Optional[CameraSampler] = None
    train_seconds: float = 0.0
    # the process's CPU seconds over the same steps (every thread): train_cpu_seconds / (train_seconds x
    # threads) near 1 says the steps had the cores to themselves; well below, the machine was shared.
    # None: unknown (resumed from a checkpoint from before it was recorded)
    train_cpu_seconds: Optional[float] = 0.0
    train_threads: Optional[int] = None  # torch threads of the training (a live state: this process's)
    train_loss: Optional[str] = None     # the photometric loss's form: "compiled" | "torch"
    history: list[dict[str, Any]] = field(default_factory=list)    # evaluations: the learning curve
    prune_log: list[dict[str, Any]] = field(default_factory=list)  # stdr.densify.prune.prune_event's records
    # resumes with changed keys (train.resume=override): config.yaml's config_changes (stdr.train.resume)
    config_changes: list[dict[str, Any]] = field(default_factory=list)
    make_optimizers: Optional[Callable[[], dict[str, torch.optim.Optimizer]]] = None
    # the checkpoint this state was last saved to or loaded from ({"step", "sha256"},
    # stdr.io.checkpoint.checkpoint_identity): the source every result of the run records
    checkpoint_id: Optional[dict[str, Any]] = None

    @property
    def step(self) -> int:
        """Iterations trained (the model's)."""
        return self.model.step

    @property
    def checkpoint_path(self) -> Path:
        return Path(self.run_dir) / CKPT

    def network_params(self) -> list[tuple[str, Tensor]]:
        """(group name, parameter) of every network the run trains (the deformation's, the plug-ins')."""
        if self.net_opt is None:
            return []
        return [(g.get("name", "network"), p) for g in self.net_opt.param_groups for p in g["params"]]

    def zero_grads(self) -> None:
        clear_grads([*self.optimizers.values(), *([self.net_opt] if self.net_opt is not None else [])])

    def payload(self) -> dict[str, Any]:
        """The checkpoint: the model's own entry (enough to render it: `stdr.model.load_model`)
        and the state of the optimization, so a resumed run repeats the uninterrupted one exactly."""
        return {
            "model": self.model.state_dict(),
            "optimizers": {k: o.state_dict() for k, o in self.optimizers.items()},
            "net_opt": self.net_opt.state_dict(),
            "strategy_state": self.strategy_state,
            "sampler": self.sampler.state_dict(),
            "rng": rng_state(),
            "train_seconds": self.train_seconds,
            "train_cpu_seconds": self.train_cpu_seconds,
            "train_threads": self.train_threads if self.train_threads is not None else torch.get_num_threads(),
            "train_loss": self.train_loss,
            "history": self.history,
            "guard": (self.guard or Guard()).state_dict(),
            "prune_log": self.prune_log,
        }

    def save(self) -> None:
        """checkpoints/last.pt (atomic, checksummed; the one it replaces is kept as last.previous.pt)."""
        self.checkpoint_id = save_checkpoint(self.checkpoint_path, self.payload(), keep_previous=True)

    def restore(self, ck: dict[str, Any], where: str) -> None:
        """Back to a payload's state (a checkpoint file's, or a guard snapshot's): the model, the
        optimizers (rebuilt for its parameters), the strategy, the sampler, every RNG and the records.
        The guard's own state is the caller's (a resume loads it; a recovery keeps its own)."""

        self.model.load_state_dict(model_entry(ck, where), where)
        self.train_seconds = float(ck["train_seconds"])
        cpu = ck.get("train_cpu_seconds")  # None: a checkpoint from before it was recorded (unknown from then on)
        self.train_cpu_seconds = None if cpu is None else float(cpu)
        self.history = list(ck.get("history", []))
        self.prune_log = list(ck.get("prune_log", []))
        self.optimizers = self.make_optimizers()
        for k, o in self.optimizers.items():
            o.load_state_dict(ck["optimizers"][k])
        self.net_opt.load_state_dict(ck["net_opt"])
        dev = self.model.device
        self.strategy_state = {k: v.to(dev) if torch.is_tensor(v) else v for k, v in ck["strategy_state"].items()}
        self.sampler.load_state_dict(ck["sampler"])
        set_rng_state(ck["rng"])

    @classmethod
    def from_checkpoint(cls, ck: dict[str, Any], model, run_dir: str | Path) -> "RunState":
        """A saved run's state for reporting and evaluating it (stdr-eval): its records as the
        checkpoint holds them, no optimizers. `history` is the run's history.json when it has one
        (it also holds the evaluations made after the last checkpoint), else the checkpoint's."""
        run_dir = Path(run_dir)
        history = list(ck.get("history", []))
        hp = run_dir / "history.json"
        if hp.is_file():
            try:
                history = list(json.loads(hp.read_text()))
            except (OSError, ValueError) as e:
                raise ValueError(f"{hp}: not a readable learning curve ({e}); delete it to re-evaluate from the "
                                 "checkpoint's own record") from None
        cpu = ck.get("train_cpu_seconds")
        return cls(model=model, run_dir=run_dir,
                   guard=Guard.from_state(ck["guard"]) if "guard" in ck else None,
                   train_seconds=float(ck.get("train_seconds") or 0.0),
                   train_cpu_seconds=None if cpu is None else float(cpu),
                   train_threads=ck.get("train_threads"), train_loss=ck.get("train_loss"),
                   history=history, prune_log=list(ck.get("prune_log", [])),
                   strategy_state=dict(ck.get("strategy_state") or {}),
                   checkpoint_id=checkpoint_identity(run_dir / CKPT))
