"""stdr-eval RUN_DIR [RUN_DIR ...] [overrides]: re-evaluate runs and print/write the table.

reevaluate=false tabulates the runs' metrics.json as they are; remeasure=fps re-times only the
render FPS (quality numbers untouched, the old value kept in `fps_history`); remeasure=size adds
model_mb to runs evaluated before it was recorded. `render.<key>=...` and `<plug-in>.<key>=...`
change those keys of each run's config for the evaluation."""
from __future__ import annotations

import contextlib
import os
import sys
from pathlib import Path

import hydra
import torch
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from ..config import CONFIG_DIR

from ..store import CHANGES_KEY, load_config
from ..io.files import read_json, read_yaml
from ..io.files import run_lock
from ..store import register
from ..errors import BadInput, MissingInput, reported
from .common import check_overrides, reproducible_blas, run_hydra_app
from ..eval.table import check_mixed_rows, collect, find_run_dirs, markdown, read_metrics, table_row, write_tables
from ..eval.evaluate import code_version, evaluate_run, measure_fps, save_metrics, machine_name
from ..train.state import RunState
from ..data.load import load_run_scene
from ..device import resolve_device
from ..model import has_model_entry, model_from_checkpoint, model_bytes
from ..io.checkpoint import load_checkpoint, CKPT
from ..plugins import registered_plugins


def evaluate_dirs(runs: list[str], split: str | None, eval_cfg, render_cfg, reevaluate: bool,
                  out_dir: Path, base: str, device: str | None = None, remeasure: str | None = None,
                  plugin_overrides: dict | None = None, unfinished: bool = False, allow_mixed: bool = False) -> dict:
    """plugin_overrides: {plug-in name: its keys to change in each run's config (null: keep)}.
    A run that has not finished is refused (nothing is written into it); unfinished=True
    evaluates its last checkpoint into out_dir/unfinished/<its folder's name>/. Re-evaluating a
    run writes into it, under its lock (stdr.io.files). A row whose runs differ in iterations,
    budget or code is refused unless allow_mixed (stdr.eval.table.check_mixed_rows)."""


    if remeasure not in (None, "fps", "size", "fps+size"):
        raise BadInput(f"remeasure={remeasure!r}: what can be redone alone is 'fps' (re-time the renders), "
                         "'size' (model_mb from the checkpoint, for runs from before it was recorded) or 'fps+size'")
    if remeasure and reevaluate:
        reevaluate = False  # remeasure=fps re-times the renders and keeps every quality number
    rows, plan = [], []
    # first every check that can refuse, on every run, before anything is written into any of them:
    # a folder of runs (a sweep's multirun folder) stands for the finished runs under it
    for rd in find_run_dirs([Path(r) if Path(r).is_absolute() else Path(base) / r for r in runs]):
        cfg_path = rd / "config.yaml"
        cfg = load_config(cfg_path)
        sp = split or cfg.data.eval_split
        if reevaluate or remeasure:
            apply_overrides(cfg, "render", render_cfg)
            for name, ov in (plugin_overrides or {}).items():
                apply_overrides(cfg, name, ov)
            if device is not None:  # e.g. a run trained on a GPU, re-evaluated on a CPU machine
                cfg.device = device
        left = unfinished_at(rd, cfg)
        if left is not None and not unfinished:
            raise BadInput(f"{rd} has not finished: its checkpoint is at iteration {left} of {cfg.optim.iterations} "
                           "and it has no final evaluation, so stdr-eval writes nothing into it. Resume it with "
                           "the stdr-train command that started it, or add unfinished=true to evaluate its last "
                           f"checkpoint into {out_dir / 'unfinished' / rd.name}")
        plan.append((rd, cfg, sp, left))
    # the rows as they will be (a re-evaluation stamps this code; iterations are the checkpoint's), checked
    # for mixed training before any run is written into
    now = code_version()
    check_mixed_rows([table_row(OmegaConf.to_container(cfg, resolve=True), sp,
                                {"iterations": int(cfg.optim.iterations) if left is None else left, "code": now}
                                if (reevaluate or left is not None) else read_metrics(rd, sp), str(rd))
                      for rd, cfg, sp, left in plan], allow_mixed)
    with contextlib.ExitStack() as locks:
        for rd, cfg, sp, left in plan:  # every run written into is held before the first is (one writer a run)
            if left is None and (reevaluate or remeasure):
                locks.enter_context(run_lock(rd, "stdr-eval"))
        for rd, cfg, sp, left in plan:
            if left is not None:  # its last checkpoint, evaluated outside the run
                res = reevaluate_run(rd, cfg, sp, eval_cfg, base, into=out_dir / "unfinished" / rd.name)
            elif reevaluate:  # it writes metrics.json, history.json and renders into the run
                res = reevaluate_run(rd, cfg, sp, eval_cfg, base)
            elif remeasure:
                res = remeasure_run(rd, cfg, sp, eval_cfg, base, remeasure.split("+"))
            else:
                res = read_metrics(rd, sp)
            rows.append(table_row(OmegaConf.to_container(cfg, resolve=True), sp, res, str(rd)))
    table = collect(check_mixed_rows(rows, allow_mixed))
    paths = write_tables(table, out_dir)
    print(markdown(table))
    print(f"[stdr] tables: {', '.join(str(p) for p in paths.values())}")
    return table


