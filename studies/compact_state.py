"""The compact file's fixed part in fewer bits: the networks in 8 bits, 4DGS's grid in 4
(research/measurements/compact_state; protocol.md there, written before the runs).

    python -m studies.compact_state train DNERF --work WORK [--experiments ...] [--scenes ...] [--seeds 2 3]
    python -m studies.compact_state val DNERF --work WORK [...]    # records/val/<exp>__<scene>__s<seed>.json
    python -m studies.compact_state decide                        # decision.json and table.md from the records
"""
from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path

from studies.common import commit, records_in, records_to_write

ROOT = Path(__file__).resolve().parents[1]

OUT = ROOT / "research" / "measurements" / "compact_state"
#: the protocol's methods (its rule and amendment 1 decide on them); amendment 2 adds the rest
FIRST = ("dnerf_deform", "dnerf_4dgs", "dnerf_scgs")
EXPERIMENTS = ("dnerf_deform", "dnerf_4dgs", "dnerf_scgs",
               # amendment 2: every method the preset serves
               "dnerf_spgs", "dnerf_deform_stdr", "dnerf_scgs_stdr", "dnerf_spgs_stdr", "dnerf_4dgs_stdr")
SCENES = ("bouncingballs", "hellwarrior", "jumpingjacks", "standup")
SEEDS = (2, 3)
#: the preset's per-Gaussian codecs without the codebook fine-tune, entropy coded (protocol.md)
BASE = {"means": "q16", "scales": "q8", "quats": "q8", "opacities": "q8", "sh0": "q8", "shN": "vq:256",
        "state": "f16", "state:grids": "q8", "entropy": "zstd"}
CANDIDATES = {"s16": {}, "s8": {"state": "q8"}, "s8g4": {"state": "q8", "state:grids": "q4"},
              # amendment 1: the networks' weights and biases alone in 8 bits
              "s8w": {"state:weight": "q8", "state:bias": "q8"}}
#: amendment 3: 4DGS's grid in 4 bits, fine-tuned (quantization-aware), against the preset with its
#: codebook fine-tune; on 4dgs and 4dgs+STDR alone
RULED = tuple(CANDIDATES)  # the candidates of the protocol's rule (amendments 1 and 2)
S8W = CANDIDATES["s8w"]
GRID4 = {"s8wft": {**S8W, "finetune": 500}, "s8wg4": {**S8W, "state:grids": "q4"},
         "s8wg4ft": {**S8W, "state:grids": "q4", "finetune": 500, "finetune_state": "grids"}}
CANDIDATES.update(GRID4)
GRID4_METHODS = ("dnerf_4dgs", "dnerf_4dgs_stdr")
BOUND = -0.05  # dB, val PSNR against s16, mean over a method's runs


def run_dir(work: Path, exp: str, scene: str, seed: int) -> Path:
    """A run's folder: the id `stdr-tool queue` gives it under WORK."""
    from stdr.tools.runqueue import run_id
    return Path(work) / run_id(exp, scene, seed)


def train(args) -> None:
    """The runs, through the project's one run queue (`stdr-tool queue`, its state in
    WORK/queue.json): `compact=on budget=cpu`, experiments x scenes x seeds, --concurrent at a
    time with --threads each; a run whose metrics.json exists is done, an interrupted one resumes."""
    from stdr.tools.runqueue import Queue, execute, plan
    state = Path(args.work) / f"queue_{'_'.join(e.removeprefix('dnerf_') for e in args.experiments)}.json"
    if state.is_file():
        q = Queue.load(state)
    else:
        q = plan(args.experiments, [str(Path(args.dnerf) / s) for s in args.scenes], args.seeds,
                 ["compact=on", "budget=cpu", "eval.save_images=false", "train.image_every=0"], est_s=300)
    for r in q.runs:  # folders finished outside the queue (a run copied in) count as done
        if r.state != "done" and (Path(args.work) / r.id / "metrics.json").is_file():
            r.state = "done"
    try:
        execute(q, Path(args.work), args.concurrent, args.budget, cores=args.concurrent * args.threads)
    finally:
        q.save(state)
    print(f"[compact_state] {q.counts()}", flush=True)


def applies(name: str, exp: str) -> bool:
    """s8g4 differs from s8 only where there is a grid (4dgs); amendment 3's candidates are
    measured on the 4dgs methods alone."""
    if name in GRID4:
        return exp in GRID4_METHODS
    return name != "s8g4" or "4dgs" in exp


