"""Seconds per training iteration of a config at Gaussian counts a short run cannot reach.

Estimates what a full schedule (e.g. budget=paper) costs on this machine without running it:
1. Build the target config's trainer: resolution, deformation network, STDR as configured.
2. Take the trained Gaussians of an existing run (realistic opacities and footprints). Replicate
   them to each requested count N: each copy is jittered by half its scale, and the scales are
   shrunk by sqrt(copies) so that the covered area stays about the same.
3. Time full training steps (deformation on, densification off) after a few untimed ones.

The estimate is then iterations x seconds per iteration at the count the schedule ends with.
It assumes that count is known (pass it). Densification, evaluation and checkpointing are not
included.

    python -m studies.cost_probe outputs/toy/deform_2x --gaussians 50000 150000 \\
        --iters 10 --out research/measurements/x.json -- experiment=nerfds_deform budget=paper data.path=...
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch

from hydra import compose, initialize_config_dir

from stdr.config import CONFIG_DIR
from stdr.store import register
from stdr.tools.bench_train import replicate, run_gaussians
from stdr.train.trainer import Trainer


def main(argv=None):
    ap = argparse.ArgumentParser(prog="python -m studies.cost_probe", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog="the target config's Hydra overrides follow --")
    ap.add_argument("run", type=Path, help="a finished run whose checkpoint supplies the Gaussians")
    ap.add_argument("--gaussians", type=int, nargs="+", required=True)
    ap.add_argument("--iters", type=int, default=10)
    ap.add_argument("--warmup-iters", type=int, default=3)
    ap.add_argument("--out", type=Path, default=None)
    argv = list(sys.argv[1:] if argv is None else argv)
    overrides = argv[argv.index("--") + 1:] if "--" in argv else []
    args = ap.parse_args(argv[:argv.index("--")] if "--" in argv else argv)
    args.overrides = overrides
    register()
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base=None):
        cfg = compose("train", overrides=list(args.overrides) + [
            "densify.refine_start=1000000000", "train.progress=false", "eval.lpips=false"])
    gen = torch.Generator().manual_seed(0)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tr = Trainer(cfg, tmp, splits=("train",))
        f0 = tr.scene.frames("train")[0]
        source = run_gaussians(args.run)
        for n in args.gaussians:
            tr.replace_gaussians(replicate(source, n, gen))
            tr.step = cfg.baseline.warmup  # deformation on
            times = []
            for i in range(args.warmup_iters + args.iters):
                t0 = time.perf_counter()
                tr.train_step()
                if i >= args.warmup_iters:
                    times.append(time.perf_counter() - t0)
            s = statistics.median(times)
            row = {"gaussians": tr.state.model.num_gaussians, "seconds_per_iter": s,
                   "iterations": cfg.optim.iterations, "hours_for_schedule": s * cfg.optim.iterations / 3600}
            rows.append(row)
            print(f"N={row['gaussians']:>8,}  {s:.3f} s/iter  -> {row['hours_for_schedule']:.1f} h for "
                  f"{cfg.optim.iterations} iterations at {f0.camera.width}x{f0.camera.height}", flush=True)
    res = {"source_run": str(args.run), "overrides": list(args.overrides),
           "resolution": [f0.camera.width, f0.camera.height], "threads": torch.get_num_threads(),
           "deform": {"depth": cfg.baseline.depth, "width": cfg.baseline.width}, "stdr": bool(cfg.stdr.enabled),
           "rows": rows}
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(res, indent=1))
        print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
