"""Compact bytes (research/measurements/compact_bytes/protocol.md): the `compact=on` preset's
runs of the eight methods at `budget=cpu`, seed 2, and the compact model file's codecs chosen on val
by the protocol's rule, then read once on test.

    # 1. train the runs (resumable: a run with its metrics.json is skipped); one thread a run
    python -m studies.compact_bytes train DNERF_ROOT --work WORK [--scenes ...] [--experiments ...]
    # 2. measure the candidates on val (step 1; after `decide`, steps 2 and 3 on top of its choice)
    python -m studies.compact_bytes val DNERF_ROOT --work WORK
    python -m studies.compact_bytes decide            # decision.json and table_val.md (generated)
    # 3. the chosen codecs on test, once; then the table
    python -m studies.compact_bytes test DNERF_ROOT --work WORK
    python -m studies.compact_bytes where --work WORK # the chosen file's bytes by part (no render)
    python -m studies.compact_bytes table             # table.md (generated)

Records (with the code commit and machine) go to research/measurements/compact_bytes/records/{val,test,where}/.
The full models are the compactness study's test records (research/measurements/compact_prune,
records.tar.xz, seed 2), not retrained.
"""
from __future__ import annotations

import argparse
import io
import json
import statistics
import tarfile
import tempfile
import time
from pathlib import Path

from studies.common import commit, gmean, records_in, records_to_write
from stdr.tools.runqueue import run_one

ROOT = Path(__file__).resolve().parents[1]

OUT = ROOT / "research" / "measurements" / "compact_bytes"
SCENES = ("bouncingballs", "hellwarrior", "jumpingjacks", "standup")
BASELINES = ("deform", "scgs", "spgs", "4dgs")
EXPERIMENTS = tuple(f"dnerf_{b}{s}" for b in BASELINES for s in ("", "_stdr"))
SEED = 2
#: the file's bytes over the full model's (paired), at most: 0.15 in protocol.md, 0.10 from amendment 5
RATIO_BOUND = 0.10
#: step 1 of the rule, largest first (studies/compact_file.py's variants)
STEP1 = ("default", "q8m16", "q8m16_vq4096", "q8m16_vq1024", "q8m16_vq256", "q8m16_vq1024_ft", "q8m16_vq256_ft")
#: step 2 (4dgs methods) and step 3 (+STDR methods), on top of step 1's choice, largest first
GRID = {"g16": {}, "g8": {"state:grids": "q8"}, "g4": {"state:grids": "q4"}}
#: step 3 (amendment 3: runs of STDR's default since 2026-11-28, stdr.mask_after_freeze=false)
MASK = {"m8": {"stdr_mask": "q8"}, "derived8": {"stdr_mask": "derived", "stdr_cond": "q8"},
        "derived4": {"stdr_mask": "derived", "stdr_cond": "q4"},
        "derivedvq": {"stdr_mask": "derived", "stdr_cond": "vq:1024"}}
FULL_RECORDS = ROOT / "research" / "measurements" / "compact_prune" / "records.tar.xz"


def run_dir(work: Path, exp: str, scene: str) -> Path:
    return Path(work) / exp / scene


# ------------------------------------------------------------------------------------------ train
def train(args, overrides=(), tag: str = "compact_bytes", refuse_former_default: bool = True) -> None:
    """Train each (experiment, scene) run of `args` that has no metrics.json: the study's
    `compact=on` command plus `overrides` (compact_grid's grid), one at a time through the project's
    run queue (stdr-tool queue; the run's output in RUN/stdout.log)."""
    for exp in args.experiments:
        for scene in args.scenes:
            rd = run_dir(args.work, exp, scene)
            if refuse_former_default:
                _refuse_a_former_default(rd)
            if (rd / "metrics.json").is_file():
                continue
            rd.parent.mkdir(parents=True, exist_ok=True)
            keys = [f"experiment={exp}", "compact=on", "budget=cpu", f"seed={SEED}",
                          f"data.path={Path(args.dnerf) / scene}", "train.progress=false", "eval.save_images=false",
                          "train.image_every=0", *overrides]
            t0 = time.time()
            print(f"[{tag}] {time.strftime('%T')} train {exp} {scene}", flush=True)
            try:
                run_one(keys, rd, threads=args.threads, log=lambda m: None)
                said = "done"
            except RuntimeError as e:
                said = f"FAILED: {e}"
            print(f"[{tag}]   {said} in {time.time() - t0:.0f} s", flush=True)


def _refuse_a_former_default(rd: Path) -> None:
    """A +STDR run folder trained with stdr.mask_after_freeze=true (the default before 2026-11-28,
    protocol amendment 3) is not one of this study's runs: move it aside rather than measure it."""
    import yaml
    f = rd / "config.yaml"
    if not f.is_file():
        return
    stdr = (yaml.safe_load(f.read_text()) or {}).get("stdr") or {}
    if stdr.get("enabled") and stdr.get("mask_after_freeze") is True:
        raise SystemExit(f"{rd}: trained with stdr.mask_after_freeze=true, STDR's default before 2026-11-28; "
                         "this study's +STDR runs use the current default (protocol amendment 3). Move the "
                         f"folder aside (e.g. to {rd.parent.parent / 'gated' / rd.parent.name / rd.name}) and run again")


