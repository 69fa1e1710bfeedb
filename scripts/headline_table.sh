#!/usr/bin/env bash
# The D-NeRF headline table, rerun at one commit: 4 baselines x {plain, +STDR} x the four shared
# scenes x seeds 0-2 (96 runs, budget=cpu, test split), breadth first (every method and scene at
# seed 0, then seed 1, then 2), resumable. Each finished run's records (config.yaml, metrics.json,
# history.json, train_profile.json; no checkpoint) are copied to
# docs/measurements/dnerf_headline_cpu/runs/<experiment>/<scene>/s<seed>/, and a run whose records
# are there already is skipped, so the study goes on from the committed records on any machine.
# Then scripts/results.py rebuilds docs/results.md and the README's table from them. Each run goes
# through scripts/idle_run.py: one that shared the machine is not recorded (its times are not
# comparable) and is redone in a later sweep; a recorded one keeps its load.json.
#
#   bash scripts/headline_table.sh DNERF_ROOT [WORK_DIR]       # WORK_DIR: run folders (default outputs/headline)
#
# HEADLINE_CODE=<checkout> runs stdr-train from another checkout (its scripts/run.sh), e.g. a
# worktree frozen at the table's commit; HEADLINE_DRY=1 prints the commands; HEADLINE_SEEDS picks
# the seeds (default "0 1 2"). Run it on an otherwise idle machine: train seconds are reported.
# To use the machine for something else meanwhile, `touch WORK_DIR/pause`: the queue finishes the
# run in progress, then waits (no run is timed while paused) until the file is removed; any
# WORK_DIR/pause.<name> does the same (another study's hold on the machine).
set -uo pipefail
here=$(cd "$(dirname "$0")/.." && pwd)
ROOT=${1:?usage: headline_table.sh DNERF_ROOT [WORK_DIR]}
WORK=${2:-$here/outputs/headline}
REC=$here/docs/measurements/dnerf_headline_cpu/runs
CODE=${HEADLINE_CODE:-$here}
# one queue per WORK_DIR: a second one would train the same runs at the same time (each then
# counts the other as a foreign job, and both write one run folder)
mkdir -p "$WORK"
exec 9> "$WORK/.queue.lock"
flock -n 9 || { echo "[headline] another queue is running on $WORK (it holds $WORK/.queue.lock); to restart it, remove $WORK/pause instead" >&2; exit 3; }
[ -x "$CODE/scripts/run.sh" ] || { echo "[headline] HEADLINE_CODE=$CODE: no scripts/run.sh there" >&2; exit 2; }
SCENES="bouncingballs hellwarrior jumpingjacks standup"
for s in $SCENES; do
  [ -f "$ROOT/$s/transforms_train.json" ] || { echo "[headline] $ROOT/$s: not a D-NeRF scene (no transforms_train.json)" >&2; exit 2; }
done
EXPS=""
for b in deform scgs spgs 4dgs; do EXPS+=" dnerf_$b dnerf_${b}_stdr"; done
paused() { compgen -G "$WORK/pause*" | tr '\n' ' '; }
failed=0
left=0
# a run that shared the machine (scripts/idle_run.py: other jobs took more than 5 % of it) is not
# recorded; it is redone in the next sweep over its seed, up to three sweeps, before the next seed
# starts (so each seed is complete as early as it can be)
for seed in ${HEADLINE_SEEDS:-0 1 2}; do
shared=1
sweep=0
while [ "$shared" -gt 0 ] && [ "$sweep" -lt 3 ]; do
sweep=$((sweep + 1))
shared=0
  for scene in $SCENES; do
    for exp in $EXPS; do
      rec=$REC/$exp/$scene/s$seed
      [ -f "$rec/metrics.json" ] && continue
      run=$WORK/$exp/$scene/s$seed
      cmd=("$CODE/scripts/run.sh" stdr-train "experiment=$exp" budget=cpu "seed=$seed" "data.path=$ROOT/$scene"
           "data.name=$scene" data.eval_split=test train.progress=false "hydra.run.dir=$run")
      if [ "${HEADLINE_DRY:-0}" = 1 ]; then echo "${cmd[*]}"; continue; fi
      # WORK/pause (yours) or WORK/pause.<name> (a study that branches this queue's runs and wants
      # the machine first) stops the queue between runs
      [ -n "$(paused)" ] && echo "[headline] $(date +%T) paused ($(paused))"
      while [ -n "$(paused)" ]; do sleep 10; done
      echo "[headline] $(date +%T) $exp $scene seed $seed"
      rm -rf "$run"; mkdir -p "$run"
      if python3 "$here/scripts/idle_run.py" --out "$run.load.json" -- "${cmd[@]}" > "$run.log" 2>&1 \
          && [ -f "$run/metrics.json" ]; then
        if grep -q '"idle": true' "$run.load.json"; then
          mkdir -p "$rec"
          for f in config.yaml metrics.json history.json train_profile.json; do
            [ -f "$run/$f" ] && cp "$run/$f" "$rec/$f"
          done
          cp "$run.load.json" "$rec/load.json"
        else
          echo "[headline] SHARED $exp $scene seed $seed: other jobs used the machine ($run.load.json); redone in the next sweep" >&2
          shared=$((shared + 1))
        fi
      else
        echo "[headline] FAILED $exp $scene seed $seed (log: $run.log)" >&2; failed=$((failed + 1))
      fi
    done
  done
done
left=$((left + shared))
done
[ "${HEADLINE_DRY:-0}" = 1 ] && exit 0
"$here/scripts/run.sh" python "$here/scripts/results.py" || exit 2
echo "[headline] done; $failed failed, $left not recorded (shared the machine in all three sweeps)"
[ "$failed" = 0 ] && [ "$left" = 0 ]
