"""STDR at the longer CPU budget: deform ± STDR at `budget=cpu_long` on the shared D-NeRF scenes,
with train, val and test PSNR along the learning curve (research/measurements/stdr_long).

    # resumable (a run with a record is skipped; a run stopped midway resumes from its last
    # checkpoint), on the project's run queue: --concurrent runs at a time, --threads each
    python -m studies.long_budget run DNERF_ROOT --work WORK [--seeds 0 1] [--threads 1] [--concurrent 1]
        [--methods deform deform_stdr ...] [--by-run] [--records DIR] [--extra KEY=VALUE ...] [--label NAME]
    # the table from the committed records (generated, stamped)
    python -m studies.long_budget table

Each run trains in segments (`train.stop_at` at every --points step, then to the end; a stopped
run resumes bit-exactly; every run of the grid to one point, then to the next) and after each
segment renders the whole train, val and test splits from
the checkpoint (PSNR, SSIM). Its record, `records/<method>/<scene>_s<seed>.json`, holds those curve
points, the final test metrics (with LPIPS) from the run's metrics.json, the command, the code
commit and the machine. Choices are made on val; test is reported as measured.
"""
from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

from studies.common import commit, records_in, records_to_write

ROOT = Path(__file__).resolve().parents[1]

RECORDS = ROOT / "research" / "measurements" / "stdr_long"
SCENES = ("bouncingballs", "hellwarrior", "jumpingjacks", "standup")
METHODS = ("deform", "deform_stdr")
POINTS = (2500, 5000, 7500)
SPLITS = ("train", "val", "test")
#: what each STDR record folder ran with, beside its name in the table: `deform_stdr` ran the default of
#: its code (24256aa), which `nogate` replaced by this study's rule
SETTINGS = {"deform_stdr": "stdr.mask_after_freeze=true, the default until 2026-11-28",
            "deform_stdr__nogate": "stdr.mask_after_freeze=false, the default since 2026-11-28",
            "deform_stdr__fop": "nogate + stdr.freeze_opacity=true, the paper's warm-up",
            "deform_stdr__reg4": "nogate + stdr.lambda_temp=0.4 stdr.lambda_spatial=0.8, the regularizers x 4",
            "deform_stdr__freeze3k": "nogate + stdr.freeze_at=3000, the mask learnable twice as long"}
#: the default each variant would replace (and is read against): nogate against the default of 24256aa,
#: the ablations queued after the change against nogate
REFERENCE = {"deform_stdr__nogate": "deform_stdr"}
ITERATIONS = 10000


def reference_of(variant: str) -> str:
    """The +STDR record folder `variant` is decided against: the default it would replace."""
    return REFERENCE.get(variant, "deform_stdr__nogate")


def evaluate_splits(run_dir: Path, splits=SPLITS) -> dict:
    """PSNR and SSIM of every frame of each split, rendered from the run's last checkpoint."""
    from stdr.store import load_config
    from stdr.data.load import load_scene
    from stdr.eval.evaluate import evaluate_model
    from stdr.model import model_from_checkpoint
    from stdr.io.checkpoint import load_checkpoint

    cfg = load_config(run_dir / "config.yaml")
    ck = load_checkpoint(run_dir / "checkpoints" / "last.pt")
    scene = load_scene(cfg.data, splits, base=str(ROOT), seed=cfg.seed)
    model = model_from_checkpoint(ck, "cpu", cfg, None, str(run_dir / "checkpoints" / "last.pt"))
    out = {"step": int(model.step)}
    for sp in splits:
        res = evaluate_model(model, scene.frames(sp), fps_repeats=1, fps_warmup=0)
        out[sp] = {"psnr": res["psnr"], "ssim": res["ssim"], "frames": res["num_frames"]}
    out["num_gaussians"] = int(res["num_gaussians"])
    return out


