"""Contribution pruning study (research/measurements/compact_prune/protocol.md): the decision and
tables from its committed records. The study is complete (its README): every val branch, the
time_bins runs that settle rule 6, and the test stage are recorded.

    python -m studies.compact_prune table [--records DIR]          # table_val.md, the protocol's rule
    python -m studies.compact_prune test-table [--test-records DIR]  # table_test.md, the targets

The runs were made by this file's `run` and `test` commands, which branched the headline runs at
their step-1500 checkpoint with the code frozen at one commit, under scripts/idle_run.py's
exclusive-machine check. Their code is in the history at the commit the records name;
`git show 25ff87d:studies/compact_prune.py` is its last form. New grids of runs go through the
project's one run queue (`stdr-tool queue`, docs/sweeps.md).
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from studies.common import gmean

ROOT = Path(__file__).resolve().parents[1]

RECORDS = ROOT / "research" / "measurements" / "compact_prune" / "runs"
SCENES = ("bouncingballs", "hellwarrior", "jumpingjacks", "standup")
EXPERIMENTS = tuple(f"dnerf_{b}{s}" for b in ("deform", "scgs", "spgs", "4dgs") for s in ("", "_stdr"))
VARIANTS = {  # name: prune.* overrides (the protocol's table)
    "control": ["prune.share=0"],
    "s30": ["prune.share=0.3", "prune.time_weight=0"],
    "s30_tw1": ["prune.share=0.3", "prune.time_weight=1"],
    "s50": ["prune.share=0.5", "prune.time_weight=0"],
    "s50_tw1": ["prune.share=0.5", "prune.time_weight=1"],
}
#: variants only for the +STDR methods
STDR_VARIANTS = {"m8": ["prune.share=0", "stdr.mask_bits=8"]}
#: +STDR variants trained from scratch (no trunk: the mask's time columns are fixed at the start),
#: with --scratch only; compared with the control branch of the same seed (protocol.md, amendment 2)
SCRATCH_VARIANTS = {"tb50": ["prune.share=0", "stdr.time_bins=50"], "tb25": ["prune.share=0", "stdr.time_bins=25"]}


def load_records(root: Path) -> dict:
    """{(experiment, scene, variant): the val entry of metrics.json, with train_profile seconds}."""
    out = {}
    for m in sorted(root.glob("*/*/*/metrics.json")):
        variant, scene, exp = m.parent.name, m.parent.parent.name, m.parent.parent.parent.name
        entry = json.loads(m.read_text())["val"]
        ident = m.parent / "identity.json"
        entry["identity"] = json.loads(ident.read_text()) if ident.is_file() else None
        br = json.loads((m.parent / "branch.json").read_text()) if (m.parent / "branch.json").is_file() else {}
        entry["branch_seconds"] = (entry["train_seconds"] - br["train_seconds_at_branch"]
                                   if "train_seconds_at_branch" in br else None)
        entry["trunk_seed"] = br.get("trunk_seed", 0)  # records from before the key branched seed 0
        entry["scratch"] = bool(br.get("scratch", False))
        out[(exp, scene, variant)] = entry
    return out


def _mean(xs):
    xs = [x for x in xs if x is not None]
    return sum(xs) / len(xs) if xs else None


def decide(recs: dict) -> dict:
    """The protocol's rule over complete records: per variant, each method's mean ΔPSNR against its
    control, admissibility (every method >= -0.1 dB), and the choice."""
    delta = {}
    for v in VARIANTS:
        if v == "control":
            continue
        per = {}
        for exp in EXPERIMENTS:
            ds = [recs[(exp, s, v)]["psnr"] - recs[(exp, s, "control")]["psnr"]
                  for s in SCENES if (exp, s, v) in recs and (exp, s, "control") in recs]
            per[exp] = sum(ds) / len(ds) if len(ds) == len(SCENES) else None
        delta[v] = per
    complete = {v: all(x is not None for x in per.values()) for v, per in delta.items()}
    if not all(complete.values()):
        return {"delta_psnr": delta, "complete": False, "choice": None}
    admissible = {v: min(per.values()) >= -0.1 for v, per in delta.items()}
    avg = {v: _mean(per.values()) for v, per in delta.items()}
    choice, why = None, ""
    for share in ("s50", "s30"):
        if admissible[share] or admissible[f"{share}_tw1"]:
            tw1 = admissible[f"{share}_tw1"] and (not admissible[share] or avg[f"{share}_tw1"] > avg[share] + 0.05)
            choice = f"{share}_tw1" if tw1 else share
            why = f"rule 2: the largest admissible share ({share})"
            break
    if choice is None:
        choice = "s30_tw1" if avg["s30_tw1"] > avg["s30"] else "s30"
        why = "rule 3: no variant admissible; the better of s30 / s30_tw1 on the eight-method mean"
    m8 = {}
    for exp in (e for e in EXPERIMENTS if e.endswith("_stdr")):
        ds = [recs[(exp, s, "m8")]["psnr"] - recs[(exp, s, "control")]["psnr"]
              for s in SCENES if (exp, s, "m8") in recs and (exp, s, "control") in recs]
        m8[exp] = sum(ds) / len(ds) if len(ds) == len(SCENES) else None
    mask8 = None if None in m8.values() else min(m8.values()) >= -0.05  # rule 5
    return {"delta_psnr": delta, "admissible": admissible, "mean_delta_psnr": avg, "complete": True,
            "choice": choice, "why": why, "m8_delta_psnr": m8, "mask_bits_8": mask8, **decide_time_bins(recs)}


def decide_time_bins(recs: dict) -> dict:
    """Rule 6 (protocol.md, amendment 2): each from-scratch time_bins variant's mean ΔPSNR against the
    control of each +STDR method; the preset's time_bins is the fewest columns whose ΔPSNR is >= -0.1 dB
    for all four methods (tb25 before tb50), else none. None while records are missing."""
    per = {}
    for v in SCRATCH_VARIANTS:
        per[v] = {}
        for exp in (e for e in EXPERIMENTS if e.endswith("_stdr")):
            ds = [recs[(exp, s, v)]["psnr"] - recs[(exp, s, "control")]["psnr"]
                  for s in SCENES if (exp, s, v) in recs and (exp, s, "control") in recs]
            per[v][exp] = sum(ds) / len(ds) if len(ds) == len(SCENES) else None
    # a variant is out once one method's complete mean is below the bar (the missing ones cannot
    # bring it back), in once every method's is at or above it; the rule decides as soon as that
    # settles it: the fewest admitted columns with every variant of fewer columns out, else none
    state = {v: "out" if any(x is not None and x < -0.1 for x in d.values()) else
             "in" if all(x is not None for x in d.values()) else None for v, d in per.items()}
    decided = None
    for v in ("tb25", "tb50"):
        if state[v] == "in":
            decided = int(v[2:])
            break
        if state[v] is None:
            break
    else:
        decided = 0
    return {"time_bins_delta_psnr": per, "time_bins_state": state, "time_bins": decided}


def _machines(recs: dict) -> str:
    n: dict = {}
    for r in recs.values():
        m = (r.get("conventions") or {}).get("machine", "not recorded")
        n[m] = n.get(m, 0) + 1
    return "; ".join(f"{k} ({v} runs)" for k, v in sorted(n.items())) or "–"


def table(args) -> int:
    from stdr.eval.evaluate import code_version, commit_stamp, machine_name
    recs = load_records(Path(args.records))
    seeds = sorted({r["trunk_seed"] for r in recs.values()})
    lines = [f"# Contribution pruning on val (budget=cpu, trunk seed {', '.join(map(str, seeds)) or '–'}, "
             "four shared D-NeRF scenes)", "",
             f"Generated by `python -m studies.compact_prune table` from {len(recs)} records at commit "
             f"{commit_stamp(code_version())} on {machine_name()}, {time.strftime('%Y-%m-%d')}. "
             f"Runs' machines: {_machines(recs)}. "
             "Rule: protocol.md. Means over the scenes present (n).", "",
             "Train s: the branch's own seconds (steps 1500-2000, the pruning events included); the first "
             "1500 steps are the headline run's, timed there.", "",
             "| method | variant | n | PSNR | SSIM | LPIPS | FPS | Gaussians | seen/frame | model MB | train s (1500-2000) | "
             "score pass s/event | identical control |", "|" + "---|" * 13]
    for exp in EXPERIMENTS:
        # `preset`: amendment 4's compact run where no variant has its keys (val numbers shown, not used)
        for v in [*VARIANTS, *(dict(STDR_VARIANTS, **SCRATCH_VARIANTS) if exp.endswith("_stdr") else {}), "preset"]:
            rows = [recs[(exp, s, v)] for s in SCENES if (exp, s, v) in recs]
            if not rows:
                continue
            ev = [e["score_seconds"] for r in rows for e in r.get("prune", [])]
            ident = "" if v != "control" else "/".join("yes" if (r["identity"] or {}).get("identical") else "NO"
                                                       for r in rows)

            if v in SCRATCH_VARIANTS:  # whole runs: their seconds are all theirs
                rows = [dict(r, branch_seconds=r.get("train_seconds")) for r in rows]

            def f(k, fmt, rows=rows):
                x = _mean(r.get(k) for r in rows)
                return "–" if x is None else format(x, fmt)
            lines.append(f"| {exp} | {v} | {len(rows)} | {f('psnr', '.2f')} | {f('ssim', '.4f')} | {f('lpips', '.4f')} | "
                         f"{f('fps', '.1f')} | {f('num_gaussians', ',.0f')} | {f('seen_per_frame', '.1%')} | "
                         f"{f('model_mb', '.2f')} | {f('branch_seconds', '.0f')} | "
                         f"{(sum(ev) / len(ev)) if ev else 0:.2f} | {ident} |")
    d = decide(recs)
    lines += ["", f"Decision: {d['choice'] or 'not yet (records incomplete)'}" + (f" ({d['why']})" if d.get('why') else "")]
    tb = d.get("time_bins", decide_time_bins(recs)["time_bins"])
    lines += ["", "`tb50` / `tb25` are trained from scratch with `stdr.time_bins` (their train s is the whole run's, "
              "not the branch's); rule 6: "
              + ("not yet (records incomplete)" if tb is None else
                 (f"stdr.time_bins={tb} joins the compact preset" if tb else "no time_bins variant is admissible"))]
    out = Path(args.records).parent
    (out / "table_val.md").write_text("\n".join(lines) + "\n")
    (out / "table_val.json").write_text(json.dumps({"decision": d, "records": {"/".join(k): v for k, v in recs.items()}},
                                                   indent=1, default=str))
    print("\n".join(lines))
    return 0


TEST_RECORDS = RECORDS.parent / "test"
ROLES = ("full", "compact")


def preset_of(d: dict, exp: str) -> tuple[str, list[str]]:
    """(branch name, keys) of method `exp`'s compact run under decision `d` (protocol.md, amendment 4):
    the chosen variant's branch, or `preset` (the chosen keys + stdr.mask_bits=8) for a +STDR method
    when rule 5 admits 8 bits, which no val variant combines with a share."""
    keys = list(VARIANTS[d["choice"]])
    if exp.endswith("_stdr") and d["mask_bits_8"]:  # m8's mask key (its prune.share=0 is the choice's here)
        return "preset", [*keys, *(k for k in STDR_VARIANTS["m8"] if not k.startswith("prune."))]
    return d["choice"], keys


TARGETS = (("psnr", "mean PSNR, compact - full (dB)", ">=", -0.1),
           ("num_gaussians", "Gaussians, compact / full", "<=", 0.5),
           ("fps", "render FPS, compact / full", ">=", 1.6),
           ("model_mb", "model bytes, compact / full", "<=", 0.4))
STDR_TARGETS = (("fps", "render FPS, +STDR / plain (both compact)", ">=", 1.0),
                ("model_mb", "model bytes, +STDR / plain (both compact)", "<=", 1.25),
                ("train_seconds", "train s, +STDR / plain (both compact)", "<=", 1.1))


def _compare(a: dict, b: dict, key: str):
    """Mean over scenes of a - b (PSNR) or geometric mean over scenes of a / b (the others)."""
    pairs = [(a[s][key], b[s][key]) for s in SCENES if s in a and s in b]
    if len(pairs) != len(SCENES):
        return None
    return _mean(x - y for x, y in pairs) if key == "psnr" else gmean(x / y for x, y in pairs)


def _meets(value, op: str, bound: float):
    return None if value is None else (value >= bound if op == ">=" else value <= bound)


def bytes_split(recs: dict) -> dict:
    """Per method, from each scene's full and compact run (the same deformation module, other
    Gaussian counts): the fixed MiB and the bytes per Gaussian of model_mb without STDR's mask,
    and the mask's MiB in each; means over the scenes that have both runs."""
    out = {}
    for exp in EXPERIMENTS:
        full, comp = recs.get((exp, "full"), {}), recs.get((exp, "compact"), {})
        rows = []
        for s in SCENES:
            if s not in full or s not in comp or full[s]["num_gaussians"] == comp[s]["num_gaussians"]:
                continue
            mf, mc = ((r.get("stdr") or {}).get("mask_bytes", 0) / 2 ** 20 for r in (full[s], comp[s]))
            bf, bc = full[s]["model_mb"] - mf, comp[s]["model_mb"] - mc
            per = (bf - bc) / (full[s]["num_gaussians"] - comp[s]["num_gaussians"])
            rows.append((bf - per * full[s]["num_gaussians"], per * 2 ** 20, mf, mc))
        if rows:
            out[exp] = dict(zip(("fixed_mib", "bytes_per_gaussian", "mask_mib_full", "mask_mib_compact"),
                                (_mean(col) for col in zip(*rows))))
    return out


