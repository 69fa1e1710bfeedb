"""The compact model file's bytes and what its codecs cost, measured on trained runs
(research/measurements/compact_file).

    python -m studies.compact_file run RUN_DIR [RUN_DIR ...] [--variants default state16]
    python -m studies.compact_file table

For each run and variant, `stdr-tool pack`'s measurement (stdr/compact/pack.py) into a temporary
file: the bytes of the full model and of the compact file, and val PSNR / SSIM of both renders.
Variants: `default` (stdr.compression.file.DEFAULT_SPEC), `state16` (networks and grids in half
precision too), `all16` (the SH rest in half precision instead of 8 bits), `q8` (every per-Gaussian
tensor but the means in 8 bits with a range per column, STDR's float mask included; networks in
half precision), `q8m16` (as `q8`, the means in 16 bits with a range per axis), `q8m16_sh<d>` (as
`q8m16`, the SH rest kept to degree d, the higher bands dropped without a fine-tune), `q8m16_vq<C>`
(as `q8m16`, the SH rest as C k-means codewords, no fine-tune; `_ft`: the codebook fine-tuned for
500 steps on the training frames, stdr.compact.finetune), and for +STDR runs `vq1024_<m>`
(as `q8m16_vq1024`, STDR's mask in the form m: m8 its 8-bit form, m4 4 bits, lr<R> the activated
mask at rank R; read back as the 8-bit mask, so the separated field reads logit(q / 255)); for runs
trained with stdr.mask_after_freeze=false `mask8` (the default spec, the mask in its 8-bit form),
`derived` / `derived8` (the default spec, the mask replaced by the separated field's output in half
precision / 8 bits) and `vq1024_derived8` / `_derived4` / `_derivedvq` (as `q8m16_vq1024`, the
field's output in 8 bits, 4 bits, or as 1,024 k-means codewords). Records:
records/<run>__<variant>.json, with the code commit and machine; the table is generated from them.
"""
from __future__ import annotations

import json
import statistics
import tempfile
import time
from pathlib import Path

from studies.common import commit, records_in, records_to_write, run_table_main

ROOT = Path(__file__).resolve().parents[1]

OUT = ROOT / "research" / "measurements" / "compact_file"
VARIANTS = {"default": {}, "state16": {"state": "f16"}, "all16": {"shN": "f16", "state": "f16"},
            "q8": {"scales": "q8", "quats": "q8", "opacities": "q8", "sh0": "q8", "*": "q8", "state": "f16"},
            "q8m16": {"means": "q16", "scales": "q8", "quats": "q8", "opacities": "q8", "sh0": "q8", "*": "q8",
                      "state": "f16"}}
for _d in (0, 1, 2):  # q8m16 with the SH rest kept to degree d (no fine-tune)
    VARIANTS[f"q8m16_sh{_d}"] = {**VARIANTS["q8m16"], "sh_degree": _d}
for _c in (256, 1024, 4096):  # q8m16 with the SH rest as a codebook of C codewords (k-means, no fine-tune)
    VARIANTS[f"q8m16_vq{_c}"] = {**VARIANTS["q8m16"], "shN": f"vq:{_c}"}
for _c in (256, 1024):  # the same, the codebook fine-tuned (stdr.compact.finetune's default steps)
    VARIANTS[f"q8m16_vq{_c}_ft"] = {**VARIANTS[f"q8m16_vq{_c}"], "finetune": 500}
# STDR's mask on top of q8m16_vq1024 (runs with a mask only): its 8-bit form, 4 bits, rank R of the
# activated mask; each read back as the 8-bit mask (stdr.compression.file, compact_form)
MASK_VARIANTS = {"m8": "q8", "m4": "q4", "lr4": "lowrank:4", "lr8": "lowrank:8", "lr16": "lowrank:16"}
for _n, _c in MASK_VARIANTS.items():
    VARIANTS[f"vq1024_{_n}"] = {**VARIANTS["q8m16_vq1024"], "stdr_mask": _c}
# STDR's mask in its derived form (the separated field's output in place of the mask; runs trained
# with stdr.mask_after_freeze=false only), against the 8-bit mask on the default spec
VARIANTS["mask8"] = {"stdr_mask": "q8"}
VARIANTS["derived"] = {"stdr_mask": "derived"}
VARIANTS["derived8"] = {"stdr_mask": "derived", "stdr_cond": "q8"}
VARIANTS["vq1024_derived8"] = {**VARIANTS["q8m16_vq1024"], "stdr_mask": "derived", "stdr_cond": "q8"}
VARIANTS["vq1024_derived4"] = {**VARIANTS["q8m16_vq1024"], "stdr_mask": "derived", "stdr_cond": "q4"}
VARIANTS["vq1024_derivedvq"] = {**VARIANTS["q8m16_vq1024"], "stdr_mask": "derived", "stdr_cond": "vq:1024"}


