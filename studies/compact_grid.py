"""Compact grid (research/measurements/compact_grid/protocol.md): 4DGS's compact file with a HexPlane
of 16 channels in `compact=on`, against the compact_bytes runs (32 channels, the same seed).

    python -m studies.compact_grid train DNERF_ROOT --work WORK [--scenes ...] [--experiments ...]
    python -m studies.compact_grid val DNERF_ROOT --work WORK     # records/val/, then decide
    python -m studies.compact_grid decide                        # decision.json, table_val.md
    python -m studies.compact_grid test DNERF_ROOT --work WORK    # only if the rule adopted it
    python -m studies.compact_grid table                         # table.md

Records (with the code commit and machine) go to research/measurements/compact_grid/records/{val,test}/.
"""
from __future__ import annotations

import argparse
import json
import math
import statistics
import tempfile
import time
from pathlib import Path

from studies import compact_bytes as cb
from studies.common import commit, records_in, records_to_write

ROOT = Path(__file__).resolve().parents[1]

OUT = ROOT / "research" / "measurements" / "compact_grid"
EXPERIMENTS = ("dnerf_4dgs", "dnerf_4dgs_stdr")
SCENES = cb.SCENES
SEED = cb.SEED
CANDIDATE = {"name": "c16", "overrides": ["baseline.hexplane.channels=16"]}
BOUND = -0.05  # dB, per method, mean over the scenes (protocol.md)


def train(args) -> None:
    """compact_bytes' training command with the candidate grid; the study writes the files itself."""
    cb.train(args, ["pack.enabled=false", *CANDIDATE["overrides"]], tag="compact_grid", refuse_former_default=False)


def reference() -> dict:
    """(experiment, scene) -> the compact_bytes run's val numbers (32 channels): its model's PSNR,
    and its file's with the codecs that study chose (the model's PSNR + that candidate's delta)."""
    dec = json.loads((cb.OUT / "decision.json").read_text())
    out = {}
    for r in cb.load_val():
        if r["experiment"] in EXPERIMENTS:
            name, _ = cb.chosen_spec(r["experiment"], dec)
            c = r["candidates"][name]
            out[(r["experiment"], r["scene"])] = {"model_psnr": r["model"]["psnr"], "file_psnr": c["psnr"],
                                                  "file_bytes": c["bytes"], "model_bytes": r["full_bytes"],
                                                  "codecs": name}
    return out


def val(args) -> None:
    """Each run's model and its compact file (compact_bytes' codecs for the method) on val."""
    from stdr.data.load import load_scene
    from stdr.eval.evaluate import evaluate_model, machine_name
    dec = json.loads((cb.OUT / "decision.json").read_text())
    for exp in args.experiments:
        for scene in args.scenes:
            rd = cb.run_dir(args.work, exp, scene)
            rec_path = records_to_write(OUT, "records") / "val" / f"{exp}__{scene}.json"
            if rec_path.is_file():
                continue
            if not (rd / "metrics.json").is_file():
                print(f"[compact_grid] val {exp} {scene}: not trained yet", flush=True)
                continue
            cfg, full = cb._load(rd)
            scn = load_scene(cfg.data, ("train", "val"), base=str(ROOT), seed=cfg.seed)
            name, spec = cb.chosen_spec(exp, dec)
            base = evaluate_model(full, scn.frames("val"), fps_warmup=0)
            with tempfile.TemporaryDirectory() as tmp:
                w, small = cb._file_model(full, cfg, spec, Path(tmp), scn.frames("train"))
                r = evaluate_model(small, scn.frames("val"), fps_warmup=0)
            rec = {"experiment": exp, "scene": scene, "seed": SEED, "split": "val", "grid": CANDIDATE, "codecs": name,
                   "model": {"psnr": base["psnr"], "ssim": base["ssim"]}, "file": {"psnr": r["psnr"], "ssim": r["ssim"]},
                   "file_bytes": w["bytes"], "model_bytes": w["full_bytes"], "num_gaussians": base["num_gaussians"],
                   "code": commit(), "machine": machine_name(), "date": time.strftime("%Y-%m-%d")}
            rec_path.parent.mkdir(parents=True, exist_ok=True)
            rec_path.write_text(json.dumps(rec, indent=1) + "\n")
            print(f"[compact_grid] val {exp} {scene}: file {r['psnr']:.3f} dB, {w['bytes'] / 2**20:.2f} MiB", flush=True)


def load(split: str) -> list[dict]:
    return [json.loads(p.read_text()) for p in sorted((records_in(OUT, "records") / split).glob("*.json"))]


