#!/usr/bin/env bash
# Regenerate this folder's tables from the run copies kept here (README.md says what each is).
#   bash research/measurements/compactness/generate.sh      (from the repository root, in the venv)
set -euo pipefail
D=research/measurements/compactness
B="deform scgs spgs 4dgs"
T="0 0.01 0.03 0.1 0.3"
args=(); for b in $B; do args+=(--baseline $b); for th in $T; do args+=("$th=$D/theta_val/$th/dnerf_${b}_stdr"); done; done
stdr-tool static-rule --split val --out $D/static_rule_val "${args[@]}" > /dev/null
args=(); for b in $B; do
  args+=(--table "$b (val)" "plain=$D/cull_train_val/plain/dnerf_$b" "A: +STDR, default=$D/cull_train_val/A/dnerf_${b}_stdr"
         "B: +STDR, cull in training=$D/cull_train_val/B/dnerf_${b}_stdr"); done
# the control: one A run retrained in the B runs' session (same command and code): same machine speed?
[ -d $D/control ] && args+=(--table "control (val): deform+STDR retrained with A's command in B's session"
  "A=$D/cull_train_val/A/dnerf_deform_stdr" "A, retrained=$D/control/dnerf_deform_stdr")
stdr-tool variants --split val --out $D/cull_train_val "${args[@]}" > /dev/null
args=(); for b in $B; do t=$D/test
  args+=(--table "$b" "plain=$t/plain/dnerf_$b" "+STDR, no culling=$t/stdr_off/dnerf_${b}_stdr"
         "+STDR, culling in evaluation=$t/stdr_cull/dnerf_${b}_stdr"
         "+STDR, culling in training and evaluation=$t/B_cull/dnerf_${b}_stdr"
         "+STDR, culling in evaluation + static θ 0.1=$t/stdr_cull_static/dnerf_${b}_stdr"
         "+STDR, culling in training + static θ 0.1=$t/B_cull_static/dnerf_${b}_stdr"); done
stdr-tool variants --split test --out $D/tables_test "${args[@]}" > /dev/null
if [ -d $D/target ]; then
  args=(--table "deform+STDR, densify.target_gaussians (val)")
  # a target enters when all four scenes ran (the means are over the scenes every variant has)
  for tg in 2500 5000 7500 10000 15000; do
    [ "$(ls $D/target/$tg 2>/dev/null | wc -l)" -ge 4 ] && args+=("target $tg=$D/target/$tg"); done
  args+=("default densification=$D/cull_train_val/A/dnerf_deform_stdr")
  stdr-tool variants --split val --smallest-within 0.1 --out $D/target_val "${args[@]}" > /dev/null
fi
if [ -d $D/reruns ]; then  # the same command and code trained twice (the measurement-tooling work's reruns, the control)
  args=(); for m in $(ls $D/reruns/first); do
    args+=(--table "$m: trained twice" "first=$D/reruns/first/$m" "second=$D/reruns/second/$m"); done
  stdr-tool variants --split val --out $D/reruns "${args[@]}" > /dev/null
fi
echo "tables written under $D"
