"""bf16 against fp32 on val: the check behind `baseline.precision=auto` (research/measurements/precision_val).

    # copy the finished runs of a queue's work folder into the records (a run already there is kept)
    python -m studies.precision_val collect WORK [--records DIR]
    # the table from the records (generated, stamped): per method, each scene/seed pair's val PSNR in
    # fp32 and bf16, the mean delta and the rule's verdict
    python -m studies.precision_val table [--records DIR]
    # two other variants, one side's records in other folders (STDR's field: network bf16, field fp32
    # in runs/ against field bf16 in runs_field/)
    python -m studies.precision_val table --records runs_field --with runs --variants bf16 bf16field

The rule (written before the runs, the study's README): the mean val delta PSNR (bf16 - fp32) is at
least -0.1 dB over a method's pairs; a verdict needs every planned pair (PLANS: at budget=cpu 4 scenes x
seeds 0, 1; at budget=cpu_long jumpingjacks and standup, seed 0). The budget is read from the runs'
config.yaml; one table holds one budget.
Training seconds are those of runs that each shared the 2-core machine with one other run (the
queue's default), the two variants of a pair side by side: a rough speed ratio, not a timing record.
"""
from __future__ import annotations

import argparse
import json

import yaml
import shutil
import statistics
from pathlib import Path
from typing import Optional

from stdr.eval.table import markdown_table
from studies.common import M, commit, records_in, records_to_write

STUDY = M / "precision_val"
RECORDS = STUDY / "runs"  # in the study's records archive once packed (studies.records)
KEEP = ("metrics.json", "config.yaml", "train_profile.json")
#: the planned scene/seed pairs of each budget (the study's README, written before the runs)
PLANS = {"cpu": (("bouncingballs", "hellwarrior", "jumpingjacks", "standup"), (0, 1)),
         "cpu_long": (("jumpingjacks", "standup"), (0,))}
THRESHOLD = -0.1  # dB, the rule's bound on the mean val delta PSNR (bf16 - fp32)
#: a run whose training had less of its thread than this (train_cpu_utilization: paused, or crowded out)
#: has no training time to compare; its pair's PSNR still counts
MIN_UTILIZATION = 0.5


def collect(work: Path, records: Path = RECORDS) -> list[str]:
    """Copy every run of WORK that has a metrics.json (a finished run) and no record yet."""
    if records == RECORDS:
        records = records_to_write(STUDY, "runs")
    added = []
    for m in sorted(Path(work).glob("*/metrics.json")):
        dst = records / m.parent.name
        if (dst / "metrics.json").is_file():
            continue
        dst.mkdir(parents=True, exist_ok=True)
        for f in KEEP:
            if (m.parent / f).is_file():
                shutil.copy2(m.parent / f, dst / f)
        added.append(m.parent.name)
    return added


def load(records: Path = RECORDS, also: tuple[Path, ...] = ()) -> dict[tuple, dict]:
    """{(experiment, scene, seed, precision): the val entry of its metrics.json, with `budget` from its
    config.yaml} (the run id is <experiment>__<scene>__s<seed>__<precision>, as stdr-tool queue plan
    names variants); `also`: more records folders, merged (a run in two of them is refused)."""
    if records == RECORDS:
        records = records_in(STUDY, "runs")
    out = {}
    for folder in (records, *also):
        for m in sorted(Path(folder).glob("*/metrics.json")):
            exp, scene, seed, prec = m.parent.name.split("__")
            entry = json.loads(m.read_text())["val"]
            entry["budget"] = yaml.safe_load((m.parent / "config.yaml").read_text())["budget"]
            key = (exp, scene, int(seed[1:]), prec)
            if key in out:
                raise SystemExit(f"precision_val: run {m.parent.name} is in two records folders ({folder} and another)")
            out[key] = entry
    return out


def budget_of(recs: dict[tuple, dict]) -> str:
    """The one budget of the records, refused when they mix budgets or use one with no plan."""
    budgets = sorted({e["budget"] for e in recs.values()})
    if len(budgets) != 1 or budgets[0] not in PLANS:
        raise SystemExit(f"precision_val: the records hold budgets {budgets}; a table takes one of {sorted(PLANS)}")
    return budgets[0]


