#!/usr/bin/env bash
# The degradation study of docs/stability.md, breadth first and resumable: one
# `stdr-train -m +sweep=stability` per stress preset (8 methods x the sweep's D-NeRF scenes each),
# in the order that gives a readable table soonest: the unstressed runs, level 3 of every stress,
# seeds 1-2 of the unstressed runs, level 1, then level 2. Finished runs are skipped: those whose
# folder is here (train.skip_finished) and those already recorded in OUT_DIR/table.json (runs of
# earlier machines: `studies/stability.py --todo` names what the table lacks, and only that runs),
# so stopping and starting again, here or on another machine, loses only the run in progress.
# Then the table and chart, with the runs already committed in OUT_DIR/table.json kept
# (studies/stability.py reads its own table), so a study spread over machines adds up:
#
#   bash studies/stability_study.sh DNERF_ROOT [OUT_DIR]       # OUT_DIR: research/measurements/stability
#
# Runs land in multirun/stability_cpu/ under the current folder. STDR_STUDY_PRESETS picks the
# presets, as preset:seed words (default: the whole grid below); STDR_STUDY_DRY=1 prints the
# commands instead of running them. STDR_STUDY_CODE names another checkout whose stdr-train runs
# the study (its scripts/run.sh), e.g. a worktree frozen at the study's commit, so a study keeps
# one code version while this checkout moves on. Extra arguments after OUT_DIR go to every
# stdr-train.
set -uo pipefail
here=$(cd "$(dirname "$0")/.." && pwd)
ROOT=${1:?usage: stability_study.sh DNERF_ROOT [OUT_DIR] [stdr-train overrides...]}
OUT=${2:-$here/research/measurements/stability}
shift $(( $# < 2 ? $# : 2 ))
GRID="none:0"
for s in window fraction sparse pose jitter; do GRID+=" ${s}_3:0"; done
GRID+=" none:1 none:2"
for lv in 1 2; do for s in window fraction sparse pose jitter; do GRID+=" ${s}_${lv}:0"; done; done
PRESETS=${STDR_STUDY_PRESETS:-$GRID}
CODE=${STDR_STUDY_CODE:-$here}
[ -x "$CODE/scripts/run.sh" ] || { echo "[study] STDR_STUDY_CODE=$CODE: no scripts/run.sh there" >&2; exit 2; }
do_run() { if [ "${STDR_STUDY_DRY:-0}" = 1 ]; then echo "$*"; else "$@"; fi; }
for p in $PRESETS; do
  [[ "$p" == *:* && -f "$here/stdr/configs/stress/${p%%:*}.yaml" ]] || {
    echo "[study] bad preset '$p': want <preset>:<seed> with stdr/configs/stress/<preset>.yaml" >&2; exit 2; }
done
planned="" planned_from=""
if [ -f "$OUT/table.json" ]; then   # what the committed table lacks, per preset: "preset:seed overrides"
  todo_args=()
  for p in $PRESETS; do todo_args+=(--todo "$p"); done
  planned=$("$here/scripts/run.sh" python "$here/studies/stability.py" "${todo_args[@]}" "$OUT/table.json") || exit 2
  planned_from=$OUT/table.json
fi
status=0
for p in $PRESETS; do
  stress=${p%%:*}; seed=${p##*:}
  todo=("")   # no committed table: the whole preset
  if [ -n "$planned_from" ]; then
    lines=$(grep "^$p " <<< "$planned" | cut -d' ' -f2-)
    [ -n "$lines" ] || { echo "[study] $stress seed $seed: every run is in $planned_from"; continue; }
    mapfile -t todo <<< "$lines"
  fi
  for overrides in "${todo[@]}"; do
    echo "[study] $(date +%T) $stress seed $seed${overrides:+ ($overrides)}"
    # shellcheck disable=SC2086  # the overrides are words: experiment=... data.name=...
    do_run "$CODE/scripts/run.sh" stdr-train -m +sweep=stability data.root="$ROOT" budget=cpu stress="$stress" \
      seed="$seed" hydra/launcher=local $overrides "$@" \
      || { echo "[study] $stress seed $seed: stdr-train failed (rc $?)" >&2; status=1; }
  done
done
inputs=()
[ -f "$OUT/table.json" ] && inputs+=("$OUT/table.json")
[ -d multirun/stability_cpu ] && inputs+=(multirun/stability_cpu)
if [ ${#inputs[@]} -gt 0 ]; then
  do_run "$here/scripts/run.sh" python "$here/studies/stability.py" "${inputs[@]}" --split val --out "$OUT" || status=1
fi
exit $status