def overrides(root: Path, scene: str, seed: int, method: str, extra=()) -> list[str]:
    """The stdr-train overrides of one run of the study (without its segment's train.stop_at)."""
    return [f"experiment=dnerf_{method}", "budget=cpu_long", f"data.path={root / scene}", f"data.name={scene}",
            f"seed={seed}", "eval.save_images=false", "train.checkpoint_every=2500", *extra]


def _segment(cells: list[dict], stop: int | None, args) -> None:
    """Every cell that lacks this point trains to it (`train.stop_at`, or to the end), through the
    project's run queue (stdr-tool queue: one sweep, --concurrent at a time), and its three splits
    are evaluated from the checkpoint."""
    from stdr.tools.runqueue import Queue, Run, execute

    step = stop if stop is not None else args.iterations
    todo = [c for c in cells if step not in {p["step"] for p in c["state"]["points"]}]
    if not todo:
        return
    q = Queue([Run(c["id"], c["overrides"] + ([f"train.stop_at={stop}"] if stop is not None else []), 0.0)
               for c in todo])
    execute(q, args.work, args.concurrent, budget_s=None, cores=args.concurrent * args.threads)
    for c, r in zip(todo, q.runs):
        if r.state == "failed":
            raise SystemExit(f"[long_budget] {r.id}: failed ({r.error})")
        point = evaluate_splits(args.work / r.id)
        c["state"]["points"].append(point)
        c["state_path"].write_text(json.dumps(c["state"], indent=1))
        print(f"[long_budget] {r.id} step {point['step']}: " + ", ".join(
            f"{sp} {point[sp]['psnr']:.2f}" for sp in SPLITS), flush=True)


def run_queue(args) -> None:
    """The runs without a record. By default segment by segment: every run to the first point, each
    evaluated, then to the next; then each run's record. With --by-run each run goes through all its
    points and is recorded before the next starts (a queue that outlasts a session leaves whole
    records behind; run two such calls side by side, each with its own --work, for two at a time)."""
    cells = []
    for seed in args.seeds:
        for scene in args.scenes:
            for method in args.methods:
                name = f"{method}__{args.label}" if args.label else method
                rec_path = records_to_write(args.records, "records") / name / f"{scene}_s{seed}.json"
                if rec_path.is_file():
                    continue
                rid = f"{name}__{scene}__s{seed}"
                state_path = args.work / f"{rid}.curve.json"
                cells.append({"id": rid, "name": name, "scene": scene, "seed": seed, "rec_path": rec_path,
                              "state_path": state_path, "overrides": overrides(args.root, scene, seed, method, args.extra),
                              "state": json.loads(state_path.read_text()) if state_path.is_file() else {"points": []}})
    args.work.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    if args.by_run:
        for c in cells:
            for stop in (*args.points, None):
                _segment([c], stop, args)
            _record(c, args, t0)
        return
    for stop in (*args.points, None):
        _segment(cells, stop, args)
    for c in cells:
        _record(c, args, t0)


#: the final-test keys a record keeps from the run's metrics.json
FINAL_KEYS = ("psnr", "ssim", "lpips", "num_gaussians", "train_seconds", "model_mb", "iterations", "fps", "precision")


def _record(c: dict, args, t0: float) -> None:
    """Write the record of cell `c` (its run finished): curve points, final test metrics, command, code,
    machine."""
    from stdr.eval.evaluate import machine_name

    m = json.loads((args.work / c["id"] / "metrics.json").read_text())["test"]
    rec = {"scene": c["scene"], "seed": c["seed"], "method": c["name"], "budget": "cpu_long",
           "command": "stdr.cli.train " + " ".join(c["overrides"]), "code": commit(), "machine": machine_name(),
           "threads": args.threads, "concurrent": args.concurrent, "wall_seconds_this_call": round(time.time() - t0, 1),
           "points": sorted(c["state"]["points"], key=lambda q: q["step"]), "extra": list(args.extra),
           "final_test": {k: m.get(k) for k in FINAL_KEYS}}
    c["rec_path"].parent.mkdir(parents=True, exist_ok=True)
    c["rec_path"].write_text(json.dumps(rec, indent=1) + "\n")
    print(f"[long_budget] {c['id']}: recorded {c['rec_path']}", flush=True)


