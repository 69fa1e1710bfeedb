"""Per-run table, generated from each run's metrics.json, config.yaml and train_profile.json.

    stdr-tool runs RUN_DIR... [--split test] [--out research/measurements/x]

One row per run directory: scene, method, the quality and cost metrics, and for STDR runs
* the N x K mask's memory with its Adam state, KNN time and the regularizers' time;
* mask statistics: the share of Gaussians switched off at some time, the mean normalized
  temporal entropy, and the share of (Gaussian, time) entries with masked opacity in
  [1/255, 0.05] ("faint": copies that can come back as ghosts);
* the field's dynamic probability.

`--config-cols KEY...` adds config values (dotted keys, e.g. data.image_scale), `--size` the
evaluated image size, `--label` the name of each run folder's parent (the candidate, in a sweep
laid out as <candidate>/<scene>), `--group-by KEY...` a mean ± sample-std row per group (keys:
scene, method, backend, seed, label or a config key), e.g. seeds of one scene and backend; the
paper-style table that averages seeds per method is `stdr-eval RUNS reevaluate=false`.
`--rule REF` (with --label) adds the screening rule's verdict per candidate
(research/measurements/fidelity/stdr_fidelity_protocol.md).
"""
from __future__ import annotations

import argparse
import os
import statistics
from pathlib import Path

from ..eval.table import fmt_value, load_run, markdown_table, write_outputs

METRIC_COLS = [("psnr", "PSNR", "{:.2f}"), ("ssim", "SSIM", "{:.4f}"), ("lpips", "LPIPS", "{:.4f}"),
               ("fps", "FPS", "{:.1f}"), ("num_gaussians", "#G", "{:,.0f}"), ("train_seconds", "train s", "{:.0f}")]
