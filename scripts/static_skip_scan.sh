#!/usr/bin/env bash
# Static skipping (docs/measurements/compactness/protocol.md §4): evaluate trained STDR runs on the
# val split at each threshold θ, on copies (the runs' own metrics.json stay as they are).
#   scripts/static_skip_scan.sh OUT RUN_DIR [RUN_DIR ...]
# RUN_DIRs are a sweep's runs, <experiment>/<scene>/s<seed> (one seed per scene). Writes
# OUT/<θ>/<experiment>/<scene>/metrics.json (val) and OUT/<θ>/table.* (stdr-eval's tables): the
# layout `stdr-tool static-rule --baseline NAME 0=OUT/0/<experiment> 0.01=OUT/0.01/<experiment> ...`
# reads.
# THETAS (default "0 0.01 0.03 0.1 0.3") and EXTRA (more stdr-eval overrides, e.g.
# "reevaluate=false remeasure=fps eval.fps_repeats=5" for the idle FPS pass) may be set.
set -euo pipefail
out=$1; shift
for th in ${THETAS:-0 0.01 0.03 0.1 0.3}; do
  dirs=()
  for rd in "$@"; do
    scene=$(dirname "$rd"); dst=$out/$th/$(basename "$(dirname "$scene")")/$(basename "$scene")
    if [ ! -f "$dst/checkpoints/last.pt" ]; then
      mkdir -p "$dst/checkpoints"
      cp "$rd/config.yaml" "$rd/metrics.json" "$dst/"
      cp "$rd/checkpoints/last.pt" "$dst/checkpoints/"
    fi
    dirs+=("$dst")
  done
  python -m stdr.cli.eval "${dirs[@]}" split=val stdr.static_skip="$th" eval.save_images=false \
    out="$out/$th/table" ${EXTRA:-}
done