def decide_records(recs: list[dict], ref: dict) -> dict:
    """The protocol's rule: per method, the mean over its scenes of val PSNR(file, candidate) -
    val PSNR(file, 32 channels) >= BOUND, for both methods, every run measured."""
    rows = {}
    for exp in EXPERIMENTS:
        rs = [r for r in recs if r["experiment"] == exp and (exp, r["scene"]) in ref]
        deltas = [r["file"]["psnr"] - ref[(exp, r["scene"])]["file_psnr"] for r in rs]
        rows[exp] = {"runs": len(rs), "of": len(SCENES), "delta_mean": statistics.mean(deltas) if deltas else None,
                     "delta_worst": min(deltas) if deltas else None,
                     "bytes_ratio": math.exp(statistics.mean(math.log(r["file_bytes"] / ref[(exp, r["scene"])]["file_bytes"])
                                                             for r in rs)) if rs else None}
    complete = all(v["runs"] == len(SCENES) for v in rows.values())
    adopt = complete and all(v["delta_mean"] >= BOUND for v in rows.values())
    return {"candidate": CANDIDATE, "bound": BOUND, "complete": complete, "adopt": adopt, "per_method": rows}


def decide(args=None) -> None:
    out = {**decide_records(load("val"), reference()), "code": commit(), "date": time.strftime("%Y-%m-%d %H:%M")}
    (OUT / "decision.json").write_text(json.dumps(out, indent=1) + "\n")
    (OUT / "table_val.md").write_text(table_val())
    print(json.dumps(out, indent=1))


def table_val() -> str:
    recs, ref = load("val"), reference()
    dec = json.loads((OUT / "decision.json").read_text()) if (OUT / "decision.json").is_file() else {}
    lines = ["# A 16-channel HexPlane for 4DGS's compact file, on val (generated by `python -m studies.compact_grid decide`)",
             "", f"Records: {len(recs)} of {len(EXPERIMENTS) * len(SCENES)} runs (`compact=on`, budget=cpu, seed {SEED}, "
             f"{' '.join(CANDIDATE['overrides'])}); code {', '.join(sorted({r['code'] for r in recs})) or '-'}; machine "
             f"{'; '.join(sorted({r['machine'] for r in recs})) or '-'}. Reference: the compact_bytes run of the same "
             "method, scene and seed (32 channels), its file with the same codecs. Rule: protocol.md.", "",
             "| method | scene | file PSNR, 32 ch | file PSNR, 16 ch | Δ | file MiB, 32 ch | file MiB, 16 ch | model PSNR, 16 ch |",
             "|---|---|---|---|---|---|---|---|"]
    for r in recs:
        f = ref[(r["experiment"], r["scene"])]
        lines.append(f"| {r['experiment']} | {r['scene']} | {f['file_psnr']:.3f} | {r['file']['psnr']:.3f} | "
                     f"{r['file']['psnr'] - f['file_psnr']:+.3f} | {f['file_bytes'] / 2**20:.2f} | "
                     f"{r['file_bytes'] / 2**20:.2f} | {r['model']['psnr']:.3f} |")
    if dec:
        lines += ["", "## Decision", "", f"{dec['date']}, bound {dec['bound']:+.2f} dB per method:", ""]
        for exp, v in dec["per_method"].items():
            if v["delta_mean"] is not None:
                lines.append(f"* {exp}: {v['runs']} of {v['of']} scenes, mean Δ {v['delta_mean']:+.3f} dB "
                             f"(worst scene {v['delta_worst']:+.3f}), file bytes {v['bytes_ratio']:.3f}x the 32-channel file's")
        lines += ["", f"**{'Adopted' if dec['adopt'] else 'Not adopted'}**" + ("" if dec["complete"] else " (not all runs measured)")]
    return "\n".join(lines) + "\n"


def test(args) -> None:
    """Only if the rule adopted the grid: each run's model and file on test, once (compact_bytes.test_record)."""
    dec = json.loads((OUT / "decision.json").read_text())
    if not dec.get("adopt"):
        raise SystemExit("compact_grid test: the rule did not adopt the grid (decision.json); test is not read")
    cdec = json.loads((cb.OUT / "decision.json").read_text())
    for exp in args.experiments:
        for scene in args.scenes:
            rec_path = records_to_write(OUT, "records") / "test" / f"{exp}__{scene}.json"
            if rec_path.is_file():
                continue
            rec = {**cb.test_record(cb.run_dir(args.work, exp, scene), exp, scene, *cb.chosen_spec(exp, cdec)),
                   "grid": CANDIDATE}
            rec_path.parent.mkdir(parents=True, exist_ok=True)
            rec_path.write_text(json.dumps(rec, indent=1) + "\n")
            print(f"[compact_grid] test {exp} {scene}: {rec['bytes'] / 2**20:.2f} MiB, PSNR {rec['file']['psnr']:.2f}",
                  flush=True)


