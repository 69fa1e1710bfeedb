"""Compact grid (docs/measurements/compact_grid/protocol.md): 4DGS's compact file with a HexPlane
of 16 channels in `compact=on`, against the compact_bytes runs (32 channels, the same seed).

    python studies/compact_grid.py train DNERF_ROOT --work WORK [--scenes ...] [--experiments ...]
    python studies/compact_grid.py val DNERF_ROOT --work WORK     # records/val/, then decide
    python studies/compact_grid.py decide                        # decision.json, table_val.md
    python studies/compact_grid.py test DNERF_ROOT --work WORK    # only if the rule adopted it
    python studies/compact_grid.py table                         # table.md

Records (with the code commit and machine) go to docs/measurements/compact_grid/records/{val,test}/.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from studies import compact_bytes as cb  # noqa: E402

OUT = ROOT / "docs" / "measurements" / "compact_grid"
EXPERIMENTS = ("dnerf_4dgs", "dnerf_4dgs_stdr")
SCENES = cb.SCENES
SEED = cb.SEED
CANDIDATE = {"name": "c16", "overrides": ["baseline.hexplane.channels=16"]}
BOUND = -0.05  # dB, per method, mean over the scenes (protocol.md)


def train(args) -> None:
    for exp in args.experiments:
        for scene in args.scenes:
            rd = cb.run_dir(args.work, exp, scene)
            if (rd / "metrics.json").is_file():
                continue
            rd.parent.mkdir(parents=True, exist_ok=True)
            cmd = [sys.executable, "-m", "stdr.cli.train", f"experiment={exp}", "compact=on", "budget=cpu",
                   f"seed={SEED}", f"data.path={Path(args.dnerf) / scene}", f"hydra.run.dir={rd}",
                   "train.progress=false", "eval.save_images=false", "train.image_every=0",
                   f"train.threads={args.threads}", "pack.enabled=false", *CANDIDATE["overrides"]]
            t0 = time.time()
            print(f"[compact_grid] {time.strftime('%T')} train {exp} {scene}", flush=True)
            with open(f"{rd}.log", "a") as log:
                rc = subprocess.run(cmd, cwd=ROOT, env={**os.environ, "OMP_NUM_THREADS": str(args.threads)},
                                    stdout=log, stderr=subprocess.STDOUT).returncode
            print(f"[compact_grid]   {'done' if rc == 0 else f'FAILED rc={rc} (log {rd}.log)'} "
                  f"in {time.time() - t0:.0f} s", flush=True)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    for name in ("train", "val", "test"):
        p = sub.add_parser(name)
        p.add_argument("dnerf", type=Path, help="folder with the D-NeRF scenes")
        p.add_argument("--work", type=Path, required=True, help="the run folders")
        p.add_argument("--experiments", nargs="+", default=list(EXPERIMENTS), choices=EXPERIMENTS)
        p.add_argument("--scenes", nargs="+", default=list(SCENES), choices=SCENES)
        p.add_argument("--threads", type=int, default=1)
    sub.add_parser("decide")
    sub.add_parser("table")
    a = ap.parse_args(argv)
    globals()[a.cmd](a)


if __name__ == "__main__":
    main()
