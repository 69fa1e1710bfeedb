#!/usr/bin/env bash
# Train and evaluate one experiment on every D-NeRF scene under a folder, then tabulate.
#   scripts/bench_dnerf.sh <dnerf folder> [experiment] [budget] [extra overrides...]
# Example: scripts/bench_dnerf.sh ../shared/data/dnerf dnerf_deform cpu
set -euo pipefail
root=${1:?usage: bench_dnerf.sh <dnerf folder> [experiment] [budget] [overrides...]}
exp=${2:-dnerf_deform}; budget=${3:-cpu}; shift $(( $# < 3 ? $# : 3 ))
here=$(cd "$(dirname "$0")/.." && pwd)
out=${BENCH_OUT:-$here/outputs/bench/${exp}_${budget}}
runs=()
for scene in "$root"/*/; do
  scene=${scene%/}; name=$(basename "$scene")
  [ -f "$scene/transforms_train.json" ] || continue
  "$here/scripts/run.sh" stdr-train experiment="$exp" budget="$budget" data.path="$scene" \
    data.name="$name" train.progress=false hydra.run.dir="$out/$name" "$@"
  runs+=("$out/$name")
done
"$here/scripts/run.sh" stdr-eval "${runs[@]}" reevaluate=false out="$out/table"
