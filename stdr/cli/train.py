"""stdr-train: train one model (Hydra app). `stdr-train --help` lists the config groups."""
from __future__ import annotations

import contextlib
import json
import shlex
import shutil
import subprocess
import sys
import time
import traceback
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.core.override_parser.overrides_parser import OverridesParser
from omegaconf import DictConfig

from ..config import CONFIG_DIR
from ..store import register
from ..errors import UserError, reported
from ..eval.table import stale_results
from ..io.files import LOCK_NAME, read_json, write_atomic
from ..tools.runqueue import FAILURES, STDOUT
from ..train.resume import StopNow
from ..train.run import run_training
from .common import check_overrides, reproducible_blas, run_hydra_app, use_fast_allocator_hint
from .sweep import LAST_SWEEP


POLL_S = 10.0  # seconds between looks at a sweep folder's pause files


def _wait_while_paused(sweep_dir: Path) -> None:
    """Hold the job while <sweep dir>/pause or any pause.<name> exists (yours, or another study's
    that wants the machine first): the run in progress finishes, the next one waits."""
    said = False
    while any(sweep_dir.glob("pause*")):
        if not said:
            print(f"[stdr] {time.strftime('%T')} paused ({' '.join(p.name for p in sweep_dir.glob('pause*'))})",
                  flush=True)
            said = True
        time.sleep(POLL_S)


def _in_own_process(hc, run_dir: Path, data_base: str) -> None:
    """The job's run as `stdr-train <the job's overrides> hydra.run.dir=<its folder>` in a child
    process (hydra.sweeper.isolate: stdr_queue): a crash or a broken CUDA context ends that run
    alone, not the launcher's worker and the jobs after it. Its output: <run folder>/stdout.log.
    hydra.sweeper.command replaces `python -m stdr.cli.train` (another checkout's stdr-train, a
    wrapper such as scripts/idle_run.py); `{run_dir}` in it is the job's folder."""
    _wait_while_paused(Path(hc.sweep.dir))
    prefix = [str(a).replace("{run_dir}", str(run_dir)) for a in (hc.sweeper.get("command") or [])]
    cmd = [*(prefix or [sys.executable, "-m", "stdr.cli.train"]), *hc.overrides.task, f"hydra.run.dir={run_dir}"]
    run_dir.mkdir(parents=True, exist_ok=True)
    with open(run_dir / STDOUT, "a") as log:
        log.write("$ " + shlex.join(cmd) + "\n")
        log.flush()
        rc = subprocess.run(cmd, stdout=log, stderr=subprocess.STDOUT, cwd=data_base).returncode
    if rc != 0:
        last = (run_dir / STDOUT).read_text(errors="replace").strip().splitlines()[-1:]
        raise RuntimeError(f"exit {rc}: {last[0] if last else 'no output'}")


def sweep_job(cfg: DictConfig, run_dir: Path, data_base: str) -> dict | None:
    """One job of a sweep (stdr-train -m): skipped when finished (train.skip_finished and
    metrics.json present); a failure is recorded in <sweep dir>/failures.jsonl with the job's
    overrides and log, printed, and does not stop the other jobs (SweepReport sums them up)."""
    hc = HydraConfig.get()
    if cfg.train.skip_finished and (run_dir / "metrics.json").is_file():
        stale = _stale_metrics(run_dir)
        if not stale:
            print(f"[stdr] skipping finished run {run_dir} (metrics.json present; train.skip_finished=false reruns it)")
            return None
        print(f"[stdr] {stale}; not skipped as finished", flush=True)
    isolate = bool(hc.sweeper.get("isolate", False))
    try:
        if isolate:
            return _in_own_process(hc, run_dir, data_base)
        return run_training(cfg, run_dir, data_base=data_base)
    except Exception as e:  # noqa: BLE001 - reported, the sweep goes on
        log = run_dir / (STDOUT if isolate else f"{hc.job.name}.log")
        rec = {"overrides": list(hc.overrides.task), "run_dir": str(run_dir), "log": str(log),
               "error": f"{type(e).__name__}: {e}", "traceback": traceback.format_exc()}
        sweep_dir = Path(hc.sweep.dir)
        sweep_dir.mkdir(parents=True, exist_ok=True)
        with open(sweep_dir / FAILURES, "a") as f:
            f.write(json.dumps(rec) + "\n")
        print(f"[stdr] FAILED {' '.join(rec['overrides'])}: {rec['error']} (log: {log})", flush=True)
        return None


def _stale_metrics(run_dir: Path) -> str:
    """Why run_dir's metrics.json is not its last checkpoint's ("" when it is, or cannot tell)."""
    try:
        metrics = read_json(run_dir / "metrics.json", "metrics")
    except UserError:
        return f"{run_dir / 'metrics.json'} is damaged"
    for entry in (metrics.values() if isinstance(metrics, dict) else []):
        why = stale_results(run_dir, entry)
        if why:
            return why
    return ""


@hydra.main(version_base=None, config_path=str(CONFIG_DIR), config_name="train")
def _main(cfg: DictConfig) -> None:
    from hydra.types import RunMode
    use_fast_allocator_hint()
    reproducible_blas()
    run_dir = Path(HydraConfig.get().runtime.output_dir)
    if HydraConfig.get().mode == RunMode.MULTIRUN:
        sweep_job(cfg, run_dir, hydra.utils.get_original_cwd())
    else:
        with reported("stdr-train"):  # bad input: one line, exit code 2
            try:
                run_training(cfg, run_dir, data_base=hydra.utils.get_original_cwd())
            except UserError:
                _restore_hydra_record(run_dir)  # a refused command leaves the run's record as it was
                _remove_if_untouched(run_dir, Path(hydra.utils.get_original_cwd()))
                raise


