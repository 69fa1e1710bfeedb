#!/usr/bin/env python
"""STDR statistics per run, generated from each run's metrics.json and train_profile.json.

One row per run directory:
* method, scene and the quality metrics;
* the N x K mask's memory with its Adam state;
* KNN time and the time of the regularizers;
* mask statistics: the share of Gaussians switched off at some time, the mean normalized
  temporal entropy, and the share of (Gaussian, time) entries with masked opacity in
  [1/255, 0.05] ("faint": copies that can come back as ghosts);
* the field's dynamic probability.
Runs without STDR show only the metrics. `--config-cols KEY...` adds config values (dotted keys,
e.g. data.image_scale data.intrinsics) and `--size` the evaluated image size (metrics.json), `--label` the name of each run folder's parent
(the candidate, in a sweep laid out as <candidate>/<scene>).

    scripts/run.sh python scripts/stdr_stats.py RUN_DIR... --out docs/measurements/x
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import yaml

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from stdr.eval.table import method_name  # noqa: E402

COLS = [("psnr", "PSNR", "{:.2f}"), ("ssim", "SSIM", "{:.4f}"), ("lpips", "LPIPS", "{:.4f}"),
        ("fps", "FPS", "{:.1f}"), ("num_gaussians", "#G", "{:,.0f}"), ("train_seconds", "train s", "{:.0f}"),
        ("K", "K", "{}"), ("mask_total_mib", "mask+Adam MiB", "{:.1f}"), ("knn_seconds", "KNN s", "{:.2f}"),
        ("knn_refreshes", "KNN refreshes", "{}"), ("stdr_reg_seconds", "reg s", "{:.1f}"),
        ("fraction_time_gated", "gated", "{:.2f}"), ("temporal_entropy_mean", "entropy", "{:.3f}"),
        ("fraction_faint", "faint", "{:.3f}"),
        ("dynamic_probability_mean", "dyn p", "{:.3f}"), ("fraction_dynamic", "dyn>0.5", "{:.2f}")]


MISSING = object()


def config_value(cfg: dict, key: str, run: Path | None = None, allow_missing: bool = False):
    v = cfg
    for part in key.split("."):
        if not isinstance(v, dict) or part not in v:
            if allow_missing:
                return MISSING
            raise KeyError(f"config key {key!r} not found in {run or 'the run'}/config.yaml (a run older than the "
                           "key: pass --allow-missing to show it as '–')")
        v = v[part]
    return v


def load(run: Path, split: str, config_cols=(), size=False, allow_missing=False) -> dict:
    m = json.loads((run / "metrics.json").read_text())[split]
    cfg = yaml.safe_load((run / "config.yaml").read_text())
    extra = {}
    for k in config_cols:
        v = config_value(cfg, k, run, allow_missing)
        extra[k] = "–" if v is MISSING else v
    if size:
        extra["size"] = f"{m['width']}x{m['height']}" if "width" in m else None
    prof = run / "train_profile.json"
    reg = json.loads(prof.read_text())["seconds"].get("stdr_reg") if prof.is_file() else None
    return {"run_dir": str(run), "method": method_name(cfg), "scene": cfg["data"]["name"],
            **{k: m.get(k) for k in ("psnr", "ssim", "lpips", "fps", "num_gaussians", "train_seconds")},
            **(m.get("stdr") or {}), "stdr_reg_seconds": reg, "extra": extra}


def fmt(v, f):
    return "–" if v is None else f.format(v)


def rule_summary(rows, runs, ref: str, min_gain: float, max_loss: float) -> str:
    """Markdown: one line per candidate (the run folder's parent) against candidate `ref`."""
    by: dict[str, dict[str, dict]] = {}
    for r, run in zip(rows, runs):
        by.setdefault(Path(os.path.abspath(run)).parent.name, {})[r["scene"]] = r
    if ref not in by:
        raise SystemExit(f"--rule {ref}: no run folder under a parent named {ref!r}")
    scenes = sorted(by[ref])
    out = [f"Rule: mean PSNR over {', '.join(scenes)} at least {min_gain} dB above `{ref}`, "
           f"no scene more than {max_loss} dB below it.", "",
           "| candidate | mean PSNR | Δ mean | worst scene Δ | mean LPIPS | mean #G | verdict |",
           "|---|---|---|---|---|---|---|"]
    ref_mean = sum(by[ref][s]["psnr"] for s in scenes) / len(scenes)
    for cand, sc in by.items():
        if sorted(sc) != scenes:
            out.append(f"| {cand} | – | – | – | – | – | incomplete: scenes {sorted(sc)} |")
            continue
        mean = sum(sc[s]["psnr"] for s in scenes) / len(scenes)
        worst = min(sc[s]["psnr"] - by[ref][s]["psnr"] for s in scenes)
        lp = [sc[s]["lpips"] for s in scenes]
        lps = "–" if None in lp else f"{sum(lp) / len(lp):.4f}"
        ng = sum(sc[s]["num_gaussians"] for s in scenes) / len(scenes)
        verdict = "reference" if cand == ref else (
            "passes" if mean - ref_mean >= min_gain and worst >= -max_loss else "fails")
        out.append(f"| {cand} | {mean:.3f} | {mean - ref_mean:+.3f} | {worst:+.2f} | {lps} | {ng:,.0f} | {verdict} |")
    return "\n".join(out) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--split", default="test")
    ap.add_argument("--out", type=Path, default=None, help="write OUT.md and OUT.json")
    ap.add_argument("--config-cols", nargs="*", default=[], help="config keys to show, e.g. data.image_scale")
    ap.add_argument("--size", action="store_true", help="show the evaluated image size")
    ap.add_argument("--label", action="store_true",
                    help="first column: the run folder's parent name (e.g. the candidate of a sweep)")
    ap.add_argument("--allow-missing", action="store_true",
                    help="a --config-cols key absent from a run's config.yaml (an older run) shows as '–'")
    ap.add_argument("--rule", metavar="REF", default=None,
                    help="with --label: per candidate, mean PSNR over its scenes, change against candidate REF, "
                         "worst scene, and the screening rule's verdict (docs/measurements/stdr_fidelity_protocol.md)")
    ap.add_argument("--min-gain", type=float, default=0.3, help="rule: mean PSNR gain needed (dB)")
    ap.add_argument("--max-loss", type=float, default=0.3, help="rule: largest loss allowed on any scene (dB)")
    args = ap.parse_args(argv)
    rows = [load(r, args.split, args.config_cols, args.size, args.allow_missing) for r in args.runs]
    if args.label:
        for r, run in zip(rows, args.runs):
            r["extra"] = {"run": Path(os.path.abspath(run)).parent.name, **r["extra"]}
    extra = list(rows[0]["extra"])
    lines = ["| scene | method | " + " | ".join(extra + [h for _, h, _ in COLS]) + " |",
             "|---|---|" + "---|" * (len(extra) + len(COLS))]
    for r in rows:
        lines.append(f"| {r['scene']} | {r['method']} | " + " | ".join(
            [str(r["extra"][k]) for k in extra] + [fmt(r.get(k), f) for k, _, f in COLS]) + " |")
    md = "\n".join(lines) + "\n"
    if args.rule:
        md += "\n" + rule_summary(rows, args.runs, args.rule, args.min_gain, args.max_loss)
    print(md)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.with_suffix(".md").write_text(md)
        args.out.with_suffix(".json").write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