def summary(recs: dict[tuple, dict], variants: tuple[str, str] = ("fp32", "bf16"),
            methods: Optional[set] = None) -> dict[str, dict]:
    """Per experiment (of `methods`, default: every one with a run of either variant): its pairs'
    deltas (B - A for `variants` = (A, B)), mean, the count of planned pairs and the verdict (`pass`,
    `fail`, or `incomplete` until every planned pair is in)."""
    scenes, seeds = PLANS[budget_of(recs)]
    va, vb = variants
    out = {}
    for exp in sorted(methods if methods is not None else {k[0] for k in recs if k[3] in variants}):
        pairs = []
        for scene in scenes:
            for seed in seeds:
                a, b = recs.get((exp, scene, seed, va)), recs.get((exp, scene, seed, vb))
                if a and b:
                    util = min(x.get("train_cpu_utilization") or 0.0 for x in (a, b))
                    pairs.append({"scene": scene, "seed": seed, "a": a["psnr"], "b": b["psnr"],
                                  "delta": b["psnr"] - a["psnr"], "s_a": a["train_seconds"], "s_b": b["train_seconds"],
                                  "timed": util >= MIN_UTILIZATION})
        mean = statistics.mean(p["delta"] for p in pairs) if pairs else None
        planned = len(scenes) * len(seeds)
        verdict = "incomplete" if len(pairs) < planned else ("pass" if mean >= THRESHOLD else "fail")
        out[exp] = {"pairs": pairs, "mean_delta": mean, "planned": planned, "verdict": verdict}
    return out


def table(records: Path = RECORDS, also: tuple[Path, ...] = (), variants: tuple[str, str] = ("fp32", "bf16")) -> str:
    recs = load(records, also)
    va, vb = variants
    # the methods of the records folder itself: the --with folders supply the other side of its pairs
    methods = {k[0] for k in load(records) if k[3] in variants}
    machines = sorted({e["conventions"]["machine"] for e in recs.values()})
    codes = sorted({e["code"]["commit"][:7] for e in recs.values()})
    budget = budget_of(recs)
    scenes, seeds = PLANS[budget]
    lines = [f"# {vb} against {va} on val (budget={budget})", "",
             f"Generated by `python -m studies.precision_val table` at {commit()} from {len(recs)} run records "
             f"(code {', '.join(codes) or '-'}; {'; '.join(machines) or '-'}). D-NeRF 400² copies at 200 px, val split, "
             f"two runs at a time on 2 cores, one thread each. Rule: mean Δ PSNR ({vb} − {va}) ≥ "
             f"{THRESHOLD} dB over the {len(scenes) * len(seeds)} scene/seed pairs of a method. Training seconds: "
             f"rough (each run shared the machine with one other); a pair with a run that had less than "
             f"{MIN_UTILIZATION:.0%} of its thread (train_cpu_utilization: paused or crowded out) is not timed.", ""]
    head = ["method", "scene", "seed", f"{va} PSNR", f"{vb} PSNR", "Δ PSNR", f"train s {va}", f"train s {vb}", f"{vb} / {va}"]
    body = []
    summ = summary(recs, variants, methods)
    for exp, s in summ.items():
        for p in s["pairs"]:
            body.append([exp, p["scene"], str(p["seed"]), f"{p['a']:.2f}", f"{p['b']:.2f}", f"{p['delta']:+.2f}",
                         f"{p['s_a']:.0f}", f"{p['s_b']:.0f}",
                         f"{p['s_b'] / p['s_a']:.2f}" if p["timed"] else "– (not timed)"])
    lines += [markdown_table(head, body), ""]
    head = ["method", "pairs", "mean Δ PSNR", "min Δ", "pairs below 0", f"train s {vb} / {va} (geometric mean)", "verdict"]
    body = []
    for exp, s in summ.items():
        ps = s["pairs"]
        timed = [p["s_b"] / p["s_a"] for p in ps if p["timed"]]
        ratio = statistics.geometric_mean(timed) if timed else None
        body.append([exp, f"{len(ps)} of {s['planned']}", "-" if s["mean_delta"] is None else f"{s['mean_delta']:+.3f}",
                     f"{min(p['delta'] for p in ps):+.2f}" if ps else "-", str(sum(p["delta"] < 0 for p in ps)),
                     "-" if ratio is None else f"{ratio:.2f}", s["verdict"]])
    lines += ["Summary:", "", markdown_table(head, body), ""]
    return "\n".join(lines)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("collect")
    c.add_argument("work", type=Path)
    t = sub.add_parser("table")
    for p in (c, t):  # collect writes the table too
        p.add_argument("--records", type=Path, default=RECORDS)
        p.add_argument("--with", dest="also", type=Path, nargs="*", default=[],
                       help="more records folders (a name without a slash: a folder of the study)")
        p.add_argument("--variants", nargs=2, default=["fp32", "bf16"], metavar=("A", "B"),
                       help="the two run-id suffixes compared, B - A (default fp32 bf16)")
    args = ap.parse_args(argv)
    if args.cmd == "collect":
        print(f"[precision_val] added {collect(args.work, args.records)}")
    also = tuple(records_in(STUDY, str(p)) if "/" not in str(p) else p for p in args.also)
    text = table(args.records, also, tuple(args.variants))
    # the budget=cpu records' table is table.md; another records folder's (runs_cpu_long) is table_<folder>.md
    name = "table.md" if args.records == RECORDS else f"table_{args.records.name}.md"
    (STUDY if args.records == RECORDS else args.records.parent).joinpath(name).write_text(text)
    print(text)


if __name__ == "__main__":
    main()
