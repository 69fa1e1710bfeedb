"""`hydra/sweeper=stdr_queue`: the pending runs of a queue file (`stdr-tool queue plan`), one job
each, handed to whichever launcher the sweep uses (`local`: joblib on this machine; `slurm`:
submitit), in the queue's order.

    stdr-train -m hydra/sweeper=stdr_queue hydra.sweeper.queue=Q.json hydra.sweep.dir=WORK \
        hydra/launcher=local hydra.launcher.n_jobs=16 train.threads=1 [hydra.sweeper.deadline=UNIX_TIME]

Job i runs `<run's overrides> <the command line's overrides> hydra.sweep.subdir=<run id>`, so a run
lands in WORK/<run id> whatever the launcher. With a deadline every job gets `train.deadline` (it
checkpoints and stops there) and `train.start_by` = deadline - the run's estimate (a job that would
begin later is not started). The sweeper only chooses jobs; it reads the queue file and never
writes it: `stdr-tool queue run` books the results (stdr.tools.runqueue).
"""

# (no `from __future__ import annotations`: Hydra imports its plugins without registering the module,
# which dataclasses then need to resolve string annotations)
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, List, Optional

from hydra.core.config_store import ConfigStore
from hydra.plugins.launcher import Launcher
from hydra.plugins.sweeper import Sweeper
from hydra.types import HydraContext, TaskFunction
from omegaconf import DictConfig, OmegaConf

#: a run of these states is launched: `running` is what a killed call left behind
LAUNCHED = ("pending", "running")


@dataclass
class QueueSweeperConf:
    _target_: str = "hydra_plugins.stdr_queue.queue_sweeper.QueueSweeper"
    queue: str = "???"                # the queue file (stdr-tool queue plan)
    deadline: Optional[float] = None  # Unix time: train.deadline and train.start_by of every job
    isolate: bool = True              # each job trains in a child process of its own (stdr.cli.train)
    # that process's command before the overrides (default: python -m stdr.cli.train); {run_dir}: the job's folder
    command: Optional[List[str]] = None


ConfigStore.instance().store(group="hydra/sweeper", name="stdr_queue", node=QueueSweeperConf, provider="stdr")


def job_overrides(runs: List[dict], arguments: List[str], deadline: Optional[float]) -> List[List[str]]:
    """One override list per run: its own overrides, then the command line's (they win), then where
    it lands and when it must stop."""
    jobs = []
    for r in runs:
        when = [] if deadline is None else [f"train.deadline={deadline:.3f}",
                                            f"train.start_by={deadline - float(r['est_s']):.3f}"]
        jobs.append([*r["overrides"], *arguments, f"hydra.sweep.subdir={r['id']}", *when])
    return jobs


class QueueSweeper(Sweeper):
    # isolate and command are read by each job from its own config (hydra.sweeper), not here
    def __init__(self, queue: str, deadline: Optional[float] = None, isolate: bool = True,
                 command: Optional[List[str]] = None) -> None:
        self.queue, self.deadline = Path(queue), deadline
        self.config: Optional[DictConfig] = None
        self.launcher: Optional[Launcher] = None
        self.hydra_context: Optional[HydraContext] = None

    def setup(self, *, hydra_context: HydraContext, task_function: TaskFunction, config: DictConfig) -> None:
        from hydra.core.plugins import Plugins
        self.config, self.hydra_context = config, hydra_context
        self.launcher = Plugins.instance().instantiate_launcher(
            hydra_context=hydra_context, task_function=task_function, config=config)

    def sweep(self, arguments: List[str]) -> Any:
        assert self.config is not None and self.launcher is not None
        if not self.queue.is_file():
            raise FileNotFoundError(f"hydra.sweeper.queue={self.queue}: no such queue file (stdr-tool queue plan makes one)")
        runs = [r for r in json.loads(self.queue.read_text())["runs"] if r["state"] in LAUNCHED]
        sweep_dir = Path(self.config.hydra.sweep.dir)
        sweep_dir.mkdir(parents=True, exist_ok=True)
        OmegaConf.save(self.config, sweep_dir / "multirun.yaml")
        jobs = job_overrides(runs, list(arguments), self.deadline)
        jobs = [job for r, job in zip(runs, jobs) if self._composes(r["id"], job, sweep_dir)]
        if not jobs:
            return []
        return self.launcher.launch(jobs, initial_job_idx=0)

    def _composes(self, run_id: str, job: List[str], sweep_dir: Path) -> bool:
        """Whether the job's config composes. One that does not (an unknown key, a missing experiment)
        is recorded in <sweep dir>/failures.jsonl like a job that failed, and not launched: the
        launcher's workers would stop the whole sweep on it."""
        assert self.hydra_context is not None and self.config is not None
        try:
            self.hydra_context.config_loader.load_sweep_config(self.config, list(job))
            return True
        except Exception as e:  # noqa: BLE001 - recorded; the other jobs go on
            rec = {"overrides": job, "run_dir": str(sweep_dir / run_id), "log": None,
                   "error": f"{type(e).__name__}: {e}", "traceback": ""}
            with open(sweep_dir / "failures.jsonl", "a") as f:  # stdr.tools.runqueue.FAILURES (no stdr import here)
                f.write(json.dumps(rec) + "\n")
            print(f"[stdr] FAILED {run_id}: its config does not compose: {rec['error']}", flush=True)
            return False