# ------------------------------------------------------------------------------------------ measure
def _load(rd: Path):
    from stdr.store import load_config
    from stdr.model import load_model
    from stdr.io.checkpoint import CKPT
    cfg = load_config(rd / "config.yaml")
    cfg.device = "cpu"
    return cfg, load_model(rd / CKPT, "cpu", cfg)


def _file_model(model, cfg, spec: dict, tmp: Path, train_frames=None):
    from stdr.compact.pack import write_compact
    from stdr.model import load_model
    path = tmp / "m.stdrc"
    rec = write_compact(model, path, spec, train_frames if spec.get("finetune") else None)
    return rec, load_model(path, "cpu", cfg)


def _mask_kl(full, small) -> float | None:
    """Mean over Gaussians of KL(p || p'), p = softmax over time of the stored mask's logits (the
    separated field's input), p' the decoded mask's."""
    import torch

    from stdr.plugins.stdr.mask import logits_of
    from stdr.plugins.stdr.mask import MASK_KEY
    if MASK_KEY not in full.params or MASK_KEY not in small.params:  # a derived form stores no mask
        return None
    lp = torch.log_softmax(logits_of(full.params[MASK_KEY].detach()).double(), 1)
    lq = torch.log_softmax(logits_of(small.params[MASK_KEY].detach()).double(), 1)
    return float((lp.exp() * (lp - lq)).sum(1).mean())


def spec_of(step1: str, grid: str | None = None, mask: str | None = None) -> dict:
    from studies.compact_file import VARIANTS
    spec = dict(VARIANTS[step1])
    if grid:
        spec.update(GRID[grid])
    if mask:
        spec.update(MASK[mask])
    return spec


def candidates(exp: str, decision: dict | None) -> dict[str, dict]:
    """name -> spec: step 1's candidates; with a decision, steps 2 and 3 on top of its choice."""
    out = {c: spec_of(c) for c in STEP1}
    if decision:
        s1 = decision["step1"]
        if "4dgs" in exp:
            out.update({f"{s1}+{g}": spec_of(s1, g) for g in GRID})
        if exp.endswith("_stdr") and ("4dgs" not in exp or decision.get("step2")):
            g = decision["step2"] if "4dgs" in exp else "g16"
            out.update({f"{s1}+{g}+{m}": spec_of(s1, g, m) for m in MASK})
    return out


def val(args) -> None:
    from stdr.data.load import load_scene
    from stdr.eval.evaluate import evaluate_model, machine_name
    decision = json.loads((OUT / "decision.json").read_text()) if (OUT / "decision.json").is_file() else None
    for exp in args.experiments:
        for scene in args.scenes:
            rd = run_dir(args.work, exp, scene)
            rec_path = records_to_write(OUT, "records") / "val" / f"{exp}__{scene}.json"
            rec = json.loads(rec_path.read_text()) if rec_path.is_file() else None
            todo = candidates(exp, decision)
            if rec is not None and all(c in rec["candidates"] for c in todo):
                continue
            if not (rd / "metrics.json").is_file():
                print(f"[compact_bytes] val {exp} {scene}: not trained yet", flush=True)
                continue
            _refuse_a_former_default(rd)
            cfg, full = _load(rd)
            scn = load_scene(cfg.data, ("train", "val"), base=str(ROOT), seed=cfg.seed)
            frames, train_frames = scn.frames("val"), scn.frames("train")
            base = evaluate_model(full, frames, fps_warmup=0)
            rec = rec or {"experiment": exp, "scene": scene, "seed": SEED, "split": "val",
                          "full_bytes": None, "model": {"psnr": base["psnr"], "ssim": base["ssim"]},
                          "num_gaussians": base["num_gaussians"], "candidates": {}}
            for name, spec in todo.items():
                if name in rec["candidates"]:
                    continue
                with tempfile.TemporaryDirectory() as tmp:
                    w, small = _file_model(full, cfg, spec, Path(tmp), train_frames)
                    r = evaluate_model(small, frames, fps_warmup=0)
                rec["full_bytes"] = w["full_bytes"]
                rec["candidates"][name] = {"bytes": w["bytes"], "spec": w["spec"], "psnr": r["psnr"], "ssim": r["ssim"],
                                           "delta_psnr": r["psnr"] - base["psnr"], "delta_ssim": r["ssim"] - base["ssim"],
                                           "mask_kl": _mask_kl(full, small)}
                print(f"[compact_bytes] val {exp} {scene} {name}: {w['bytes'] / 2**20:.2f} MiB, "
                      f"{r['psnr'] - base['psnr']:+.3f} dB", flush=True)
            rec.update({"code": commit(), "machine": machine_name(), "date": time.strftime("%Y-%m-%d")})
            rec_path.parent.mkdir(parents=True, exist_ok=True)
            rec_path.write_text(json.dumps(rec, indent=1) + "\n")


