#!/usr/bin/env bash
# The degradation study of docs/stability.md, breadth first and resumable: one
# `stdr-train -m +sweep=stability` per stress preset (8 methods x the sweep's D-NeRF scenes each),
# in the order that gives a readable table soonest: the unstressed runs, level 3 of every stress,
# seeds 1-2 of the unstressed runs, level 1, then level 2. Finished runs are skipped
# (train.skip_finished), so stopping and starting again loses only the run in progress. Then the
# table and chart, with the runs already committed in OUT_DIR/table.json kept (stdr-tool stability
# reads its own table), so a study spread over machines adds up:
#
#   bash scripts/stability_study.sh DNERF_ROOT [OUT_DIR]       # OUT_DIR: docs/measurements/stability
#
# Runs land in multirun/stability_cpu/ under the current folder. STDR_STUDY_PRESETS picks the
# presets, as preset:seed words (default: the whole grid below); STDR_STUDY_DRY=1 prints the
# commands instead of running them. Extra arguments after OUT_DIR go to every stdr-train.
set -uo pipefail
here=$(cd "$(dirname "$0")/.." && pwd)
ROOT=${1:?usage: stability_study.sh DNERF_ROOT [OUT_DIR] [stdr-train overrides...]}
OUT=${2:-$here/docs/measurements/stability}
shift $(( $# < 2 ? $# : 2 ))
GRID="none:0"
for s in window fraction sparse pose jitter; do GRID+=" ${s}_3:0"; done
GRID+=" none:1 none:2"
for lv in 1 2; do for s in window fraction sparse pose jitter; do GRID+=" ${s}_${lv}:0"; done; done
PRESETS=${STDR_STUDY_PRESETS:-$GRID}
do_run() { if [ "${STDR_STUDY_DRY:-0}" = 1 ]; then echo "$*"; else "$here/scripts/run.sh" "$@"; fi; }
status=0
for p in $PRESETS; do
  stress=${p%%:*}; seed=${p##*:}
  [[ "$p" == *:* && -f "$here/configs/stress/$stress.yaml" ]] || {
    echo "[study] bad preset '$p': want <preset>:<seed> with configs/stress/<preset>.yaml" >&2; exit 2; }
  echo "[study] $(date +%T) $stress seed $seed"
  do_run stdr-train -m +sweep=stability data.root="$ROOT" budget=cpu stress="$stress" seed="$seed" \
    hydra/launcher=local "$@" || { echo "[study] $stress seed $seed: stdr-train failed (rc $?)" >&2; status=1; }
done
inputs=()
[ -f "$OUT/table.json" ] && inputs+=("$OUT/table.json")
[ -d multirun/stability_cpu ] && inputs+=(multirun/stability_cpu)
if [ ${#inputs[@]} -gt 0 ]; then
  do_run stdr-tool stability "${inputs[@]}" --split val --out "$OUT" || status=1
fi
exit $status
