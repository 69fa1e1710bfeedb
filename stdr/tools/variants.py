"""Variants of one method side by side (e.g. plain, +STDR, +culling), from each run's metrics.json.

Each `--table NAME LABEL=FOLDER ...` is one table: its rows are the variants, each a folder laid
out as <folder>/<scene>/metrics.json. The numbers are means over the scenes that every variant of
the table has (the others are named, never averaged): PSNR, SSIM, LPIPS, render FPS (with the
render settings it was timed under), Gaussians in the model, Gaussians rendered per frame after
temporal culling (mean and max over the frames), the model's megabytes and training seconds, and for FPS, Gaussians and training
seconds the ratio to the table's first variant (and the PSNR difference to it). A per-scene table follows.

    stdr-tool variants --split test --out research/measurements/compactness/tables \\
        --table deform plain=outputs/tab/deform_s0 +STDR=outputs/tab_fps/off/deform_stdr_s0 \\
                       "+STDR cull=outputs/tab_fps/eval/deform_stdr_s0"
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path
from statistics import mean

from ..eval.table import fmt_value as fmt
from ..eval.table import markdown_table, read_metrics, write_outputs

KEYS = ("psnr", "ssim", "lpips", "fps", "num_gaussians", "active_gaussians_mean", "active_gaussians_max", "model_mb",
        "train_seconds")
RATIOS = ("fps", "num_gaussians", "train_seconds")


def read(run: Path, split: str) -> dict:
    try:
        m = read_metrics(run, split)
    except (FileNotFoundError, KeyError) as e:
        raise SystemExit(f"{e} (pick the split with --split)")
    conv = m.get("conventions", {})
    out = {k: m.get(k) for k in KEYS}
    prof = run / "train_profile.json"  # the training's seconds by section, where the run kept it
    out["profile"] = None
    if prof.is_file():
        sec = json.loads(prof.read_text()).get("seconds")
        if not isinstance(sec, dict):
            raise SystemExit(f"{prof}: no 'seconds' section table (a train_profile.json the trainer writes has one)")
        out["profile"] = sec
    out.update({"run": str(run), "iterations": m.get("iterations"),
                "render_cull": conv.get("fps_render_cull", m.get("render_cull")),
                "fps_passes": len(m.get("fps_passes") or [1]), "fps_remeasured": bool(conv.get("fps_remeasured"))})
    return out


def parse_variant(spec: str) -> tuple[str, Path]:
    if "=" not in spec:
        raise SystemExit(f"variant {spec!r}: write it as LABEL=FOLDER (a folder of <scene>/metrics.json)")
    label, folder = spec.split("=", 1)
    if not Path(folder).is_dir():
        raise SystemExit(f"variant {label!r}: {folder} is not a folder")
    return label, Path(folder)


def build_table(name: str, variants: list[tuple[str, Path]], split: str) -> dict:
    if len({lb for lb, _ in variants}) != len(variants):
        raise SystemExit(f"table {name!r}: two variants share a label")
    found = {lb: {p.parent.name for p in f.glob("*/metrics.json")} for lb, f in variants}
    common = set.intersection(*found.values())
    if not common:
        raise SystemExit(f"table {name!r}: no scene has a metrics.json in every variant "
                         f"({', '.join(f'{lb}: {sorted(s)}' for lb, s in found.items())})")
    scenes = sorted(common)
    per_scene = {lb: {sc: read(f / sc, split) for sc in scenes} for lb, f in variants}
    rows = []
    for lb, _ in variants:
        runs = list(per_scene[lb].values())
        row = {"variant": lb, **{k: _mean([r[k] for r in runs]) for k in KEYS}}
        row["active_share"] = None if row["active_gaussians_mean"] is None or not row["num_gaussians"] \
            else row["active_gaussians_mean"] / row["num_gaussians"]
        for k in ("render_cull", "fps_passes", "iterations"):
            vals = sorted({str(r[k]) for r in runs})
            row[k] = vals[0] if len(vals) == 1 else "/".join(vals)
        profs = [r["profile"] for r in runs]
        row["profile"] = None if None in profs else \
            {k: mean(p.get(k, 0.0) for p in profs) for k in dict.fromkeys(k for p in profs for k in p)}
        rows.append(row)
    first = rows[0]
    for r in rows:
        r["d_psnr"] = None if r["psnr"] is None or first["psnr"] is None else r["psnr"] - first["psnr"]
        for k in RATIOS:
            r[f"{k}_ratio"] = None if r[k] is None or not first[k] else r[k] / first[k]
    missing = {lb: sorted(s - common) for lb, s in found.items() if s - common}
    return {"name": name, "split": split, "scenes": scenes, "rows": rows, "per_scene": per_scene,
            "missing": missing}


def smallest_within(table: dict, db: float) -> list[dict]:
    """Per scene: the best PSNR over the table's variants, and the first variant (in the order
    given, smallest model first) within `db` of it: the smallest model the scene needs."""
    out = []
    for sc in table["scenes"]:
        runs = {lb: r[sc] for lb, r in table["per_scene"].items()}
        best_lb = max(runs, key=lambda lb: runs[lb]["psnr"])
        best = runs[best_lb]["psnr"]
        pick = next(lb for lb, r in runs.items() if r["psnr"] >= best - db)
        out.append({"scene": sc, "best": best_lb, "best_psnr": best, "best_gaussians": runs[best_lb]["num_gaussians"],
                    "smallest": pick, "psnr": runs[pick]["psnr"], "gaussians": runs[pick]["num_gaussians"],
                    "within_db": db})
    return out


def _mean(v):
    return None if any(x is None for x in v) else mean(v)


HEAD = ["variant", "PSNR↑", "Δ PSNR", "SSIM↑", "LPIPS↓", "FPS↑", "FPS ×", "Gaussians", "G ×", "active/frame", "active share",
        "active max", "model MB", "train s", "train ×", "cull"]


def row_cells(r: dict) -> list[str]:
    return [r["variant"], fmt(r["psnr"], "{:.2f}"), fmt(r["d_psnr"], "{:+.2f}"), fmt(r["ssim"], "{:.4f}"), fmt(r["lpips"], "{:.4f}"),
            fmt(r["fps"], "{:.1f}"), fmt(r["fps_ratio"], "{:.2f}"), fmt(r["num_gaussians"], "{:,.0f}"),
            fmt(r["num_gaussians_ratio"], "{:.2f}"), fmt(r["active_gaussians_mean"], "{:,.0f}"),
            fmt(r["active_share"], "{:.0%}"), fmt(r["active_gaussians_max"], "{:,.0f}"), fmt(r["model_mb"], "{:.2f}"), fmt(r["train_seconds"], "{:.0f}"),
            fmt(r["train_seconds_ratio"], "{:.2f}"), str(r["render_cull"])]


def markdown(tables: list[dict]) -> str:
    out = []
    for t in tables:
        out += [f"## {t['name']}", "",
                f"Split: {t['split']}; mean over {len(t['scenes'])} scenes ({', '.join(t['scenes'])}). "
                "Δ and × are against the first row. cull: the render.cull the FPS was timed under. "
                "Generated by stdr-tool variants.", "",
                markdown_table(HEAD, [row_cells(r) for r in t["rows"]]), ""]
        body = []
        for sc in t["scenes"]:
            for lb, runs in t["per_scene"].items():
                r = runs[sc]
                body.append([sc, lb, fmt(r["psnr"], "{:.2f}"), fmt(r["lpips"], "{:.4f}"), fmt(r["fps"], "{:.1f}"),
                             fmt(r["num_gaussians"], "{:,}"), fmt(r["active_gaussians_mean"], "{:,.0f}"),
                             fmt(r["train_seconds"], "{:.0f}")])
        out += ["Per scene:", "", markdown_table(["scene", "variant", "PSNR", "LPIPS", "FPS", "Gaussians",
                                                  "active/frame", "train s"], body), ""]
        profiled = [r for r in t["rows"] if r["profile"]]
        if profiled:
            secs = list(dict.fromkeys(k for r in profiled for k in r["profile"]))
            out += ["Training seconds by section (mean over the scenes; the trainer's train_profile.json):", "",
                    markdown_table(["variant", *secs, "sum"],
                                   [[r["variant"], *(fmt(r["profile"].get(k), "{:.1f}") for k in secs),
                                     fmt(sum(r["profile"].values()), "{:.1f}")] for r in profiled]), ""]
        for lb, sc in t["missing"].items():
            out.append(f"Not in the means: {lb} also has {', '.join(sc)} (not every variant has it).\n")
        if t.get("smallest"):
            db = t["smallest"][0]["within_db"]
            out += [f"The smallest model each scene needs: the first variant (in the order above) within {db:g} dB "
                    "of the scene's best PSNR:", "",
                    markdown_table(["scene", "best", "best PSNR", "its Gaussians", f"smallest within {db:g} dB",
                                    "PSNR", "Gaussians"],
                                   [[r["scene"], r["best"], fmt(r["best_psnr"], "{:.2f}"),
                                     fmt(r["best_gaussians"], "{:,}"), r["smallest"], fmt(r["psnr"], "{:.2f}"),
                                     fmt(r["gaussians"], "{:,}")] for r in t["smallest"]]), ""]
    return "\n".join(out)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(prog="stdr-tool variants", description=__doc__.split("\n")[0])
    ap.add_argument("--table", nargs="+", action="append", required=True, metavar="NAME LABEL=FOLDER",
                    help="a table's name, then its variants as LABEL=FOLDER (the first is the reference)")
    ap.add_argument("--split", default="test")
    ap.add_argument("--out", type=Path, default=None, help="write OUT.md and OUT.json")
    ap.add_argument("--smallest-within", type=float, default=None, metavar="DB",
                    help="per scene, the first variant within DB of the best PSNR (give the variants smallest first)")
    a = ap.parse_args(argv)
    tables = []
    for spec in a.table:
        if len(spec) < 2:
            raise SystemExit(f"--table {' '.join(spec)}: give a name and at least one LABEL=FOLDER")
        tables.append(build_table(spec[0], [parse_variant(v) for v in spec[1:]], a.split))
        if a.smallest_within is not None:
            tables[-1]["smallest"] = smallest_within(tables[-1], a.smallest_within)
    md = markdown(tables)
    print(md, end="")
    write_outputs(a.out, md, {"split": a.split, "tables": tables})


if __name__ == "__main__":
    main()
