"""One training run of a composed config, start to end (`run_training`)."""
from __future__ import annotations

import os
import time
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from ..compact.pack import check_pack_config, pack, summary
from ..plugins import enabled_plugins
from ..store import CHANGES_KEY, run_name
from ..io.checkpoint import CKPT, load_checkpoint
from ..io.files import leftover_temporaries, write_atomic
from ..io.files import run_lock, set_aside_results
from ..device import resolve_device
from ..gaussians import check_init_fits
from ..data.load import pin_run_data, scene_folder
from ..eval.table import collect, markdown, table_row
from ..validate import check_run_config
from ..baselines.base import PRECISIONS, choose_precision
from ..baselines.registry import get_baseline
from .resume import resume_changes, saved_config
from .trainer import Trainer


def run_training(cfg: DictConfig, run_dir: Path, data_base: str | None = None) -> dict | None:
    """One training run of a composed config (stdr-train, each job of a sweep, stdr-tool compact):
    the config checked, run_dir/config.yaml written, trained, evaluated on data.eval_split, the
    compact file written when pack.enabled, and the result row printed. Returns the evaluation
    (None for a run stopped early by train.stop_at or train.deadline, or not started: train.start_by)."""
    check_run_config(cfg, data_base)  # keys, values and paths, before anything is written or trained
    cores = os.cpu_count() or 1
    if cfg.train.threads > cores:  # torch's threads then take turns on the cores: many times slower
        print(f"[stdr] train.threads={cfg.train.threads} on a machine with {cores} cores: more threads than cores "
              f"slow training down several times; train.threads=0 takes one per core", flush=True)
    check_init_fits(cfg.model, resolve_device(cfg.device))
    start_by = cfg.train.get("start_by")
    if start_by is not None and time.time() > start_by:
        print(f"[stdr] {run_dir}: not started, train.start_by passed {time.time() - start_by:.0f} s ago")
        return None
    with run_lock(run_dir, "stdr-train"):  # one writer per run folder (stdr.io.files)
        return _train_locked(cfg, run_dir, data_base)


def settle_precision(cfg: DictConfig, record: dict | None) -> str:
    """Resolve baseline.precision=auto in `cfg` before the run's record is written, so config.yaml
    and metrics.json name the arithmetic that trained: a resumed run keeps the precision its record
    names (exact resume, on any machine); a new one takes stdr.baselines.base.choose_precision's.
    Returns the one line to print (empty: nothing to say)."""
    requested = str(cfg.baseline.precision)
    recorded = ((record or {}).get("baseline") or {}).get("precision")
    if requested == "auto" and recorded in PRECISIONS:
        requested = recorded
    chosen, why = choose_precision(requested, get_baseline(cfg.baseline.name).bf16_default, resolve_device(cfg.device),
                                   name=cfg.baseline.name)
    cfg.baseline.precision = chosen
    return why


def _train_locked(cfg: DictConfig, run_dir: Path, data_base: str | None) -> dict | None:
    for stale in leftover_temporaries(run_dir):  # a writer killed mid-write (we hold the lock: none is writing)
        stale.unlink(missing_ok=True)
    if not cfg.data.name:  # label for tables: the scene folder's name
        cfg.data.name = scene_folder(cfg.data, data_base).name
    name = run_name(cfg)  # baseline=X without experiment=: the run is <data>_X, not the default experiment
    if name != cfg.name:
        print(f"[stdr] run name {name} (experiment {cfg.name} with baseline={cfg.baseline.name}"
              f"{''.join(f', {p.name}=on' for p in enabled_plugins(cfg))})", flush=True)
        cfg.name = name
    ckpt = run_dir / CKPT
    if cfg.train.resume is False:  # started over: the earlier run's results never stand beside the new one's
        moved = set_aside_results(run_dir)
        if moved is not None:
            print(f"[stdr] train.resume=false: the earlier run's results in {run_dir} moved to {moved}")
    resuming = bool(cfg.train.resume and ckpt.is_file())
    note = settle_precision(cfg, saved_config(run_dir) if resuming else None)
    if note:
        print(f"[stdr] {note}")
    if resuming:  # a resume keeps its run's record (stdr.train.resume)
        model = load_checkpoint(ckpt).get("model", {})
        step = int(model.get("step", 0))
        record, changes = resume_changes(cfg, run_dir, step, trained=model.get("config"))
    else:
        record, changes = OmegaConf.to_container(cfg, resolve=True), []
    if changes:
        record[CHANGES_KEY] = changes
    split = cfg.data.eval_split
    spec = check_pack_config(cfg)  # the compact file's codecs are checked before training, not after it
    # the data read (and refused) before the record is written: a scene that cannot be read leaves no config.yaml
    trainer = Trainer(cfg, run_dir, splits=("train", split), data_base=data_base)
    write_atomic(run_dir / "config.yaml", OmegaConf.to_yaml(OmegaConf.create(record)), site="config")
    pin_run_data(run_dir, cfg.data, trainer.scene, data_base)  # data.json: the scene's folder and fingerprints
    trainer.state.config_changes = changes
    print(f"[stdr] {cfg.name}: {len(trainer.scene.frames('train'))} train / "
          f"{len(trainer.scene.frames(split))} {split} frames at "
          f"{trainer.scene.frames('train')[0].camera.width}x{trainer.scene.frames('train')[0].camera.height}, "
          f"device={trainer.device}, backend={trainer.backend}, run dir {run_dir}")
    print(f"[stdr] TensorBoard: tensorboard --logdir {run_dir / 'tb'}")
    print(trainer.state.model.schedule.describe())
    trainer.train()
    if trainer.step < cfg.optim.iterations:  # stop_at or deadline: an unfinished run is not evaluated
        return None
    res = trainer.evaluate_final(split, cfg.eval)
    warm = [h for h in trainer.state.history if h["tag"] == "static_warmup"]
    lp = "n/a" if res["lpips"] is None else f"{res['lpips']:.4f}"
    print(f"[stdr] {split}: PSNR {res['psnr']:.2f} dB  SSIM {res['ssim']:.4f}  LPIPS {lp}  "
          f"FPS {res['fps']:.1f}  Gaussians {res['num_gaussians']}  train {res['train_seconds']:.0f} s")
    if warm:
        print(f"[stdr] static warm-up (iteration {warm[-1]['iteration']}): PSNR {warm[-1]['psnr']:.2f} dB "
              f"-> final {res['psnr']:.2f} dB")
    if spec is not None:  # the compact model file (compact=on): RUN/model.stdrc and RUN/pack.json
        print(summary(pack(run_dir, spec=spec, split=split if cfg.pack.evaluate else None,
                           data_base=data_base)))
    print(markdown(collect([table_row(OmegaConf.to_container(cfg, resolve=True), split, res, str(run_dir))])))
    print(f"[stdr] metrics: {run_dir / 'metrics.json'}  (tables over runs: stdr-eval RUN_DIR ...)")
    return res