def load_records(records: Path) -> list[dict]:
    return [json.loads(p.read_text()) for p in sorted(records_in(records, "records").glob("*/*.json"))]


def _reaches(rec: dict, step: int) -> bool:
    return any(p["step"] == step for p in rec["points"])


def point_at(rec: dict, step: int) -> dict:
    return next(p for p in rec["points"] if p["step"] == step)


def table(records: Path) -> str:
    """The table: per scene and seed, each method's PSNR on train / val / test at every point and the
    train - test gap; then means over the pairs both methods have (STDR - plain on each split)."""
    recs = load_records(records)
    by = by_run(recs)
    steps = sorted({p["step"] for r in recs for p in r["points"]})
    lines = ["# deform ± STDR at budget=cpu_long (generated by studies/long_budget.py table)", "",
             f"Records: {len(recs)} runs; code {', '.join(sorted({r['code'] for r in recs}))}; machine "
             f"{'; '.join(sorted({r['machine'] for r in recs}))}; threads {sorted({r['threads'] for r in recs})}.", "",
             "PSNR (dB) rendered from each checkpoint over the whole split; gap = train - test.", "",
             "| scene | seed | method | " + " | ".join(f"{s} train / val / test" for s in steps) + " | gap at end | final test SSIM, LPIPS | Gaussians | train s |",
             "|---|---|---|" + "---|" * len(steps) + "---|---|---|---|"]
    for (scene, seed, method), r in sorted(by.items()):
        pts = {p["step"]: p for p in r["points"]}
        cells = [" / ".join(f"{pts[s][sp]['psnr']:.2f}" for sp in SPLITS) if s in pts else "–" for s in steps]
        last = pts[max(pts)]
        f = r["final_test"]
        lp = "n/a" if f.get("lpips") is None else f"{f['lpips']:.4f}"
        lines.append(f"| {scene} | {seed} | {method} | " + " | ".join(cells) +
                     f" | {last['train']['psnr'] - last['test']['psnr']:.2f} | {f['ssim']:.4f}, {lp} | "
                     f"{f['num_gaussians']:,} | {f['train_seconds']:.0f} |")
    for variant in sorted({m for (_, _, m) in by if m.startswith("deform_stdr")}):
        lines += _difference(by, variant, steps)
    for variant in sorted({m for (_, _, m) in by if m.startswith("deform_stdr__")}):
        lines += _decision_lines(decide(by, variant))
    lines += ["", f"Generated {time.strftime('%Y-%m-%d')} from {len(recs)} records by "
              f"`python -m studies.long_budget table` (code {commit()})."]
    return "\n".join(lines) + "\n"


def by_run(recs: list[dict]) -> dict:
    """(scene, seed, method) -> record."""
    return {(r["scene"], r["seed"], r["method"]): r for r in recs}


def pairs_of(by: dict, variant: str = "deform_stdr") -> list[tuple[dict, dict]]:
    """(plain deform, variant) records of every scene/seed both have."""
    return [(by[(sc, sd, "deform")], by[(sc, sd, variant)]) for (sc, sd, m) in by if m == "deform"
            and (sc, sd, variant) in by]