#: a sweep of more runs than this is announced before Hydra composes them (that alone takes minutes)
BIG_SWEEP = 1000


def sweep_size(argv: list[str]) -> tuple[int, list[str]]:
    """(the number of runs a `-m` command line sweeps: the product of its sweep overrides' lengths,
    each sweep override with its length)."""
    total, parts = 1, []
    try:
        parsed = OverridesParser.create().parse_overrides([a for a in argv if not a.startswith("-") and "=" in a])
    except Exception:  # noqa: BLE001 - Hydra reports a bad override itself
        return 1, []
    for o in parsed:
        if o.is_sweep_override() and not o.key_or_group.startswith("hydra"):
            n = sum(1 for _ in o.sweep_iterator())
            total *= n
            parts.append(f"{o.input_line} ({n:,})")
    return total, parts


def _say_sweep_size(argv: list[str]) -> None:
    total, parts = sweep_size(argv)
    if total > BIG_SWEEP:
        print(f"[stdr] this sweep is {total:,} runs ({' x '.join(parts)}); composing them takes a while before the "
              "first starts. Ctrl+C stops it", flush=True)


#: what Hydra writes into a run folder before stdr-train's checks (and the lock file)
_HYDRA_ONLY = (".hydra", ".stdr.lock")


def _remove_if_untouched(run_dir: Path, cwd: Path) -> None:
    """A refused command leaves no folder: the run folder is removed when it holds nothing but
    what Hydra made before the config was checked (.hydra/, an empty <job>.log, the empty lock),
    then each parent it made that is now empty, up to the working folder."""
    if not run_dir.is_dir():
        return
    log = f"{HydraConfig.get().job.name}.log"
    for p in run_dir.iterdir():
        if p.name not in _HYDRA_ONLY and not (p.name == log and p.stat().st_size == 0):
            return  # a run's files: not this command's to remove
        if p.name == LOCK_NAME and p.stat().st_size:
            return
    if run_dir.resolve() in _EXISTED:  # the user's folder: only what Hydra put into it goes
        for p in run_dir.iterdir():
            shutil.rmtree(p, ignore_errors=True) if p.is_dir() else p.unlink(missing_ok=True)
        return
    shutil.rmtree(run_dir, ignore_errors=True)
    parent = run_dir.parent
    while (parent != cwd and cwd in parent.parents and parent.resolve() not in _EXISTED
           and not any(parent.iterdir())):
        parent.rmdir()
        parent = parent.parent


#: the folders on the way to the run folder that existed before this command (hydra.run.dir): a
#: refused command removes only what it made
_EXISTED: set[Path] = set()


#: the run folder's .hydra/ files before Hydra rewrote them for this command: {path: bytes}
_HYDRA_BEFORE: dict[Path, bytes] = {}


def _note_existing(argv: list[str]) -> None:
    _EXISTED.clear()
    _HYDRA_BEFORE.clear()
    given = [a.split("=", 1)[1] for a in argv if a.startswith("hydra.run.dir=")]
    if not given:
        return
    try:  # a path the command cannot use (too long, not ours to read) is named by the command itself
        d = Path(given[-1]).expanduser().resolve()
        for f in (d, *d.parents):
            if f.is_dir():
                _EXISTED.add(f)
        if (d / ".hydra").is_dir():
            _HYDRA_BEFORE.update({f: f.read_bytes() for f in (d / ".hydra").iterdir() if f.is_file()})
    except OSError:
        pass


def _restore_hydra_record(run_dir: Path) -> None:
    """Put back the .hydra/ files (Hydra's record of the command: config.yaml, overrides.yaml) that
    Hydra rewrote for a command that was then refused (a resume with changed keys)."""
    for f, data in _HYDRA_BEFORE.items():
        if f.parent.parent == run_dir.resolve():
            with contextlib.suppress(OSError):
                write_atomic(f, data, site="config")


def main() -> None:
    """stdr-train. `--cfg job` prints the config with its derived `schedule` resolved (Hydra's
    --resolve is added), so the printed config shows every phase boundary of the run. A sweep
    (-m) with failed jobs exits 1 after listing them (stdr.cli.sweep.SweepReport)."""
    if "--cfg" in sys.argv or "-c" in sys.argv:
        if "--resolve" not in sys.argv:
            sys.argv.append("--resolve")
    with reported("stdr-train"):  # a wrongly declared baseline or plug-in of an installed package: one line
        register()
    check_overrides("stdr-train", sys.argv[1:])  # a bad override: one line, exit code 2
    if "-m" in sys.argv[1:] or "--multirun" in sys.argv[1:]:
        _say_sweep_size(sys.argv[1:])
    LAST_SWEEP["failed"] = 0
    _note_existing(sys.argv[1:])
    try:
        run_hydra_app("stdr-train", _main)
    except KeyboardInterrupt as e:  # before training holds Ctrl+C, or a second one while it stops
        again = isinstance(e, StopNow)
        print("[stdr] Ctrl+C again: stopped without a checkpoint of the step in progress; the same command resumes "
              "from the last checkpoint written" if again else
              "[stdr] Ctrl+C: stopped outside the training steps; the same command goes on from the last checkpoint "
              "written, if there is one", flush=True)
        raise SystemExit(130) from None
    if LAST_SWEEP["failed"]:
        raise SystemExit(1)


if __name__ == "__main__":
    main()