def unfinished_at(rd: Path, cfg) -> int | None:
    """The iteration of the run's last checkpoint when it is before optim.iterations (the run has
    not finished: stopped by train.stop_at or a deadline, killed, or still training), else None."""
    done = rd / "metrics.json"
    if done.is_file():  # finished and evaluated at optim.iterations: no need to read the checkpoint
        try:
            entries = read_json(done, "metrics")
        except BadInput:  # damaged: the checkpoint says whether the run finished (a re-evaluation rewrites it)
            entries = {}
        its = [e.get("iterations") for e in entries.values() if isinstance(e, dict)] if isinstance(entries, dict) else []
        if its and all(isinstance(i, int) and i >= int(cfg.optim.iterations) for i in its):
            return None
    ck = rd / CKPT
    if not ck.is_file():
        if (rd / "metrics.json").is_file():
            return None  # evaluated, its checkpoint moved away: tabulated from metrics.json as it is
        raise MissingInput(f"{rd} has neither {CKPT} nor metrics.json: it has not trained a step (or its files "
                           "were moved); train it with stdr-train first")
    step = int(load_checkpoint(ck).get("model", {}).get("step", 0))
    return step if step < int(cfg.optim.iterations) else None


def reevaluate_run(rd: Path, cfg, split: str, eval_cfg, base: str, into: Path | None = None) -> dict:
    """Load the run's state from its checkpoint (its model through the public API, stdr.model),
    and evaluate it as stdr-train does (stdr.eval.evaluate.evaluate_run: render `split`, merge the
    numbers into its metrics.json). into: write metrics.json, history.json and the renders
    there instead of into the run."""

    ck, model, scene = _load_for_eval(rd, cfg, split, base)
    state = RunState.from_checkpoint(ck, model, rd)
    state.config_changes = list((read_yaml(rd / "config.yaml") or {}).get(CHANGES_KEY) or [])
    if into is not None:
        into.mkdir(parents=True, exist_ok=True)
        state.run_dir = into
    before = _entry(Path(state.run_dir) / "metrics.json", split)
    busy = machine_load()
    if busy:
        print(f"[stdr] {rd}: {busy}: the FPS measured now is not comparable with one taken on an idle machine; "
              "metrics.json keeps the training-time FPS as fps_at_training", flush=True)
    res = evaluate_run(state, scene, split, eval_cfg, max_gaussians=cfg.densify.max_gaussians)
    kept = before.get("fps_at_training", before.get("fps"))
    if kept is not None:  # the FPS timed when the run finished training stays beside the new timing
        res["fps_at_training"] = kept
        mp = Path(state.run_dir) / "metrics.json"
        metrics = read_json(mp, "metrics")
        metrics[split]["fps_at_training"] = kept
        save_metrics(mp, metrics)
    return res


def _entry(path: Path, split: str) -> dict:
    """metrics.json[split] as it is now ({} when there is none or it cannot be read)."""
    try:
        m = read_json(path, "metrics") if path.is_file() else {}
    except BadInput:
        return {}
    e = m.get(split) if isinstance(m, dict) else None
    return e if isinstance(e, dict) else {}


def machine_load() -> str:
    """'load L on N cores' when other work keeps more than half of this machine's cores busy (the
    1-minute load average, measured before this process renders anything), else ''."""
    try:
        load = os.getloadavg()[0]
    except OSError:
        return ""
    cores = os.cpu_count() or 1
    return f"the machine is busy (load {load:.1f} on {cores} cores)" if load > 0.5 * cores else ""


def apply_overrides(cfg, section: str, overrides) -> None:
    """Set the keys of `section` (e.g. render) given on the command line (non-null) in a run's
    config; the run keeps its own value of every other key (e.g. render.antialiased)."""
    if overrides is None:
        return
    items = overrides.items() if isinstance(overrides, dict) else OmegaConf.to_container(overrides).items()
    for k, v in items:
        if v is not None:
            cfg[section][k] = v