# ------------------------------------------------------------------------------------------ decide
def load_val() -> list[dict]:
    return [json.loads(p.read_text()) for p in sorted((records_in(OUT, "records") / "val").glob("*.json"))]


def _smallest_passing(names, recs, bound_all, bound_method, methods):
    """The smallest (mean bytes) of `names` whose delta PSNR meets the bounds; with its numbers. A
    candidate not yet measured on every run of `methods` (every scene) cannot pass: a partial
    mean is no decision."""
    rows, need = [], len(methods) * len(SCENES)
    for n in names:
        rs = [r for r in recs if n in r["candidates"] and r["experiment"] in methods]
        if not rs:
            continue
        d_all = statistics.mean(r["candidates"][n]["delta_psnr"] for r in rs)
        per = {m: statistics.mean(r["candidates"][n]["delta_psnr"] for r in rs if r["experiment"] == m)
               for m in sorted({r["experiment"] for r in rs})}
        ok = (len(rs) == need and (bound_all is None or d_all >= bound_all)
              and all(v >= bound_method for v in per.values()))
        rows.append({"name": n, "runs": len(rs), "of": need, "mean_bytes": statistics.mean(r["candidates"][n]["bytes"] for r in rs),
                     "delta_all": d_all, "delta_per_method": per, "passes": ok})
    passing = [r for r in rows if r["passes"]]
    # equal bytes (a fine-tuned codebook and its k-means form): the smaller loss
    return (min(passing, key=lambda r: (r["mean_bytes"], -r["delta_all"]))["name"] if passing else None), rows


def decide_records(recs: list[dict], prev: dict) -> dict:
    """The protocol's rule on val records: step 1 always; steps 2 and 3 once `prev` (the last
    decision) chose the same step 1, so that their candidates were measured on top of it."""
    s1, rows1 = _smallest_passing(STEP1, recs, -0.05, -0.1, EXPERIMENTS)
    out = {"runs": len(recs), "complete": len(recs) == len(EXPERIMENTS) * len(SCENES), "step1": s1, "step1_rows": rows1}
    if not (s1 and prev.get("step1") == s1):
        return out
    s2, rows2 = _smallest_passing([f"{s1}+{g}" for g in GRID], recs, None, -0.05, [e for e in EXPERIMENTS if "4dgs" in e])
    out.update({"step2": s2.split("+")[1] if s2 else None, "step2_rows": rows2})
    if not out["step2"]:
        return out
    # one mask form for the four +STDR methods: each method reads it on top of its own earlier
    # choices (4dgs+STDR: step 2's grid), and every method's mean must pass
    rows3 = []
    for m in MASK:
        per, sizes, runs = {}, [], 0
        for b in BASELINES:
            name = f"{s1}+{out['step2'] if b == '4dgs' else 'g16'}+{m}"
            rs = [r for r in recs if r["experiment"] == f"dnerf_{b}_stdr" and name in r["candidates"]]
            if rs:
                per[b] = statistics.mean(r["candidates"][name]["delta_psnr"] for r in rs)
                sizes += [r["candidates"][name]["bytes"] for r in rs]
                runs += len(rs)
        need = len(BASELINES) * len(SCENES)  # every +STDR run: a partial mean is no decision
        rows3.append({"name": m, "delta_per_method": per, "mean_bytes": statistics.mean(sizes) if sizes else None,
                      "runs": runs, "of": need,
                      "passes": runs == need and all(v >= -0.05 for v in per.values())})
    passing = [r for r in rows3 if r["passes"]]
    out.update({"step3": min(passing, key=lambda r: r["mean_bytes"])["name"] if passing else None, "step3_rows": rows3,
                "step3_measured": min(r["runs"] for r in rows3) == len(BASELINES) * len(SCENES)})
    return out


def decide(args) -> None:
    prev = json.loads((OUT / "decision.json").read_text()) if (OUT / "decision.json").is_file() else {}
    out = {**decide_records(load_val(), prev), "code": commit(), "date": time.strftime("%Y-%m-%d %H:%M")}
    (OUT / "decision.json").write_text(json.dumps(out, indent=1) + "\n")
    print(json.dumps({k: v for k, v in out.items() if not k.endswith("rows")}, indent=1))


def preset_spec(exp: str) -> tuple[str, dict]:
    """("compact=on", the file's spec `compact=on` writes for `exp`): its pack section as stdr-train
    composes it, which is this study's decision with compact_state's choices on top
    (tests/test_compact_preset.py pins that)."""
    from stdr.compact.pack import spec_of_config
    from stdr.store import compose_config
    return "compact=on", spec_of_config(compose_config([f"experiment={exp}", "compact=on"]).pack)


