#!/usr/bin/env bash
# The before/after table of this folder (compare.md / compare.json) from its four benchmark
# files, written by `stdr-tool bench-rasterizer` in one sitting, alternating before, after,
# before, after (README.md says which code each is):
#   stdr-tool bench-rasterizer --backends cpu --n 10000 100000 --res 256 400 800 \
#       --json <before|after>_r<1|2>.json --markdown <before|after>_r<1|2>.md
# Run from the repository root: bash research/measurements/rasterizer_simd/generate.sh
set -euo pipefail
D=research/measurements/rasterizer_simd
python - "$D" <<'PY'
import json, sys
from pathlib import Path
d = Path(sys.argv[1])
load = lambda f: {(r["n"], r["width"]): r for r in json.loads((d / f).read_text())["rows"]}
runs = {v: [load(f"{v}_r{i}.json") for i in (1, 2)] for v in ("before", "after")}
keys = ("fwd_ms", "fwd_bwd_ms", "render_fwd_bwd_ms")
rows, out = [], []
for cfg in sorted(runs["before"][0]):
    row = {"n": cfg[0], "res": cfg[1]}
    for k in keys:
        b = [r[cfg][k] for r in runs["before"]]
        a = [r[cfg][k] for r in runs["after"]]
        row[k] = {"before": b, "after": a, "speedup": (sum(b) / len(b)) / (sum(a) / len(a))}
    out.append(row)
    rows.append(f"| {cfg[0]:,} | {cfg[1]}² | " + " | ".join(
        f"{' / '.join(f'{x:.1f}' for x in row[k]['before'])} → {' / '.join(f'{x:.1f}' for x in row[k]['after'])} "
        f"({row[k]['speedup']:.2f}×)" for k in keys) + " |")
md = ["CPU rasterizer, before → after (ms, rounds 1 / 2; speed-up of the means), 2 threads, tile 8, coverage 5", "",
      "| N | image | forward | forward+backward | render() forward+backward |", "|---|---|---|---|---|", *rows]
(d / "compare.md").write_text("\n".join(md) + "\n")
(d / "compare.json").write_text(json.dumps(out, indent=1) + "\n")
print("\n".join(md))
PY