def _load_for_eval(rd: Path, cfg, split: str, base: str):
    """(model, scene) of a run folder for rendering `split`: the model from its checkpoint."""

    ck = load_checkpoint(rd / CKPT)
    dev = resolve_device(cfg.device)
    # a checkpoint from before format 2 does not hold the training times: read them from the data
    splits = (split,) if has_model_entry(ck) else tuple(dict.fromkeys(("train", split)))
    scene = load_run_scene(rd, cfg, splits, base=base, seed=cfg.seed).to(dev)  # the data it trained on
    model = model_from_checkpoint(ck, dev, cfg, None if has_model_entry(ck) else scene.train_times(), str(rd / CKPT))
    return ck, model, scene


def remeasure_run(rd: Path, cfg, split: str, eval_cfg, base: str, what: list[str]) -> dict:
    """Redo some measurements of a run's `split` and update metrics.json[split]; every other
    number stays as it was. Returns the updated entry.

    fps: re-time the renders; `fps` becomes the new value and the entry it replaces is appended
    to `fps_history` with where it was measured. size: `model_mb` from the checkpoint's model
    (the tensors a saved model holds), for runs evaluated before it was recorded."""


    mp = rd / "metrics.json"
    if not mp.is_file():
        raise MissingInput(f"{mp} not found: remeasure updates an evaluated run; evaluate it first")
    metrics = read_json(mp, "metrics")
    if split not in metrics:
        raise KeyError(f"{mp} has no split {split!r} (it has {sorted(metrics)}): evaluate that split first")
    _, model, scene = _load_for_eval(rd, cfg, split, base)
    entry = metrics[split]
    if "size" in what:
        entry["model_mb"] = model_bytes(model) / 2 ** 20
    if "fps" in what:
        timing = measure_fps(model, scene.frames(split), fps_warmup=eval_cfg.fps_warmup,
                             fps_repeats=eval_cfg.fps_repeats)
        _refresh_fps(entry, timing, model, rd)
    save_metrics(mp, metrics)
    return entry


def _refresh_fps(entry: dict, timing: dict, model, rd: Path) -> None:
    """Put a new timing (measure_fps) in `entry`: fps, its passes, and the rows rendered per frame
    under the render settings it ran with (render.cull may differ from the run's); the replaced
    values go to fps_history."""

    conv = entry.get("conventions", {})
    entry.setdefault("fps_history", []).append(
        {"fps": entry.get("fps"), "fps_passes": entry.get("fps_passes"), "machine": conv.get("machine"),
         "torch_threads": conv.get("torch_threads"), "render_backend": conv.get("render_backend"),
         "device": conv.get("device"), "render_cull": conv.get("fps_render_cull", entry.get("render_cull")),
         "active_gaussians_mean": entry.get("active_gaussians_mean")})
    entry.update(timing)
    fps = timing["fps"]
    entry.setdefault("conventions", {}).update(
        {"fps_remeasured": True, "fps_machine": machine_name(), "fps_torch_threads": torch.get_num_threads(),
         "fps_render_backend": model.backend, "fps_device": str(model.device),
         "fps_render_cull": model.cull_mode()})
    print(f"[stdr] {rd}: FPS {entry['fps_history'][-1]['fps']} -> {fps:.2f}")


@hydra.main(version_base=None, config_path=str(CONFIG_DIR), config_name="eval")
def _main(cfg: DictConfig) -> None:
    if not cfg.runs:
        raise SystemExit("usage: stdr-eval RUN_DIR [RUN_DIR ...] [key=value ...]")
    reproducible_blas()
    # out= is read from where the command was typed (hydra.job.chdir=true moves the working folder)
    # and printed absolute, so the path printed is where the tables are
    cwd = Path(hydra.utils.get_original_cwd())
    out = (cwd / Path(cfg.out).expanduser()).resolve() if cfg.out else Path(HydraConfig.get().runtime.output_dir).resolve()
    with reported("stdr-eval"):  # bad input: one line, exit code 2
        evaluate_dirs(list(cfg.runs), cfg.split, cfg.eval, cfg.render, cfg.reevaluate, out,
                      hydra.utils.get_original_cwd(), cfg.device, cfg.remeasure,
                      {s.name: cfg.get(s.name) for s in registered_plugins()}, cfg.unfinished, cfg.allow_mixed)


def main() -> None:
    """Turn positional run folders into the `runs=[...]` override, then hand over to Hydra."""
    args, runs = [sys.argv[0]], []
    for a in sys.argv[1:]:
        if not a.startswith("-") and "=" not in a:
            runs.append(a)
        else:
            args.append(a)
    if runs:
        quoted = ",".join("'" + r.replace("'", "\\'") + "'" for r in runs)
        args.append(f"runs=[{quoted}]")
    sys.argv = args
    with reported("stdr-eval"):  # a wrongly declared baseline or plug-in of an installed package: one line
        register()
    check_overrides("stdr-eval", args[1:], "eval")  # a bad override: one line, exit code 2
    run_hydra_app("stdr-eval", _main)


if __name__ == "__main__":
    main()
