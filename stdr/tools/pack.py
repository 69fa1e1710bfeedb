"""Write a trained run's compact model file (stdr.io.compact_file) and measure what it costs.

    stdr-tool pack RUN [--out FILE] [--codec KEY=CODEC ... sh_degree=D finetune=STEPS] [--split val] [--no-eval]

Writes RUN/model.stdrc (default) from RUN/checkpoints/last.pt with the default codecs
(stdr.io.compact_file.DEFAULT_SPEC; `--codec shN=f16 state=f16` changes one; `--codec shN=vq:1024
finetune=500` stores the SH rest as a codebook fine-tuned for 500 steps on the training frames,
stdr.io.finetune), then renders `--split`
with the full model and with the model read back from the file, and writes RUN/pack.json: the
bytes of both (the tensors a saved model holds), the codec of every tensor, and PSNR / SSIM of both
renders with their difference. `load_model(FILE)`, `stdr-export FILE` and `stdr-render FILE` read
the file.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Optional


def pack(run_dir: Path, out: Optional[Path] = None, spec: Optional[dict] = None, split: Optional[str] = "val",
         data_base: Optional[str] = None) -> dict:
    """The compact file of run_dir's model, and (split not None) its renders against the full model's."""
    from ..config import load_config
    from ..eval.evaluate import evaluate_model
    from ..io.compact_file import SUFFIX, write_compact
    from ..model import load_model
    from ..train.state import CKPT
    run_dir = Path(run_dir)
    src = run_dir / CKPT
    if not (run_dir / "config.yaml").is_file() or not src.is_file():
        raise FileNotFoundError(f"{run_dir}: not a trained run (config.yaml and {CKPT} are needed)")
    out = Path(out) if out is not None else run_dir / f"model{SUFFIX}"
    cfg = load_config(run_dir / "config.yaml")
    cfg.device = "cpu"
    full = load_model(src, "cpu", cfg)
    frames = None
    if (spec or {}).get("finetune"):  # the codebooks' fine-tune renders the training frames
        from ..data.load import load_scene
        frames = load_scene(cfg.data, ("train",), base=data_base, seed=cfg.seed).frames("train")
    rec = {"file": str(out), **write_compact(full, out, spec, frames)}
    rec["ratio"] = rec["bytes"] / rec["full_bytes"]
    if split:
        from ..data.load import load_scene
        scene = load_scene(cfg.data, (split,), base=data_base, seed=cfg.seed)
        small = load_model(out, "cpu", cfg)
        a = evaluate_model(full, scene.frames(split), fps_warmup=0)
        b = evaluate_model(small, scene.frames(split), fps_warmup=0)
        rec.update({"split": split, "full": {k: a[k] for k in ("psnr", "ssim")},
                    "compact": {k: b[k] for k in ("psnr", "ssim")}, "delta_psnr": b["psnr"] - a["psnr"]})
    (run_dir / "pack.json").write_text(json.dumps(rec, indent=1) + "\n")
    return rec


def spec_of_config(pcfg) -> dict:
    """The compact spec of a run's `pack` config section (stdr.config.PackConfig)."""
    spec = {str(k): str(v) for k, v in (pcfg.codecs or {}).items()}
    if pcfg.get("finetune"):
        spec["finetune"] = int(pcfg.finetune)
    if pcfg.get("sh_degree") is not None:
        spec["sh_degree"] = int(pcfg.sh_degree)
    return spec


def summary(rec: dict) -> str:
    line = (f"[stdr] {rec['file']}: {rec['bytes'] / 2**20:.2f} MiB of tensors, {rec['ratio']:.1%} of the model's "
            f"{rec['full_bytes'] / 2**20:.2f} MiB")
    if "delta_psnr" in rec:
        line += (f"; {rec['split']} PSNR {rec['compact']['psnr']:.2f} dB vs {rec['full']['psnr']:.2f} "
                 f"({rec['delta_psnr']:+.3f})")
    return line


def _spec(items: list[str]) -> dict:
    out = {}
    for it in items:
        k, sep, v = it.partition("=")
        if not sep or not k or not v:
            raise SystemExit(f"stdr-tool pack: --codec {it!r}: use KEY=CODEC, e.g. shN=f16 or state=f16")
        out[k] = int(v) if k in ("sh_degree", "finetune") else v
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(prog="stdr-tool pack", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", type=Path, help="a trained run folder")
    ap.add_argument("--out", type=Path, default=None, help="the compact file (default RUN/model.stdrc)")
    ap.add_argument("--codec", nargs="*", default=[], help="KEY=CODEC overrides of the default codecs")
    ap.add_argument("--split", default="val", help="the split rendered by both models (default val)")
    ap.add_argument("--no-eval", action="store_true", help="write the file only")
    a = ap.parse_args(argv)
    try:
        rec = pack(a.run, a.out, _spec(a.codec), None if a.no_eval else a.split)
    except ValueError as e:
        raise SystemExit(f"stdr-tool pack: {e}") from None
    print(summary(rec))


if __name__ == "__main__":
    main()
