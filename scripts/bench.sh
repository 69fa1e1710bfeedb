#!/usr/bin/env bash
# Train and evaluate one experiment on every scene under a dataset folder, then tabulate.
#   scripts/bench.sh <dataset folder> [experiment] [budget] [extra overrides...]
# A scene is a sub-folder holding transforms_train.json (D-NeRF) or dataset.json (Nerfies format:
# NeRF-DS, HyperNeRF; the experiment's data config sets split_mode and image_scale).
# Examples: scripts/bench.sh ../shared/data/dnerf dnerf_deform cpu
#           scripts/bench.sh /data/nerfds nerfds_deform_stdr cpu
set -euo pipefail
root=${1:?usage: bench.sh <dataset folder> [experiment] [budget] [overrides...]}
exp=${2:-dnerf_deform}; budget=${3:-cpu}; shift $(( $# < 3 ? $# : 3 ))
here=$(cd "$(dirname "$0")/.." && pwd)
out=${BENCH_OUT:-$here/outputs/bench/${exp}_${budget}}
runs=()
for scene in "$root"/*/; do
  scene=${scene%/}; name=$(basename "$scene")
  [ -f "$scene/transforms_train.json" ] || [ -f "$scene/dataset.json" ] || continue
  "$here/scripts/run.sh" stdr-train experiment="$exp" budget="$budget" data.path="$scene" \
    data.name="$name" train.progress=false hydra.run.dir="$out/$name" "$@"
  runs+=("$out/$name")
done
[ ${#runs[@]} -gt 0 ] || { echo "bench.sh: no scene folders (transforms_train.json or dataset.json) under $root" >&2; exit 2; }
"$here/scripts/run.sh" stdr-eval "${runs[@]}" reevaluate=false out="$out/table"