def val(args) -> None:
    from stdr.compact.pack import write_compact
    from stdr.store import load_config
    from stdr.data.load import load_scene
    from stdr.eval.evaluate import evaluate_model, machine_name
    from stdr.io.checkpoint import CKPT
    from stdr.model import load_model
    for seed in args.seeds:
        for exp in args.experiments:
            for scene in args.scenes:
                rd = run_dir(args.work, exp, scene, seed)
                rec_path = records_to_write(OUT, "records") / "val" / f"{exp}__{scene}__s{seed}.json"
                rec = json.loads(rec_path.read_text()) if rec_path.is_file() else None
                todo = [n for n in CANDIDATES if applies(n, exp) and (rec is None or n not in rec["candidates"])]
                if not todo or not (rd / "metrics.json").is_file():
                    continue
                cfg = load_config(rd / "config.yaml")
                cfg.device = "cpu"
                full = load_model(rd / CKPT, "cpu", cfg)
                scn = load_scene(cfg.data, ("train", "val"), base=str(ROOT), seed=cfg.seed)
                frames, train_frames = scn.frames("val"), scn.frames("train")
                rec = rec or {"experiment": exp, "scene": scene, "seed": seed, "split": "val",
                              "num_gaussians": full.num_gaussians, "full_bytes": None, "candidates": {}}
                for name in todo:
                    extra = CANDIDATES[name]
                    with tempfile.TemporaryDirectory() as tmp:
                        w = write_compact(full, Path(tmp) / "m.stdrc", {**BASE, **extra}, train_frames)
                        r = evaluate_model(load_model(Path(tmp) / "m.stdrc", "cpu", cfg), frames, fps_warmup=0)
                    rec["full_bytes"] = w["full_bytes"]
                    rec["candidates"][name] = {"bytes": w["bytes"], "psnr": r["psnr"], "ssim": r["ssim"], "code": commit(),
                                               **({"finetune": w["finetune"]} if "finetune" in w else {})}
                    _save(rec, rec_path)  # a long candidate (a fine-tune) is not lost to an interruption
                base = rec["candidates"]["s16"]
                for c in rec["candidates"].values():
                    c["delta_psnr"] = c["psnr"] - base["psnr"]
                print(f"[compact_state] val {exp} {scene} s{seed}: " + ", ".join(
                    f"{n} {c['bytes'] / 2**20:.3f} MiB {c['delta_psnr']:+.3f} dB" for n, c in rec["candidates"].items()),
                    flush=True)
                rec.update({"code": commit(), "machine": machine_name(), "date": time.strftime("%Y-%m-%d %H:%M")})
                _save(rec, rec_path)


def _save(rec: dict, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(rec, indent=1) + "\n")


def decide(recs: list[dict]) -> dict:
    """protocol.md's rule: per candidate, mean bytes and val ΔPSNR against s16 per method; a method
    whose runs are not all measured cannot pass (a partial mean is no decision)."""
    need = len(SCENES) * len(SEEDS)
    rows = {}
    for name in RULED:
        per = {}
        for exp in EXPERIMENTS:
            rs = [r for r in recs if r["experiment"] == exp and name in r["candidates"]]
            if rs and applies(name, exp):
                per[exp] = {"runs": len(rs), "delta_psnr": statistics.mean(r["candidates"][name]["delta_psnr"] for r in rs),
                            "bytes": statistics.mean(r["candidates"][name]["bytes"] for r in rs),
                            "file_over_model": statistics.mean(r["candidates"][name]["bytes"] / r["full_bytes"] for r in rs)}
        first = {e: v for e, v in per.items() if e in FIRST}
        rows[name] = {"per_method": per,
                      "passes": bool(first) and all(v["runs"] == need and v["delta_psnr"] >= BOUND for v in first.values())}
    chosen = {}
    for exp in FIRST:  # per method of the protocol, the smallest passing candidate that applies to it
        ok = [(rows[n]["per_method"][exp]["bytes"], n) for n in RULED
              if exp in rows[n]["per_method"] and rows[n]["passes"]]
        chosen[exp] = min(ok)[1] if ok else None
    # amendment 2: the preset (one spec for every method) takes a candidate that passes on all of them
    full = [n for n in RULED if all(e in rows[n]["per_method"] and rows[n]["per_method"][e]["runs"] == need
                                         and rows[n]["per_method"][e]["delta_psnr"] >= BOUND for e in EXPERIMENTS)]
    preset = min(full, key=lambda n: statistics.mean(v["bytes"] for v in rows[n]["per_method"].values())) if full else None
    return {"rule": f"smallest candidate with val dPSNR vs s16 >= {BOUND} dB per method, {need} runs a method",
            "candidates": rows, "chosen": chosen, "preset": preset,
            "passes_on": f"{', '.join(FIRST)} (the protocol's methods); preset: all of {', '.join(EXPERIMENTS)}",
            "grid4": decide_grid4(recs)}