def codecs_of(exp: str, args) -> tuple[str, dict]:
    """The codecs `test` and `where` write: the preset's (--preset), or decision.json's choice."""
    if getattr(args, "preset", False):
        return preset_spec(exp)
    dec = json.loads((OUT / "decision.json").read_text())
    if not dec.get("complete") or not dec.get("step3"):
        raise SystemExit("compact_bytes: decision.json is not complete (run val and decide until steps 1-3 are chosen)")
    return chosen_spec(exp, dec)


def chosen_spec(exp: str, dec: dict) -> tuple[str, dict]:
    g = dec.get("step2") if "4dgs" in exp else None
    m = dec.get("step3") if exp.endswith("_stdr") else None
    name = "+".join(x for x in (dec["step1"], g, m) if x)
    return name, spec_of(dec["step1"], g, m)


# ------------------------------------------------------------------------------------------ test
def test_record(rd: Path, exp: str, scene: str, name: str, spec: dict) -> dict:
    """A run's model and its compact file (`spec`) on test, once: each rendered with LPIPS, FPS the
    median of 3 passes, the two models' passes in the same process one after the other."""
    from stdr.store import load_config
    from stdr.data.load import load_scene
    from stdr.eval.evaluate import evaluate_model, machine_name, make_lpips
    cfg, full = _load(rd)
    lp = make_lpips(load_config(rd / "config.yaml").eval)
    scn = load_scene(cfg.data, ("train", "test"), base=str(ROOT), seed=cfg.seed)
    with tempfile.TemporaryDirectory() as tmp:
        w, small = _file_model(full, cfg, spec, Path(tmp), scn.frames("train"))
        load_s = _load_seconds(Path(tmp) / "m.stdrc", cfg)
        res = {}
        for label, m in (("model", full), ("file", small)):
            r = evaluate_model(m, scn.frames("test"), lpips_fn=lp, fps_warmup=3, fps_repeats=3)
            res[label] = {k: r[k] for k in ("psnr", "ssim", "lpips", "fps", "num_gaussians")}
    return {"experiment": exp, "scene": scene, "seed": SEED, "split": "test", "codecs": name, "spec": w["spec"],
            "bytes": w["bytes"], "model_bytes": w["full_bytes"], "load_s": load_s, **res,
            "code": commit(), "machine": machine_name(), "date": time.strftime("%Y-%m-%d")}


def _load_seconds(path: Path, cfg, repeats: int = 3) -> float:
    """The median wall time of reading the compact file into a model (load_model: check, entropy
    decode, codecs), over `repeats` reads."""
    from stdr.model import load_model
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        load_model(path, "cpu", cfg)
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def test(args) -> None:
    """The chosen codecs (or --preset, compact=on's) on test, once per run (test_record)."""
    for exp in args.experiments:
        for scene in args.scenes:
            rec_path = records_to_write(OUT, "records") / "test" / f"{exp}__{scene}.json"
            if rec_path.is_file():
                continue
            rd = run_dir(args.work, exp, scene)
            _refuse_a_former_default(rd)
            rec = test_record(rd, exp, scene, *codecs_of(exp, args))
            rec_path.parent.mkdir(parents=True, exist_ok=True)
            rec_path.write_text(json.dumps(rec, indent=1) + "\n")
            print(f"[compact_bytes] test {exp} {scene} {rec['codecs']}: {rec['bytes'] / 2**20:.2f} MiB, "
                  f"PSNR {rec['file']['psnr']:.2f} (model {rec['model']['psnr']:.2f})", flush=True)


def where_bytes(model, spec: dict) -> dict:
    """The bytes of `model`'s compact file with `spec`, by part: each per-Gaussian table (its
    codebook included), the deformation module's state, each plug-in's, and the rest (`other`). The fine-tune moves
    codewords and quantized values and changes no byte, so the spec's `finetune` is left out."""
    from stdr.compression.codecs import nbytes
    from stdr.compression.file import encode_model
    m = encode_model(model, {k: v for k, v in spec.items() if k not in ("finetune", "finetune_state")})["model"]
    out = {"num_gaussians": model.num_gaussians, "params": {k: nbytes(v) for k, v in m["params"].items()},
           "deform": nbytes(m["deform"]), "plugins": {k: nbytes(v) for k, v in m["plugins"].items()}}
    # the model entry's other tensors (background, training times, ...)
    out["other"] = nbytes(m) - sum(out["params"].values()) - out["deform"] - sum(out["plugins"].values())
    return out


def where(args) -> None:
    """records/where/: the chosen codecs' file of every run, its bytes by part (where_bytes)."""
    from stdr.eval.evaluate import machine_name
    for exp in args.experiments:
        for scene in args.scenes:
            rd = run_dir(args.work, exp, scene)
            rec_path = records_to_write(OUT, "records") / "where" / f"{exp}__{scene}.json"
            if rec_path.is_file() or not (rd / "metrics.json").is_file():
                continue
            _refuse_a_former_default(rd)
            _, full = _load(rd)
            name, spec = codecs_of(exp, args)
            rec = {"experiment": exp, "scene": scene, "seed": SEED, "codecs": name, **where_bytes(full, spec),
                   "code": commit(), "machine": machine_name(), "date": time.strftime("%Y-%m-%d")}
            rec_path.parent.mkdir(parents=True, exist_ok=True)
            rec_path.write_text(json.dumps(rec, indent=1) + "\n")


