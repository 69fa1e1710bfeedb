"""stdr-train: train one model (Hydra app). `stdr-train --help` lists the config groups."""
from __future__ import annotations

from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from ..config import CONFIG_DIR, register
from ..errors import reported
from .common import check_overrides, reproducible_blas, use_fast_allocator_hint

register()


def run(cfg: DictConfig, run_dir: Path, data_base: str | None = None) -> dict | None:
    from ..train.trainer import Trainer
    from ..validate import check_run_config

    check_run_config(cfg, data_base)  # keys, values and paths, before anything is written or trained
    run_dir.mkdir(parents=True, exist_ok=True)
    if not cfg.data.name:  # label for tables: the scene folder's name
        from ..data.load import scene_folder
        cfg.data.name = scene_folder(cfg.data, data_base).name
    (run_dir / "config.yaml").write_text(OmegaConf.to_yaml(cfg, resolve=True))
    split = cfg.data.eval_split
    if cfg.pack.enabled:  # the compact file's codecs are checked before training, not after it
        from ..io.compact_file import check_spec
        from ..tools.pack import spec_of_config
        from ..plugins import enabled_plugins, plugin_node
        try:
            spec = check_spec(spec_of_config(cfg.pack))
            for p in enabled_plugins(cfg):
                p.plugin.check_compact_spec(plugin_node(cfg, p.name), spec)
        except ValueError as e:
            raise ValueError(f"pack.codecs: {e}") from None
    trainer = Trainer(cfg, run_dir, splits=("train", split), data_base=data_base)
    print(f"[stdr] {cfg.name}: {len(trainer.scene.frames('train'))} train / "
          f"{len(trainer.scene.frames(split))} {split} frames at "
          f"{trainer.scene.frames('train')[0].camera.width}x{trainer.scene.frames('train')[0].camera.height}, "
          f"device={trainer.device}, backend={trainer.backend}, run dir {run_dir}")
    print(f"[stdr] TensorBoard: tensorboard --logdir {run_dir / 'tb'}")
    print(trainer.model.schedule.describe())
    trainer.train()
    if trainer.step < cfg.optim.iterations:  # train.stop_at: an unfinished run is not evaluated
        return None
    res = trainer.evaluate_final(split, cfg.eval)
    warm = [h for h in trainer.history if h["tag"] == "static_warmup"]
    lp = "n/a" if res["lpips"] is None else f"{res['lpips']:.4f}"
    print(f"[stdr] {split}: PSNR {res['psnr']:.2f} dB  SSIM {res['ssim']:.4f}  LPIPS {lp}  "
          f"FPS {res['fps']:.1f}  Gaussians {res['num_gaussians']}  train {res['train_seconds']:.0f} s")
    if warm:
        print(f"[stdr] static warm-up (iteration {warm[-1]['iteration']}): PSNR {warm[-1]['psnr']:.2f} dB "
              f"-> final {res['psnr']:.2f} dB")
    if cfg.pack.enabled:  # the compact model file (compact=on): RUN/model.stdrc and RUN/pack.json
        from ..tools.pack import pack, spec_of_config, summary
        print(summary(pack(run_dir, spec=spec_of_config(cfg.pack), split=split if cfg.pack.evaluate else None,
                           data_base=data_base)))
    from ..eval.table import collect, markdown, table_row
    print(markdown(collect([table_row(OmegaConf.to_container(cfg, resolve=True), split, res, str(run_dir))])))
    print(f"[stdr] metrics: {run_dir / 'metrics.json'}  (tables over runs: stdr-eval RUN_DIR ...)")
    return res


FAILURES = "failures.jsonl"  # in a sweep folder: one line per failed job


def sweep_job(cfg: DictConfig, run_dir: Path, data_base: str) -> dict | None:
    """One job of a sweep (stdr-train -m): skipped when finished (train.skip_finished and
    metrics.json present); a failure is recorded in <sweep dir>/failures.jsonl with the job's
    overrides and log, printed, and does not stop the other jobs (SweepReport sums them up)."""
    import json
    import traceback

    hc = HydraConfig.get()
    if cfg.train.skip_finished and (run_dir / "metrics.json").is_file():
        print(f"[stdr] skipping finished run {run_dir} (metrics.json present; train.skip_finished=false reruns it)")
        return None
    try:
        return run(cfg, run_dir, data_base=data_base)
    except Exception as e:  # noqa: BLE001 - reported, the sweep goes on
        log = run_dir / f"{hc.job.name}.log"
        rec = {"overrides": list(hc.overrides.task), "run_dir": str(run_dir), "log": str(log),
               "error": f"{type(e).__name__}: {e}", "traceback": traceback.format_exc()}
        sweep_dir = Path(hc.sweep.dir)
        sweep_dir.mkdir(parents=True, exist_ok=True)
        with open(sweep_dir / FAILURES, "a") as f:
            f.write(json.dumps(rec) + "\n")
        print(f"[stdr] FAILED {' '.join(rec['overrides'])}: {rec['error']} (log: {log})", flush=True)
        return None


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
            run(cfg, run_dir, data_base=hydra.utils.get_original_cwd())


def main() -> None:
    """stdr-train. `--cfg job` prints the config with its derived `schedule` resolved (Hydra's
    --resolve is added), so the printed config shows every phase boundary of the run."""
    import sys
    if "--cfg" in sys.argv or "-c" in sys.argv:
        if "--resolve" not in sys.argv:
            sys.argv.append("--resolve")
    check_overrides("stdr-train", sys.argv[1:])  # a bad override: one line, exit code 2
    _main()


if __name__ == "__main__":
    main()