def decide_grid4(recs: list[dict]) -> dict:
    """Amendment 3's rule: per 4dgs method, the mean over its runs of val PSNR(s8wg4ft) - val
    PSNR(s8wft) (and of s8wg4, for the record); adopted when every method has all its runs and
    a mean >= BOUND."""
    need = len(SCENES) * len(SEEDS)
    per = {}
    for exp in GRID4_METHODS:
        rs = [r["candidates"] for r in recs if r["experiment"] == exp and all(n in r["candidates"] for n in GRID4)]
        if rs:
            per[exp] = {"runs": len(rs), **{f"{n}_vs_s8wft": statistics.mean(c[n]["psnr"] - c["s8wft"]["psnr"] for c in rs)
                                            for n in ("s8wg4", "s8wg4ft")},
                        "worst_s8wg4ft": min(c["s8wg4ft"]["psnr"] - c["s8wft"]["psnr"] for c in rs),
                        **{f"{n}_bytes": statistics.mean(c[n]["bytes"] for c in rs) for n in GRID4}}
    adopted = len(per) == len(GRID4_METHODS) and all(v["runs"] == need and v["s8wg4ft_vs_s8wft"] >= BOUND
                                                     for v in per.values())
    return {"rule": f"s8wg4ft - s8wft >= {BOUND} dB, mean over {need} runs, for each of {', '.join(GRID4_METHODS)}",
            "per_method": per, "adopted": adopted}


def table(dec: dict, recs: list[dict]) -> str:
    lines = ["# Compact state: the networks and 4DGS's grid in fewer bits (val)", "",
             f"Generated by `python -m studies.compact_state decide` from {len(recs)} val records (code "
             f"{', '.join(sorted({r['code'] for r in recs}))}; machine {recs[0]['machine'] if recs else '-'}). "
             "Rule: protocol.md. Bytes: the compact file's tensors, entropy coded; model: the run's "
             "`compact=on` model.", "",
             "| candidate | method | runs | val ΔPSNR vs s16 (dB) | file KiB | file / model | passes |",
             "|---|---|---|---|---|---|---|"]
    for name, row in dec["candidates"].items():
        for exp, v in row["per_method"].items():
            lines.append(f"| {name} | {exp} | {v['runs']} | {v['delta_psnr']:+.3f} | {v['bytes'] / 1024:.1f} | "
                         f"{v['file_over_model']:.3f} | {'yes' if row['passes'] else 'no'} |")
    lines += ["", "Chosen: " + ", ".join(f"{e}: {c or 'none'}" for e, c in dec["chosen"].items()),
              "", f"For `compact=on` (every method measured and passing, amendment 2): {dec.get('preset') or 'none yet'}"]
    g = dec.get("grid4") or {}
    if g.get("per_method"):
        lines += ["", "## Amendment 3: the grid in 4 bits, fine-tuned (val, against `s8wft`: the preset with its "
                  "codebook fine-tune)", "", f"Rule: {g['rule']}.", "",
                  "| method | runs | s8wg4 − s8wft (dB) | s8wg4ft − s8wft (dB) | worst run | file KiB: s8wft, s8wg4ft |",
                  "|---|---|---|---|---|---|"]
        for exp, v in g["per_method"].items():
            lines.append(f"| {exp} | {v['runs']} | {v['s8wg4_vs_s8wft']:+.3f} | {v['s8wg4ft_vs_s8wft']:+.3f} | "
                         f"{v['worst_s8wg4ft']:+.3f} | {v['s8wft_bytes'] / 1024:.1f}, {v['s8wg4ft_bytes'] / 1024:.1f} |")
        lines += ["", f"Amendment 3: {'adopted' if g['adopted'] else 'not adopted'}"]
    return "\n".join(lines) + "\n"


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    for name in ("train", "val"):
        p = sub.add_parser(name)
        p.add_argument("dnerf", type=Path)
        p.add_argument("--work", type=Path, required=True)
        p.add_argument("--experiments", nargs="+", default=list(EXPERIMENTS), choices=EXPERIMENTS)
        p.add_argument("--scenes", nargs="+", default=list(SCENES), choices=SCENES)
        p.add_argument("--seeds", nargs="+", type=int, default=list(SEEDS))
        p.add_argument("--threads", type=int, default=1)
        p.add_argument("--concurrent", type=int, default=2, help="train: runs at a time")
        p.add_argument("--budget", type=float, default=6 * 3600.0, help="train: seconds for this call")
    sub.add_parser("decide")
    a = ap.parse_args(argv)
    if a.cmd == "train":
        train(a)
    elif a.cmd == "val":
        val(a)
    else:
        recs = [json.loads(p.read_text()) for p in sorted((records_in(OUT, "records") / "val").glob("*.json"))]
        dec = decide(recs)
        (OUT / "decision.json").write_text(json.dumps(dec, indent=1) + "\n")
        (OUT / "table.md").write_text(table(dec, recs))
        print(table(dec, recs), end="")


if __name__ == "__main__":
    main()