STDR_COLS = [("K", "K", "{}"), ("mask_total_mib", "mask+Adam MiB", "{:.1f}"), ("knn_seconds", "KNN s", "{:.2f}"),
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


def row(run: Path, split: str, config_cols=(), size=False, allow_missing=False, label=False) -> dict:
    r = load_run(run, split)
    m, cfg = r["metrics"], r["config"]
    extra = {"run": Path(os.path.abspath(run)).parent.name} if label else {}
    for k in config_cols:
        v = config_value(cfg, k, run, allow_missing)
        extra[k] = "–" if v is MISSING else v
    if size:
        extra["size"] = f"{m['width']}x{m['height']}" if "width" in m else None
    reg = (r["profile"] or {}).get("seconds", {}).get("stdr_reg")
    return {"run_dir": str(run), "method": r["method"], "scene": r["scene"], "seed": r["seed"],
            "backend": r["backend"], **{k: m.get(k) for k, _, _ in METRIC_COLS},
            **(m.get("stdr") or {}), "stdr_reg_seconds": reg, "extra": extra}


def group_key(r: dict, key: str):
    if key in r and key != "extra":
        return r[key]
    if key == "label":
        return r["extra"].get("run")
    if key in r["extra"]:
        return r["extra"][key]
    raise KeyError(f"--group-by {key!r}: not a column (scene, method, backend, seed, label, or one of --config-cols)")


def group_stats(rows: list[dict], keys: list[str], cols) -> list[dict]:
    """Mean and sample std (n - 1; 0 for one run) of each column per group of rows."""
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault(tuple(group_key(r, k) for k in keys), []).append(r)
    out = []
    for g, rs in groups.items():
        stats = {}
        for k, _, _ in cols:
            vals = [r.get(k) for r in rs]
            if any(v is None for v in vals):
                stats[k] = {"mean": None, "std": None}
            else:
                stats[k] = {"mean": statistics.fmean(vals), "std": statistics.stdev(vals) if len(vals) > 1 else 0.0}
        out.append({"group": dict(zip(keys, g)), "n_runs": len(rs), "stats": stats})
    return out


def rule_summary(rows: list[dict], ref: str, min_gain: float, max_loss: float) -> str:
    """Markdown: one line per candidate (the run folder's parent) against candidate `ref`."""
    by: dict[str, dict[str, dict]] = {}
    for r in rows:
        by.setdefault(r["extra"]["run"], {})[r["scene"]] = r
    if ref not in by:
        raise SystemExit(f"--rule {ref}: no run folder under a parent named {ref!r}")
    scenes = sorted(by[ref])
    body = []
    ref_mean = sum(by[ref][s]["psnr"] for s in scenes) / len(scenes)
    for cand, sc in by.items():
        if sorted(sc) != scenes:
            body.append([cand, "–", "–", "–", "–", "–", f"incomplete: scenes {sorted(sc)}"])
            continue
        mean = sum(sc[s]["psnr"] for s in scenes) / len(scenes)
        worst = min(sc[s]["psnr"] - by[ref][s]["psnr"] for s in scenes)
        lp = [sc[s]["lpips"] for s in scenes]
        lps = "–" if None in lp else f"{sum(lp) / len(lp):.4f}"
        ng = sum(sc[s]["num_gaussians"] for s in scenes) / len(scenes)
        verdict = "reference" if cand == ref else (
            "passes" if mean - ref_mean >= min_gain and worst >= -max_loss else "fails")
        body.append([cand, f"{mean:.3f}", f"{mean - ref_mean:+.3f}", f"{worst:+.2f}", lps, f"{ng:,.0f}", verdict])
    head = (f"Rule: mean PSNR over {', '.join(scenes)} at least {min_gain} dB above `{ref}`, "
            f"no scene more than {max_loss} dB below it.\n\n")
    return head + markdown_table(["candidate", "mean PSNR", "Δ mean", "worst scene Δ", "mean LPIPS", "mean #G",
                                  "verdict"], body) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(prog="stdr-tool runs", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--split", default="test")
    ap.add_argument("--out", type=Path, default=None, help="write OUT.md and OUT.json")
    ap.add_argument("--config-cols", nargs="*", default=[], help="config keys to show, e.g. data.image_scale")
    ap.add_argument("--size", action="store_true", help="show the evaluated image size")
    ap.add_argument("--label", action="store_true",
                    help="first column: the run folder's parent name (e.g. the candidate of a sweep)")
    ap.add_argument("--allow-missing", action="store_true",
                    help="a --config-cols key absent from a run's config.yaml (an older run) shows as '–'")
    ap.add_argument("--group-by", nargs="*", default=[], metavar="KEY",
                    help="add a mean ± std row per group, e.g. --group-by scene backend")
    ap.add_argument("--rule", metavar="REF", default=None,
                    help="with --label: per candidate, mean PSNR over its scenes, change against candidate REF, "
                         "worst scene, and the screening rule's verdict")
    ap.add_argument("--min-gain", type=float, default=0.3, help="rule: mean PSNR gain needed (dB)")
    ap.add_argument("--max-loss", type=float, default=0.3, help="rule: largest loss allowed on any scene (dB)")
    args = ap.parse_args(argv)
    if args.rule and not args.label:
        ap.error("--rule compares candidates by their run folder's parent: add --label")
    rows = [row(r, args.split, args.config_cols, args.size, args.allow_missing, args.label) for r in args.runs]
    cols = METRIC_COLS + (STDR_COLS if any(r.get("K") is not None for r in rows) else [])
    extra = list(rows[0]["extra"])
    body = [[r["scene"], r["method"], *[str(r["extra"][k]) for k in extra], *[fmt_value(r.get(k), f) for k, _, f in cols]]
            for r in rows]
    groups = group_stats(rows, args.group_by, cols) if args.group_by else []
    mean_fmt = [(k, "{:.1f}" if f == "{}" else f) for k, _, f in cols]  # counts average to fractions
    for g in groups:
        label = ", ".join(f"{k}={v}" for k, v in g["group"].items())
        body.append([f"**mean ± std ({g['n_runs']})**", label, *[""] * len(extra),
                     *[fmt_value(g["stats"][k]["mean"], f) + ("" if g["stats"][k]["mean"] is None else
                                                             " ± " + f.format(g["stats"][k]["std"]))
                       for k, f in mean_fmt]])
    md = markdown_table(["scene", "method", *extra, *[h for _, h, _ in cols]], body) + "\n"
    if any(r["backend"].endswith("*") for r in rows) and "backend" in args.group_by:
        md += ("\n\\* resolved backend not recorded: the run predates the compiled backends, "
               "when `auto` always meant `reference`.\n")
    if args.rule:
        md += "\n" + rule_summary(rows, args.rule, args.min_gain, args.max_loss)
    print(md)
    write_outputs(args.out, md, {"split": args.split, "rows": rows, "groups": groups})


if __name__ == "__main__":
    main()