def table(args=None) -> str:
    """table.md: 4DGS's full model, compact_bytes' file (32 channels) and this study's (16), on test."""
    recs = load("test")
    dec = json.loads((OUT / "decision.json").read_text()) if (OUT / "decision.json").is_file() else {}
    lines = ["# A 16-channel HexPlane for 4DGS's compact file, on test (generated by `python -m studies.compact_grid table`)", ""]
    if not recs:
        lines.append("Not adopted by the rule on val: test not read." if dec.get("complete") and not dec.get("adopt")
                     else "No test records yet.")
        text = "\n".join(lines) + "\n"
        (OUT / "table.md").write_text(text)
        return text
    full = cb.full_records()
    old = {(r["experiment"], r["scene"]): r for r in (json.loads(p.read_text()) for p in
                                                      sorted((records_in(cb.OUT, "records") / "test").glob("*.json")))}
    lines += [f"Records: {len(recs)} runs (`compact=on`, budget=cpu, seed {SEED}, {' '.join(CANDIDATE['overrides'])}); code "
              f"{', '.join(sorted({r['code'] for r in recs}))}; machine {'; '.join(sorted({r['machine'] for r in recs}))}. "
              "Full: the compactness study's test records; 32 channels: compact_bytes' test records (its file, the same "
              "seed, another training); 16 channels: this study's runs, their files with the same codecs.", "",
              "| method | scenes | model | PSNR | SSIM | LPIPS | MiB | FPS |", "|---|---|---|---|---|---|---|---|"]
    targets, m = [], statistics.mean
    for exp, rs in cb.by_method(recs):
        fs, os_ = [full[(exp, r["scene"])] for r in rs], [old[(exp, r["scene"])] for r in rs]
        cs = [full[(exp, r["scene"], "compact")] for r in rs]
        for label, vals, mib in (("full", fs, [f["model_mb"] for f in fs]),
                                 ("file, 32 ch (compact_bytes)", [o["file"] for o in os_], [o["bytes"] / 2**20 for o in os_]),
                                 ("compact=on model, 16 ch", [r["model"] for r in rs], [r["model_bytes"] / 2**20 for r in rs]),
                                 ("file, 16 ch", [r["file"] for r in rs], [r["bytes"] / 2**20 for r in rs])):
            lines.append(f"| {exp} | {len(rs)} | {label} | {m(v['psnr'] for v in vals):.2f} | {m(v['ssim'] for v in vals):.4f} | "
                         f"{m(v['lpips'] for v in vals):.4f} | {m(mib):.2f} | {m(v['fps'] for v in vals):.1f} |")
        ratio = cb._gmean([(r["bytes"] / 2**20) / f["model_mb"] for r, f in zip(rs, fs)])
        direct = m(r["file"]["psnr"] - f["psnr"] for r, f in zip(rs, fs))
        chain = (m(r["file"]["psnr"] - o["file"]["psnr"] for r, o in zip(rs, os_))
                 + m(o["file"]["psnr"] - o["model"]["psnr"] for o in os_) + m(c["psnr"] - f["psnr"] for c, f in zip(cs, fs)))
        fps_own = cb._gmean([r["file"]["fps"] / r["model"]["fps"] for r in rs])
        fps_old = cb._gmean([r["file"]["fps"] / o["model"]["fps"] for r, o in zip(rs, os_)])
        targets += [(exp, "file bytes / full model bytes", "<= 0.15", ratio, ratio <= 0.15),
                    (exp, "PSNR file - full, dB (direct)", ">= -0.1", direct, direct >= -0.1),
                    (exp, "PSNR file - full, dB (chain through the 32-channel file)", "(reported)", chain, None),
                    (exp, "FPS file / its compact=on model (one process)", ">= 1", fps_own, fps_own >= 1),
                    (exp, "FPS file / the 32-channel compact=on model (another process)", "(reported)", fps_old, None)]
    lines += ["", "Targets (ratios: geometric mean over the scenes of the per-scene ratio):", "",
              *cb.targets_lines(targets)]
    text = "\n".join(lines) + "\n"
    (OUT / "table.md").write_text(text)
    return text


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    for name in ("train", "val", "test"):
        cb.add_run_args(sub.add_parser(name), EXPERIMENTS, SCENES)
    sub.add_parser("decide")
    sub.add_parser("table")
    a = ap.parse_args(argv)
    globals()[a.cmd](a)


if __name__ == "__main__":
    main()