def by_method(recs: list[dict]) -> list[tuple[str, list[dict]]]:
    """The records grouped by experiment, in EXPERIMENTS' order, experiments without records left out."""
    return [(exp, rs) for exp in EXPERIMENTS if (rs := [r for r in recs if r["experiment"] == exp])]


def where_rows(recs: list[dict]) -> list[dict]:
    """Per method (means over its scenes): Gaussians, bytes a Gaussian (the per-Gaussian tables over
    N), the fixed part (networks, grids, plug-in state) and the total, all in bytes."""
    out = []
    for exp, rs in by_method(recs):
        m = statistics.mean
        fixed = [r["deform"] + sum(r["plugins"].values()) + r.get("other", 0) for r in rs]
        tables = [sum(r["params"].values()) for r in rs]
        keys = sorted({k for r in rs for k in r["params"]})
        out.append({"experiment": exp, "scenes": len(rs), "num_gaussians": m(r["num_gaussians"] for r in rs),
                    "per_gaussian": m(t / r["num_gaussians"] for t, r in zip(tables, rs)),
                    "by_table": {k: m(r["params"].get(k, 0) / r["num_gaussians"] for r in rs) for k in keys},
                    "fixed": m(fixed), "total": m(t + f for t, f in zip(tables, fixed))})
    return out


# ------------------------------------------------------------------------------------------ tables
def full_records() -> dict:
    """(experiment, scene) -> the compactness study's test metrics (seed 2) of the full model, and
    (experiment, scene, "compact") -> of its compact branch (the same trunk: a paired comparison)."""
    out = {}
    with tarfile.open(FULL_RECORDS) as tar:
        for m in tar.getmembers():
            parts = m.name.split("/")
            if len(parts) == 5 and parts[0] == "test" and parts[3] in ("full", "compact") and parts[4] == "metrics.json":
                key = (parts[1], parts[2]) if parts[3] == "full" else (parts[1], parts[2], "compact")
                out[key] = json.load(io.TextIOWrapper(tar.extractfile(m)))["test"]
    return out


def table_val() -> str:
    recs = load_val()
    dec = json.loads((OUT / "decision.json").read_text()) if (OUT / "decision.json").is_file() else {}
    lines = ["# Compact file codecs on val (generated by `python -m studies.compact_bytes decide`)", "",
             f"Records: {len(recs)} of {len(EXPERIMENTS) * len(SCENES)} runs (`compact=on`, budget=cpu, seed {SEED}); "
             f"code {', '.join(sorted({r['code'] for r in recs})) or '-'}; machine "
             f"{'; '.join(sorted({r['machine'] for r in recs})) or '-'}. Rule: protocol.md.", "",
             "ΔPSNR = val PSNR of the model read back from the file − the run's model's; file / model = bytes of "
             "the file's tensors over the run's model's (geometric mean over the scenes).", ""]
    names = sorted({n for r in recs for n in r["candidates"]}, key=lambda n: (n.count("+"), n))
    lines += ["| method | candidate | scenes | file MiB | file / model | ΔPSNR mean | ΔPSNR worst scene | mask KL(p‖p′) |",
              "|---|---|---|---|---|---|---|---|"]
    for exp in EXPERIMENTS:
        for n in names:
            rs = [r for r in recs if r["experiment"] == exp and n in r["candidates"]]
            if not rs:
                continue
            c = [r["candidates"][n] for r in rs]
            kl = [x["mask_kl"] for x in c if x.get("mask_kl") is not None]
            lines.append(f"| {exp} | {n} | {len(rs)} | {statistics.mean(x['bytes'] for x in c) / 2**20:.3f} | "
                         f"{gmean([x['bytes'] / r['full_bytes'] for x, r in zip(c, rs)]):.1%} | "
                         f"{statistics.mean(x['delta_psnr'] for x in c):+.3f} | {min(x['delta_psnr'] for x in c):+.3f} | "
                         f"{f'{statistics.mean(kl):.2e}' if kl else '–'} |")
    lines += ["", "## Decision", ""]
    if not dec:
        lines.append("Not decided yet.")
    else:
        lines.append(f"From {dec['runs']} runs ({'all' if dec['complete'] else 'not all'} of them), {dec['date']}:")
        lines.append("")
        for key, what in (("step1", "per-Gaussian attributes"), ("step2", "4dgs grid"), ("step3", "STDR's mask")):
            if key == "step3" and key in dec and not dec.get("step3_measured", True):
                lines.append(f"* step 3 ({what}): not measured on every +STDR run yet")
            elif key in dec:
                lines.append(f"* step {key[-1]} ({what}): **{dec[key] or 'none passes'}**")
    return "\n".join(lines) + "\n"


