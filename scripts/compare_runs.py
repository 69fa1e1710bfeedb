#!/usr/bin/env python
"""Per-run table (one row per run directory) with per-group means and standard deviations.

For comparisons that `stdr-eval` deliberately refuses to average (runs whose configs differ,
e.g. in the render backend): rows are grouped by the resolved render backend recorded in
metrics.json, and each row shows its seed, so seed-to-seed spread is visible.

    scripts/run.sh python scripts/compare_runs.py RUN_DIR... --split test --out docs/measurements/x
"""
from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path

import yaml

COLS = ("psnr", "ssim", "lpips", "num_gaussians", "train_seconds", "fps")
FMT = {"psnr": "{:.2f}", "ssim": "{:.4f}", "lpips": "{:.4f}", "num_gaussians": "{:,.0f}",
       "train_seconds": "{:.0f}", "fps": "{:.1f}"}


def load(run: Path, split: str) -> dict:
    m = json.loads((run / "metrics.json").read_text())[split]
    cfg = yaml.safe_load((run / "config.yaml").read_text())
    return {"run_dir": str(run), "scene": cfg["data"]["name"], "seed": cfg["seed"],
            # runs from before the compiled backends did not record the resolved backend
            "backend": m["conventions"].get("render_backend", cfg["render"]["backend"] + "*"),
            **{k: m.get(k) for k in COLS}}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--split", default="test")
    ap.add_argument("--out", type=Path, default=None, help="write OUT.md and OUT.json")
    args = ap.parse_args(argv)
    rows = sorted((load(r, args.split) for r in args.runs), key=lambda r: (r["scene"], r["backend"], r["seed"]))
    groups: dict[tuple, list] = {}
    for r in rows:
        groups.setdefault((r["scene"], r["backend"]), []).append(r)
    lines = ["| scene | backend | seed | PSNR | SSIM | LPIPS | Gaussians | train s | FPS |",
             "|---|---|---|---:|---:|---:|---:|---:|---:|"]
    summary = []
    for (scene, backend), rs in groups.items():
        for r in rs:
            lines.append(f"| {scene} | {backend} | {r['seed']} | "
                         + " | ".join(FMT[k].format(r[k]) for k in COLS) + " |")
        stats = {}
        for k in COLS:
            vals = [r[k] for r in rs]
            stats[k] = {"mean": statistics.fmean(vals),
                        "std": statistics.stdev(vals) if len(vals) > 1 else 0.0}
        lines.append(f"| {scene} | **{backend} mean ± std ({len(rs)})** | | "
                     + " | ".join(f"{FMT[k].format(stats[k]['mean'])} ± {FMT[k].format(stats[k]['std'])}"
                                  for k in COLS) + " |")
        summary.append({"scene": scene, "backend": backend, "n_runs": len(rs), "stats": stats})
    if any(r["backend"].endswith("*") for r in rows):
        lines += ["", "\\* resolved backend not recorded: the run predates the compiled backends, "
                  "when `auto` always meant `reference`."]
    md = "\n".join(lines) + "\n"
    print(md)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.with_suffix(".md").write_text(md)
        args.out.with_suffix(".json").write_text(json.dumps({"rows": rows, "groups": summary}, indent=1))
        print(f"wrote {args.out.with_suffix('.md')} and .json")


if __name__ == "__main__":
    main()
