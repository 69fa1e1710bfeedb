"""Write a trained run's compact model file (stdr.compression.file) and measure what it costs.

    stdr-tool pack RUN [--out FILE] [--codec KEY=CODEC ... sh_degree=D finetune=STEPS finetune_state=PARTS]
                   [--split val] [--no-eval]

Writes RUN/model.stdrc (default) from RUN/checkpoints/last.pt with the default codecs
(stdr.compression.file.DEFAULT_SPEC; `--codec shN=f16 state=f16` changes one; `--codec shN=vq:1024
finetune=500` stores the SH rest as a codebook fine-tuned for 500 steps on the training frames,
stdr.compact.finetune; `state:grids=q4 finetune_state=grids` adds 4DGS's grid in 4 bits to that
fine-tune, quantization-aware), then renders `--split`
with the full model and with the model read back from the file, and writes RUN/pack.json: the
bytes of both (the tensors a saved model holds), the codec of every tensor, and PSNR / SSIM of both
renders with their difference. `load_model(FILE)`, `stdr-export FILE` and `stdr-render FILE` read
the file.
"""
from __future__ import annotations

import argparse
from pathlib import Path

from ..compact.pack import pack, summary


def _spec(items: list[str]) -> dict:
    out = {}
    for it in items:
        k, sep, v = it.partition("=")
        if not sep or not k or not v:
            raise SystemExit(f"stdr-tool pack: --codec {it!r}: use KEY=CODEC, e.g. shN=f16 or state=f16")
        if k in ("sh_degree", "finetune") and not v.isdigit():
            raise SystemExit(f"stdr-tool pack: --codec {it!r}: {k} takes a whole number, e.g. {k}={3 if k == 'sh_degree' else 500}")
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
    except (ValueError, FileNotFoundError) as e:  # a bad spec, or a folder that is not a trained run
        raise SystemExit(f"stdr-tool pack: {e}") from None
    print(summary(rec))


if __name__ == "__main__":
    main()