def test_rows(recs: list[dict], full: dict) -> list[dict]:
    """Per method (mean over its scenes): full, compact=on and file, each {label, psnr, ssim, lpips, mib, fps}."""
    out = []
    for exp, rs in by_method(recs):
        fs = [full[(exp, r["scene"])] for r in rs]
        m = statistics.mean
        out.append({"experiment": exp, "scenes": len(rs), "codecs": rs[0]["codecs"], "models": [
            {"label": "full", **{k: m(f[k] for f in fs) for k in ("psnr", "ssim", "lpips", "fps")},
             "mib": m(f["model_mb"] for f in fs)},
            {"label": "compact=on", **{k: m(r["model"][k] for r in rs) for k in ("psnr", "ssim", "lpips", "fps")},
             "mib": m(r["model_bytes"] / 2**20 for r in rs)},
            {"label": "file", **{k: m(r["file"][k] for r in rs) for k in ("psnr", "ssim", "lpips", "fps")},
             "mib": m(r["bytes"] / 2**20 for r in rs)}]})
    return out


def chart(rows: list[dict], out: Path, stamp: str = "") -> Path:
    """PSNR against MiB (log) per method: full (circle), compact=on (square), the file (diamond,
    labelled with its FPS), joined; colour per baseline, hollow plain, filled +STDR."""
    import csv

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from stdr.eval.chart import palette_png
    colors = dict(zip(BASELINES, ("tab:blue", "tab:orange", "tab:green", "tab:red")))
    fig, ax = plt.subplots(figsize=(7.5, 4.6))
    for row in rows:
        b = row["experiment"].removeprefix("dnerf_").removesuffix("_stdr")
        stdr = row["experiment"].endswith("_stdr")
        xs, ys = [m["mib"] for m in row["models"]], [m["psnr"] for m in row["models"]]
        ax.plot(xs, ys, "-", color=colors[b], lw=0.8, alpha=0.6)
        for m, marker in zip(row["models"], ("o", "s", "D")):
            ax.plot(m["mib"], m["psnr"], marker, color=colors[b], mfc=colors[b] if stdr else "white", ms=6)
        f = row["models"][2]
        ax.annotate(f"{f['fps']:.0f} FPS", (f["mib"], f["psnr"]), textcoords="offset points", xytext=(4, -10), fontsize=6)
    ax.set_xscale("log")
    ax.set_xlabel("MiB (log): full model ○, compact=on □, compact file ◆")
    ax.set_ylabel("test PSNR (dB), mean over scenes")
    handles = [plt.Line2D([], [], color=c, marker="o", ls="", mfc=c, label=b) for b, c in colors.items()]
    ax.legend(handles=handles, fontsize=7, title="baseline (filled: +STDR)", title_fontsize=7, loc="center left", bbox_to_anchor=(1.01, 0.5))
    if stamp:
        fig.text(0.01, -0.02, stamp, fontsize=6, color="0.35")
    ax.set_title("Bytes, PSNR and render FPS (budget=cpu, seed 2, four shared D-NeRF scenes)", fontsize=9)
    out.mkdir(parents=True, exist_ok=True)
    png = out / "size_accuracy_bytes.png"
    fig.savefig(png, dpi=130, bbox_inches="tight")
    plt.close(fig)
    palette_png(png)
    with open(out / "size_accuracy_bytes.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["method", "model", "mib", "psnr", "ssim", "lpips", "fps"])
        w.writerows([[r["experiment"], m["label"], m["mib"], m["psnr"], m["ssim"], m["lpips"], m["fps"]]
                     for r in rows for m in r["models"]])
    return png


def table(out: Path = OUT, full: dict | None = None) -> str:
    recs = [json.loads(p.read_text()) for p in sorted((records_in(out, "records") / "test").glob("*.json"))]
    full = full_records() if full is None else full
    lines = ["# Full, today's compact and the compact file on test (generated by `python -m studies.compact_bytes table`)", ""]
    if not recs:
        return "\n".join(lines + ["No test records yet."]) + "\n"
    lines += [f"Records: {len(recs)} runs (`compact=on`, budget=cpu, seed {SEED}, four shared D-NeRF scenes); code "
              f"{', '.join(sorted({r['code'] for r in recs}))}; machine {'; '.join(sorted({r['machine'] for r in recs}))}. "
              "Full: the compactness study's test records (same seed). Codecs: "
              + ("those `compact=on` writes (this study's decision.json with compact_state's choices, both on val). "
                 if all(r["codecs"] == "compact=on" for r in recs) else "decision.json (chosen on val, protocol.md). ") +
              "FPS of the run's model and of the file's model are measured one after the other in one process "
              "(median of 3 passes); the full model's FPS is from its own evaluation, on another machine. The file's MiB "
              "are those of the file written when test was read (the records' code); `where` below counts the same "
              "models' files in the format of its own code.", "",
              "| method | scenes | model | PSNR | SSIM | LPIPS | MiB | FPS |", "|---|---|---|---|---|---|---|---|"]
    rows = test_rows(recs, full)
    by = {}
    for r in recs:
        by.setdefault(r["experiment"], []).append(r)
    targets = []
    for row in rows:
        exp, rs = row["experiment"], by[row["experiment"]]
        fs = [full[(exp, r["scene"])] for r in rs]
        for m in row["models"]:
            label = f"file ({row['codecs']})" if m["label"] == "file" else m["label"]
            lines.append(f"| {exp} | {row['scenes']} | {label} | {m['psnr']:.2f} | {m['ssim']:.4f} | {m['lpips']:.4f} | "
                         f"{m['mib']:.2f} | {m['fps']:.1f} |")
        # paired (amendment 2): the file against this run's model, times the compactness study's
        # compact branch against its full trunk (same run up to the first pruning event)
        cs = [full.get((exp, r["scene"], "compact")) for r in rs]
        paired = all(c is not None for c in cs)
        if paired:
            ratio = gmean([(r["bytes"] / r["model_bytes"]) * (c["model_mb"] / f["model_mb"]) for r, c, f in zip(rs, cs, fs)])
            dpsnr = (statistics.mean(r["file"]["psnr"] - r["model"]["psnr"] for r in rs)
                     + statistics.mean(c["psnr"] - f["psnr"] for c, f in zip(cs, fs)))
            targets += [(exp, "file bytes / full model bytes (paired)", f"<= {RATIO_BOUND}", ratio, ratio <= RATIO_BOUND),
                        (exp, "PSNR file - full, dB (paired)", ">= -0.1", dpsnr, dpsnr >= -0.1)]
        raw_ratio = gmean([(r["bytes"] / 2**20) / f["model_mb"] for r, f in zip(rs, fs)])
        raw = row["models"][2]["psnr"] - row["models"][0]["psnr"]
        fps = gmean([r["file"]["fps"] / r["model"]["fps"] for r in rs])
        targets += [(exp, "file bytes / full model bytes (unpaired)", "(reported)", raw_ratio, None),
                    (exp, "PSNR file - full, dB (unpaired)", "(reported)", raw, None),
                    (exp, "FPS file / compact=on", "(reported)", fps, None)]
    wrecs = [json.loads(p.read_text()) for p in sorted((records_in(out, "records") / "where").glob("*.json"))]
    wtotal = {(r["experiment"], r["scene"]): sum(r["params"].values()) + r["deform"] + sum(r["plugins"].values())
              + r.get("other", 0) for r in wrecs}
    wcode = ", ".join(sorted({r["code"] for r in wrecs}))
    for b in BASELINES:
        a, s = by.get(f"dnerf_{b}", []), by.get(f"dnerf_{b}_stdr", [])
        common = sorted({r["scene"] for r in a} & {r["scene"] for r in s})
        if common:
            bs = {(r["experiment"], r["scene"]): r["bytes"] for r in a + s}
            v = gmean([bs[(f"dnerf_{b}_stdr", sc)] / bs[(f"dnerf_{b}", sc)] for sc in common])
            targets.append((f"dnerf_{b}_stdr", "+STDR file / plain file bytes", "<= 1.25", v, v <= 1.25))
            keys = [(e, sc) for sc in common for e in (f"dnerf_{b}", f"dnerf_{b}_stdr")]
            if all(k in wtotal for k in keys):  # the same models and codecs, the file format of `where`'s code
                v = gmean([wtotal[(f"dnerf_{b}_stdr", sc)] / wtotal[(f"dnerf_{b}", sc)] for sc in common])
                targets.append((f"dnerf_{b}_stdr", f"+STDR file / plain file bytes, format of {wcode} (`where`)",
                                "<= 1.25", v, v <= 1.25))
    ratios = [r["file"]["fps"] / r["model"]["fps"] for r in recs]
    targets.append(("all", f"FPS file / compact=on, geometric mean over the {len(ratios)} runs", ">= 1",
                    gmean(ratios), gmean(ratios) >= 1.0))
    lines += ["", "Targets (ratios: geometric mean over the scenes of the per-scene ratio; paired: this run's file "
              "against its own model, times the compactness study's compact branch against its full trunk, "
              "protocol.md amendment 2; unpaired: against the other study's full run directly):", "",
              *targets_lines(targets)]
    loads = [(r["load_s"], r["model"]["num_gaussians"]) for r in recs if "load_s" in r]
    if loads:
        slow = max(loads)
        lines += ["", f"Loading the file (`load_model`, median of 3 reads, on the records' "
                  f"machine): {min(s for s, _ in loads):.3f} to {slow[0]:.3f} s over {len(loads)} runs; the slowest "
                  f"holds {slow[1]:,} Gaussians."]
    same = all(r["file"].get("num_gaussians", -1) == r["model"].get("num_gaussians", -2) for r in recs)
    lines += ["", f"FPS file / compact=on per run, all {len(ratios)} runs: {min(ratios):.3f} to {max(ratios):.3f} "
              f"(geometric mean {gmean(ratios):.3f})." + (
                  " In every run the file's model renders as many Gaussians as the run's, with its tensors decoded "
                  "to float32, so this spread is the timing's own." if same else "")]
    if wrecs:
        lines += where_section(where_rows(wrecs), wcode)
    if rows:
        chart(rows, out / "charts", f"test records: code {', '.join(sorted({r['code'] for r in recs}))}; "
                                    f"{'; '.join(sorted({r['machine'] for r in recs}))}")
        lines += ["", "![PSNR against MiB: full, compact=on and the compact file, with the file's FPS]"
                      "(charts/size_accuracy_bytes.png)"]
    return "\n".join(lines) + "\n"


def targets_lines(targets: list[tuple]) -> list[str]:
    """The targets table: (method, target, bound, measured, met: True / False / None for reported)."""
    return ["| method | target | bound | measured | met |", "|---|---|---|---|---|",
            *(f"| {exp} | {what} | {bound} | {v:.3f} | {'–' if ok is None else 'yes' if ok else '**no**'} |"
              for exp, what, bound, v, ok in targets)]


def add_run_args(p, experiments, scenes, dnerf: bool = True) -> None:
    """The arguments of a subcommand over run folders: [DNERF] --work --experiments --scenes (--threads)."""
    if dnerf:
        p.add_argument("dnerf", type=Path, help="folder with the D-NeRF scenes")
    p.add_argument("--work", type=Path, required=True, help="the run folders")
    p.add_argument("--experiments", nargs="+", default=list(experiments), choices=experiments)
    p.add_argument("--scenes", nargs="+", default=list(scenes), choices=scenes)
    if dnerf:
        p.add_argument("--threads", type=int, default=1)
    p.add_argument("--preset", action="store_true", help="test / where: the codecs compact=on writes today, not decision.json's")


def where_section(rows: list[dict], code: str = "") -> list[str]:
    """Where the file's bytes are (records/where/), and each +STDR/plain ratio split into its two
    measured factors: the Gaussian count and the bytes STDR adds."""
    lines = ["", f"Where the file's bytes are (`where`, code {code or '-'}: each run's file with the chosen codecs, "
             "its tensors' bytes by part, counted without rendering; means over the scenes; B = bytes):", "",
             "| method | Gaussians | B a Gaussian | of which: largest tables (B a Gaussian) | fixed part KiB | total MiB |",
             "|---|---|---|---|---|---|"]
    for r in rows:
        top = sorted(r["by_table"].items(), key=lambda kv: -kv[1])[:4]
        lines.append(f"| {r['experiment']} | {r['num_gaussians']:,.0f} | {r['per_gaussian']:.1f} | "
                     f"{', '.join(f'`{k}` {v:.1f}' for k, v in top)} | {r['fixed'] / 1024:.1f} | {r['total'] / 2**20:.3f} |")
    by = {r["experiment"]: r for r in rows}
    split = []
    for b in BASELINES:
        a, s = by.get(f"dnerf_{b}"), by.get(f"dnerf_{b}_stdr")
        if a and s:
            # total_s / total_a = (N_s / N_a) x (bytes of +STDR at plain's count / plain's total)
            count = s["num_gaussians"] / a["num_gaussians"]
            split.append(f"| {b} | {s['total'] / a['total']:.3f} | {count:.3f} | "
                         f"{(s['per_gaussian'] - a['per_gaussian']):+.1f} | {(s['fixed'] - a['fixed']) / 1024:+.1f} |")
    if split:
        lines += ["", "+STDR against plain, per baseline (ratio of the mean totals; the target above is the "
                  "geometric mean of per-scene ratios): the Gaussian count's ratio, and what STDR adds a Gaussian "
                  "and to the fixed part:", "",
                  "| baseline | +STDR / plain bytes | Gaussians +STDR / plain | B a Gaussian added | fixed KiB added |",
                  "|---|---|---|---|---|", *split]
    return lines


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    for name in ("train", "val", "test"):
        add_run_args(sub.add_parser(name), EXPERIMENTS, SCENES)
    add_run_args(sub.add_parser("where"), EXPERIMENTS, SCENES, dnerf=False)
    sub.add_parser("decide")
    sub.add_parser("table")
    a = ap.parse_args(argv)
    if a.cmd == "train":
        train(a)
    elif a.cmd == "val":
        val(a)
        (OUT / "table_val.md").write_text(table_val())
    elif a.cmd == "decide":
        decide(a)
        (OUT / "table_val.md").write_text(table_val())
    elif a.cmd == "where":
        where(a)
        (OUT / "table.md").write_text(table())
    elif a.cmd == "test":
        test(a)
        (OUT / "table.md").write_text(table())
    else:
        (OUT / "table.md").write_text(table())
        print((OUT / "table.md").read_text())


if __name__ == "__main__":
    main()