def _difference(by: dict, variant: str, steps: list[int]) -> list[str]:
    """The section `variant` (deform_stdr or deform_stdr__<label>) - plain deform, over the
    scene/seed pairs both have, at every step: mean differences per split and the two gaps."""
    pairs = pairs_of(by, variant)
    names = ", ".join(sorted(f"{a['scene']} s{a['seed']}" for a, _ in pairs))
    what = "STDR" if variant == "deform_stdr" else f"STDR ({variant.split('__', 1)[1]})"
    if variant in SETTINGS:
        what += f" [{SETTINGS[variant]}]"
    lines = ["", f"## {what} - plain, mean over {len(pairs)} scene/seed pairs ({names})", ""]
    if pairs:
        lines += ["| step | Δ train | Δ val | Δ test | plain gap | STDR gap |", "|---|---|---|---|---|---|"]
        for s in steps:
            both = [(a, b) for a, b in pairs if _reaches(a, s) and _reaches(b, s)]
            if not both:
                continue
            d = {sp: statistics.mean(point_at(b, s)[sp]["psnr"] - point_at(a, s)[sp]["psnr"] for a, b in both) for sp in SPLITS}
            g = [statistics.mean(point_at(r, s)["train"]["psnr"] - point_at(r, s)["test"]["psnr"] for r in rs)
                 for rs in ([a for a, _ in both], [b for _, b in both])]
            lines.append(f"| {s} | {d['train']:+.2f} | {d['val']:+.2f} | {d['test']:+.2f} | {g[0]:.2f} | {g[1]:.2f} |")
        lines += _spread(pairs, steps[-1])
    return lines


def _spread(pairs: list[tuple[dict, dict]], step: int) -> list[str]:
    """The val difference at `step` pair by pair, its mean by seed and its standard deviation over
    the pairs (the spread a mean of a few pairs carries)."""
    val = {(a["scene"], a["seed"]): point_at(b, step)["val"]["psnr"] - point_at(a, step)["val"]["psnr"] for a, b in pairs
           if _reaches(a, step) and _reaches(b, step)}
    if not val:
        return []
    seeds = sorted({sd for _, sd in val})
    by_seed = "; ".join(f"seed {sd}: {statistics.fmean(v for (_, s), v in val.items() if s == sd):+.2f} "
                        f"(n = {sum(s == sd for _, s in val)})" for sd in seeds)
    sd_ = f", standard deviation over the pairs {statistics.stdev(val.values()):.2f} dB" if len(val) > 1 else ""
    return ["", f"Val Δ at {step:,}, pair by pair: " + ", ".join(f"{sc} s{sd} {v:+.2f}" for (sc, sd), v in sorted(val.items()))
            + f". By seed: {by_seed}{sd_}."]


# The rule for an ablation to become the default, written before its runs (README, "Decision").
RAISE_R1, RAISE_R2, WORST_R2, COST_R1, LEVEL = 0.10, 0.30, -0.30, 1.10, -0.05


def decide(by: dict, variant: str) -> dict:
    """Whether `variant` (deform_stdr__<label>) replaces the default +STDR, by the README's rule.

    The default is `reference_of(variant)`: the +STDR default when the variant was queued.
    Triples: the scene/seed runs where plain, that default and the variant all reached the last
    step. R1: mean val(variant) - val(default) >= RAISE_R1 dB and the variant's training time at
    most COST_R1 x the default's (means over the triples). R2: that mean > RAISE_R2 and no triple
    below WORST_R2. Coverage: the triples hold every scene recorded for plain and both seeds 0, 1.
    `level`: mean val(variant) - val(plain) over every pair of the variant (>= LEVEL: level)."""
    ref = reference_of(variant)
    trip = [(by[(sc, sd, "deform")], by[(sc, sd, ref)], v) for (sc, sd, m), v in sorted(by.items())
            if m == variant and (sc, sd, "deform") in by and (sc, sd, ref) in by]
    last = max((p["step"] for r in by.values() for p in r["points"]), default=0)
    trip = [t for t in trip if all(_reaches(r, last) for r in t)]
    raise_ = [point_at(v, last)["val"]["psnr"] - point_at(d, last)["val"]["psnr"] for _, d, v in trip]
    pairs = [(a, b) for a, b in pairs_of(by, variant) if _reaches(b, last)]
    out = {"variant": variant, "reference": ref, "step": last, "triples": [f"{a['scene']} s{a['seed']}" for a, _, _ in trip],
           "raise": raise_, "pairs": len(pairs)}
    if not trip:
        return {**out, "adopt": False}
    mean = statistics.fmean(raise_)
    cost = statistics.fmean(v["final_test"]["train_seconds"] for *_, v in trip) / statistics.fmean(
        d["final_test"]["train_seconds"] for _, d, _ in trip)
    scenes = {sc for (sc, _, m) in by if m == "deform"}
    coverage = {a["scene"] for a, _, _ in trip} >= scenes and {a["seed"] for a, _, _ in trip} >= {0, 1}
    level = statistics.fmean(point_at(b, last)["val"]["psnr"] - point_at(a, last)["val"]["psnr"] for a, b in pairs)
    r1 = mean >= RAISE_R1 and cost <= COST_R1
    r2 = mean > RAISE_R2 and min(raise_) >= WORST_R2
    return {**out, "mean": mean, "worst": min(raise_), "cost": cost, "r1": r1, "r2": r2, "coverage": coverage,
            "level": level, "adopt": r1 and r2 and coverage}