def run(runs: list[Path], variants: list[str], out: Path, tag: str = "") -> None:
    """tag: appended to the method's name in the records (e.g. `nogate` for runs trained with an
    ablation's settings), so they never overwrite the records of the method's default runs."""
    from stdr.store import load_config
    from stdr.eval.evaluate import machine_name
    from stdr.compact.pack import pack
    dest = records_to_write(out, "records")
    for rd in runs:
        cfg = load_config(rd / "config.yaml")
        for v in variants:
            if "stdr_mask" in VARIANTS[v] and not cfg.stdr.enabled:
                continue
            if VARIANTS[v].get("stdr_mask") == "derived" and cfg.stdr.mask_after_freeze:
                print(f"[compact_file] {rd.name} {v}: skipped (the derived mask needs stdr.mask_after_freeze=false)")
                continue
            with tempfile.TemporaryDirectory() as tmp:
                rec = pack(rd, Path(tmp) / "model.stdrc", VARIANTS[v], split="val")
            rec.pop("file")
            method = f"{cfg.name}__{tag}" if tag else cfg.name
            rec.update({"run": rd.name, "method": method, "scene": cfg.data.name, "seed": int(cfg.seed),
                        "budget": cfg.get("budget"), "variant": v, "code": commit(),
                        "machine": machine_name(), "date": time.strftime("%Y-%m-%d")})
            name = f"{method}__{cfg.data.name}__s{cfg.seed}__{v}.json"
            (dest / name).write_text(json.dumps(rec, indent=1) + "\n")
            print(f"[compact_file] {name}: {rec['bytes'] / 2**20:.2f} / {rec['full_bytes'] / 2**20:.2f} MiB, "
                  f"val {rec['delta_psnr']:+.3f} dB", flush=True)


def table(out: Path) -> str:
    recs = [json.loads(p.read_text()) for p in sorted(records_in(out, "records").glob("*.json"))]
    lines = ["# The compact model file on trained runs (generated by studies/compact_file.py)", ""]
    if not recs:
        return "\n".join(lines + ["No records yet."]) + "\n"
    lines += [f"Records: {len(recs)}; code {', '.join(sorted({r['code'] for r in recs}))}; machine "
              f"{'; '.join(sorted({r['machine'] for r in recs}))}.", "",
              "MiB of tensors (the model's, the compact file's); val PSNR of the full model and the change "
              "the file's codecs make.", "",
              "| method | scene | seed | budget | variant | full MiB | file MiB | file / full | val PSNR full | Δ PSNR | Δ SSIM |",
              "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in sorted(recs, key=lambda r: (r["method"], r["scene"], r["seed"], list(VARIANTS).index(r["variant"]))):
        lines.append(f"| {r['method']} | {r['scene']} | {r['seed']} | {r['budget']} | {r['variant']} | {r['full_bytes'] / 2**20:.2f} | "
                     f"{r['bytes'] / 2**20:.2f} | {r['ratio']:.1%} | {r['full']['psnr']:.2f} | {r['delta_psnr']:+.3f} | "
                     f"{r['compact']['ssim'] - r['full']['ssim']:+.4f} |")
    lines += ["", "Mean over runs, per method and variant (file / full, Δ PSNR):", ""]
    groups = {}
    for r in recs:
        groups.setdefault((r["method"], r["variant"]), []).append(r)
    for (m, v), rs in sorted(groups.items()):
        lines.append(f"* {m}, {v}: {statistics.mean(r['ratio'] for r in rs):.1%}, "
                     f"{statistics.mean(r['delta_psnr'] for r in rs):+.3f} dB over {len(rs)} run(s)")
    return "\n".join(lines) + "\n"


def main(argv=None) -> None:
    def args(p):
        p.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
        p.add_argument("--tag", default="", help="appended to the method's name in the records (an ablation's runs)")
    run_table_main(__doc__, OUT, "table.md", lambda a: run(a.runs, a.variants, a.out, a.tag), table, args, argv)


if __name__ == "__main__":
    main()
