"""stdr-eval RUN_DIR [RUN_DIR ...] [overrides]: re-evaluate runs and print/write the table.

reevaluate=false tabulates the runs' metrics.json as they are; remeasure=fps re-times only the
render FPS (quality numbers untouched, the old value kept in `fps_history`); remeasure=size adds
model_mb to runs evaluated before it was recorded. `render.<key>=...` and `<plug-in>.<key>=...`
change those keys of each run's config for the evaluation."""
from __future__ import annotations

import sys
from pathlib import Path

import hydra
import torch
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from ..config import CONFIG_DIR, load_config
from ..store import register
from ..errors import BadInput, MissingInput, reported
from .common import check_overrides, reproducible_blas
from ..eval.table import collect, find_run_dirs, markdown, table_row, write_tables
from ..eval.evaluate import evaluate_run, measure_fps, save_metrics, machine_name
from ..train.state import RunState
from ..data.load import load_scene
from ..device import resolve_device
from ..model import has_model_entry, model_from_checkpoint, model_bytes
from ..io.checkpoint import load_checkpoint, CKPT
from ..plugins import registered_plugins

register()


def evaluate_dirs(runs: list[str], split: str | None, eval_cfg, render_cfg, reevaluate: bool,
                  out_dir: Path, base: str, device: str | None = None, remeasure: str | None = None,
                  plugin_overrides: dict | None = None) -> dict:
    """plugin_overrides: {plug-in name: its keys to change in each run's config (null: keep)}."""
    import json


    if remeasure not in (None, "fps", "size", "fps+size"):
        raise BadInput(f"remeasure={remeasure!r}: what can be redone alone is 'fps' (re-time the renders), "
                         "'size' (model_mb from the checkpoint, for runs from before it was recorded) or 'fps+size'")
    if remeasure and reevaluate:
        reevaluate = False  # remeasure=fps re-times the renders and keeps every quality number
    rows = []
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
        if reevaluate:
            res = reevaluate_run(rd, cfg, sp, eval_cfg, base)
        elif remeasure:
            res = remeasure_run(rd, cfg, sp, eval_cfg, base, remeasure.split("+"))
        else:
            mp = rd / "metrics.json"
            if not mp.is_file():
                raise MissingInput(f"{mp} not found: run stdr-eval without reevaluate=false")
            res = json.loads(mp.read_text()).get(sp)
            if res is None:
                raise KeyError(f"{mp} has no split {sp!r}")
        rows.append(table_row(OmegaConf.to_container(cfg, resolve=True), sp, res, str(rd)))
    table = collect(rows)
    paths = write_tables(table, out_dir)
    print(markdown(table))
    print(f"[stdr] tables: {', '.join(str(p) for p in paths.values())}")
    return table


def reevaluate_run(rd: Path, cfg, split: str, eval_cfg, base: str) -> dict:
    """Load the run's state from its checkpoint (its model through the public API, stdr.model),
    and evaluate it as stdr-train does (stdr.eval.evaluate.evaluate_run: render `split`, merge the
    numbers into its metrics.json)."""

    ck, model, scene = _load_for_eval(rd, cfg, split, base)
    state = RunState.from_checkpoint(ck, model, rd)
    return evaluate_run(state, scene, split, eval_cfg, max_gaussians=cfg.densify.max_gaussians)


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
    scene = load_scene(cfg.data, splits, base=base, seed=cfg.seed).to(dev)
    model = model_from_checkpoint(ck, dev, cfg, None if has_model_entry(ck) else scene.train_times(), str(rd / CKPT))
    return ck, model, scene


def remeasure_run(rd: Path, cfg, split: str, eval_cfg, base: str, what: list[str]) -> dict:
    """Redo some measurements of a run's `split` and update metrics.json[split]; every other
    number stays as it was. Returns the updated entry.

    fps: re-time the renders; `fps` becomes the new value and the entry it replaces is appended
    to `fps_history` with where it was measured. size: `model_mb` from the checkpoint's model
    (the tensors a saved model holds), for runs evaluated before it was recorded."""
    import json


    mp = rd / "metrics.json"
    if not mp.is_file():
        raise MissingInput(f"{mp} not found: remeasure updates an evaluated run; evaluate it first")
    metrics = json.loads(mp.read_text())
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
    out = Path(cfg.out) if cfg.out else Path(HydraConfig.get().runtime.output_dir)
    with reported("stdr-eval"):  # bad input: one line, exit code 2
        evaluate_dirs(list(cfg.runs), cfg.split, cfg.eval, cfg.render, cfg.reevaluate, out,
                      hydra.utils.get_original_cwd(), cfg.device, cfg.remeasure,
                      {s.name: cfg.get(s.name) for s in registered_plugins()})


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
    check_overrides("stdr-eval", args[1:], "eval")  # a bad override: one line, exit code 2
    _main()


if __name__ == "__main__":
    main()
