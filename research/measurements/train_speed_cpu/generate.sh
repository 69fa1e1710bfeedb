#!/usr/bin/env bash
# Regenerate this folder's end-to-end table from the run copies kept here (README.md says what
# each is): D-NeRF, budget=cpu, seed 0, test split, before (49cf03e) and after (the training-speed work's code).
#   bash research/measurements/train_speed_cpu/generate.sh      (from the repository root, in the venv)
set -euo pipefail
D=research/measurements/train_speed_cpu
R=$D/runs
stdr-tool variants --split test --out $D/table \
  --table "deform" "before=$R/before/dnerf_deform" "after=$R/after/dnerf_deform" \
                   "after, bf16 (baseline.precision)=$R/after_bf16/dnerf_deform" \
  --table "4dgs" "before=$R/before/dnerf_4dgs" "after=$R/after/dnerf_4dgs" > /dev/null
echo "tables written under $D"