def test_table(args) -> int:
    """table_test.md / .json: per baseline, plain and +STDR, full and compact on test, and the targets."""
    from stdr.eval.evaluate import code_version, commit_stamp, machine_name
    root = Path(args.test_records)
    recs: dict = {}
    for m in sorted(root.glob("*/*/*/metrics.json")):
        role, scene, exp = m.parent.name, m.parent.parent.name, m.parent.parent.parent.name
        entry = json.loads(m.read_text())["test"]
        entry["source"] = json.loads((m.parent / "source.json").read_text())
        recs.setdefault((exp, role), {})[scene] = entry
    if not recs:
        raise SystemExit(f"studies/compact_prune.py test-table: no records under {root}; run `studies/compact_prune.py test` first")
    src = next(iter(next(iter(recs.values())).values()))["source"]
    lines = ["# Full and compact on test (budget=cpu, trunk seed 2, four shared D-NeRF scenes)", "",
             f"Generated by `python -m studies.compact_prune test-table` from {sum(map(len, recs.values()))} records at "
             f"commit {commit_stamp(code_version())} on {machine_name()}, {time.strftime('%Y-%m-%d')}. "
             f"Runs' machines: {_machines({(k, s): v for k, d in recs.items() for s, v in d.items()})}. "
             f"Compact: the preset chosen on val (`{src['decision']}`"
             + (", + `stdr.mask_bits=8` for +STDR" if src["mask_bits_8"] else "") +
             "; protocol.md, amendment 4). Means over the scenes present (n); train s: the trunk's first "
             "1500 steps + the branch's 500.", "",
             "| baseline | method | n | PSNR | SSIM | LPIPS | FPS | Gaussians | seen/frame | model MB | train s |",
             "|" + "---|" * 11]
    for b in ("deform", "scgs", "spgs", "4dgs"):
        for exp in (f"dnerf_{b}", f"dnerf_{b}_stdr"):
            for role in ROLES:
                rows = list(recs.get((exp, role), {}).values())
                if not rows:
                    continue

                def f(k, fmt, rows=rows):
                    x = _mean(r.get(k) for r in rows)
                    return "–" if x is None else format(x, fmt)
                label = ("+STDR" if exp.endswith("_stdr") else "plain") + f" {role}"
                lines.append(f"| {b} | {label} | {len(rows)} | {f('psnr', '.2f')} | {f('ssim', '.4f')} | "
                             f"{f('lpips', '.4f')} | {f('fps', '.1f')} | {f('num_gaussians', ',.0f')} | "
                             f"{f('seen_per_frame', '.1%')} | {f('model_mb', '.2f')} | {f('train_seconds', '.0f')} |")
    targets = []
    for exp in EXPERIMENTS:
        full, comp = recs.get((exp, "full"), {}), recs.get((exp, "compact"), {})
        for key, what, op, bound in TARGETS:
            v = _compare(comp, full, key)
            targets.append({"method": exp, "target": what, "bound": f"{op} {bound}", "value": v,
                            "met": _meets(v, op, bound)})
    for b in ("deform", "scgs", "spgs", "4dgs"):
        st, pl = recs.get((f"dnerf_{b}_stdr", "compact"), {}), recs.get((f"dnerf_{b}", "compact"), {})
        for key, what, op, bound in STDR_TARGETS:
            v = _compare(st, pl, key)
            targets.append({"method": f"dnerf_{b}_stdr", "target": what, "bound": f"{op} {bound}", "value": v,
                            "met": _meets(v, op, bound)})
    lines += ["", "Compactness targets (ratios: geometric mean over the scenes of the per-scene ratio):", "",
              "| method | target | bound | measured | met |", "|---|---|---|---|---|"]
    for t in targets:
        v = "–" if t["value"] is None else f"{t['value']:+.2f}" if "PSNR" in t["target"] else f"{t['value']:.2f}"
        met = "–" if t["met"] is None else "yes" if t["met"] else "**no**"
        lines.append(f"| {t['method']} | {t['target']} | {t['bound']} | {v} | {met} |")
    split = bytes_split(recs)
    lines += ["", "Where the bytes are: model MiB = fixed part (deformation network, fields) + per-Gaussian bytes x N "
              "(+ STDR's mask), solved per scene from the full and the compact run (same method: the fixed part is "
              "untouched by pruning), means over the scenes:", "",
              "| method | fixed MiB | bytes per Gaussian (mask excluded) | mask MiB full | mask MiB compact |",
              "|---|---|---|---|---|"]
    for exp, b in split.items():
        lines.append(f"| {exp} | {b['fixed_mib']:.2f} | {b['bytes_per_gaussian']:.0f} | {b['mask_mib_full']:.2f} | "
                     f"{b['mask_mib_compact']:.2f} |")
    out = root.parent
    (out / "table_test.md").write_text("\n".join(lines) + "\n")
    (out / "table_test.json").write_text(json.dumps(
        {"targets": targets, "bytes_split": split, "records": {f"{e}/{r}/{s}": v for (e, r), d in recs.items() for s, v in d.items()}},
        indent=1, default=str))
    print("\n".join(lines))
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    t = sub.add_parser("table")
    t.add_argument("--records", default=str(RECORDS))
    tt = sub.add_parser("test-table")
    tt.add_argument("--test-records", default=str(TEST_RECORDS))
    args = ap.parse_args(argv)
    return {"table": table, "test-table": test_table}[args.cmd](args)


if __name__ == "__main__":
    raise SystemExit(main())
