"""stdr-eval RUN_DIR [RUN_DIR ...] [overrides]: re-evaluate runs and print/write the table."""
from __future__ import annotations

import sys
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from ..config import Config, register
from .common import CONFIG_DIR

register()


def evaluate_dirs(runs: list[str], split: str | None, eval_cfg, render_cfg, reevaluate: bool,
                  out_dir: Path, base: str, device: str | None = None) -> dict:
    import json

    from ..eval.evaluate import evaluate_run
    from ..eval.table import collect, markdown, table_row, write_tables
    from ..train.trainer import CKPT, Trainer

    rows = []
    for r in runs:
        rd = Path(r) if Path(r).is_absolute() else Path(base) / r
        cfg_path = rd / "config.yaml"
        if not cfg_path.is_file():
            raise FileNotFoundError(f"{rd} is not a stdr run directory (no config.yaml); "
                                    "pass folders that stdr-train wrote")
        cfg = OmegaConf.merge(OmegaConf.structured(Config), OmegaConf.load(cfg_path))
        sp = split or cfg.data.eval_split
        if reevaluate:
            if render_cfg is not None:
                cfg.render = render_cfg
            if device is not None:  # e.g. a run trained on a GPU, re-evaluated on a CPU machine
                cfg.device = device
            tr = Trainer(cfg, rd, splits=(sp,), data_base=base, init_gaussians=False)
            tr.load(rd / CKPT, training=False)
            res = evaluate_run(tr, sp, eval_cfg)
        else:
            mp = rd / "metrics.json"
            if not mp.is_file():
                raise FileNotFoundError(f"{mp} not found: run stdr-eval without reevaluate=false")
            res = json.loads(mp.read_text()).get(sp)
            if res is None:
                raise KeyError(f"{mp} has no split {sp!r}")
        rows.append(table_row(OmegaConf.to_container(cfg, resolve=True), sp, res, str(rd)))
    table = collect(rows)
    paths = write_tables(table, out_dir)
    print(markdown(table))
    print(f"[stdr] tables: {', '.join(str(p) for p in paths.values())}")
    return table


@hydra.main(version_base=None, config_path=CONFIG_DIR, config_name="eval")
def _main(cfg: DictConfig) -> None:
    if not cfg.runs:
        raise SystemExit("usage: stdr-eval RUN_DIR [RUN_DIR ...] [key=value ...]")
    out = Path(cfg.out) if cfg.out else Path(HydraConfig.get().runtime.output_dir)
    evaluate_dirs(list(cfg.runs), cfg.split, cfg.eval, cfg.render, cfg.reevaluate, out,
                  hydra.utils.get_original_cwd(), cfg.device)


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
    _main()


if __name__ == "__main__":
    main()