def _decision_lines(d: dict) -> list[str]:
    label = d["variant"].split("__", 1)[1]
    ref = "default +STDR" if d["reference"] == "deform_stdr" else d["reference"].split("__", 1)[1]
    lines = ["", f"## Decision: does `{label}` replace {ref}? (the rule in the README, val at {d['step']:,})", ""]
    if not d["triples"]:
        return lines + [f"No scene/seed has plain, {ref} and this variant yet."]
    yes = {True: "holds", False: "does not hold"}
    return lines + [
        f"Triples (plain, {ref}, {label}): {len(d['triples'])} ({', '.join(d['triples'])}); "
        "val raise per triple: " + ", ".join(f"{x:+.2f}" for x in d["raise"]) + " dB.", "",
        f"* R1 (mean raise ≥ {RAISE_R1:.2f} dB, training time ≤ {COST_R1:.2f}× {ref}): mean {d['mean']:+.2f} dB, "
        f"time {d['cost']:.2f}× → {yes[d['r1']]}.",
        f"* R2 (mean raise > {RAISE_R2:.2f} dB, none below {WORST_R2:+.2f}): worst {d['worst']:+.2f} → {yes[d['r2']]}.",
        f"* Coverage (every scene with a plain run, seeds 0 and 1): {yes[d['coverage']]}.",
        f"* Level with plain (mean val Δ over its {d['pairs']} pairs ≥ {LEVEL:+.2f}): {d['level']:+.2f} dB → "
        f"{'level' if d['level'] >= LEVEL else 'behind'}.",
        f"* **Adopt as the default: {'yes' if d['adopt'] else 'not (yet)'}.**"]


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run", help="the resumable queue")
    r.add_argument("root", type=Path, help="a folder of D-NeRF scenes (e.g. ../shared/data/dnerf)")
    r.add_argument("--work", type=Path, required=True, help="run folders (outside the repository)")
    r.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    r.add_argument("--scenes", nargs="+", default=list(SCENES))
    r.add_argument("--methods", nargs="+", default=list(METHODS))
    r.add_argument("--points", type=int, nargs="+", default=list(POINTS))
    r.add_argument("--threads", type=int, default=1)
    r.add_argument("--concurrent", type=int, default=1, help="runs at a time")
    r.add_argument("--records", type=Path, default=RECORDS)
    r.add_argument("--iterations", type=int, default=ITERATIONS, help="the run's length (with --extra optim.iterations=N)")
    r.add_argument("--extra", nargs="*", default=[], help="more overrides (a record names them; with --label, an ablation)")
    r.add_argument("--by-run", action="store_true", help="each run through all its points, recorded before the next")
    r.add_argument("--label", default="", help="an ablation's name: records/<method>__<label>/, compared with plain deform")
    t = sub.add_parser("table", help="the table (and each ablation's decision) from the records")
    t.add_argument("--records", type=Path, default=RECORDS)
    args = ap.parse_args(argv)
    if args.cmd == "run":
        args.root = args.root.resolve()
        run_queue(args)
    else:
        text = table(args.records)
        (args.records / "table.md").write_text(text)
        print(text)


if __name__ == "__main__":
    main()
