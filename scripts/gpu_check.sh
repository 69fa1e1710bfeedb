#!/usr/bin/env bash
# The checks that need an NVIDIA GPU, staged to fit one job with a time limit (scripts/gpu_check.py says
# what each stage does; docs/development.md how to run it on a GPU machine).
#
#   bash scripts/gpu_check.sh OUT --scene DNERF_SCENE [--budget 420] [--stages a b ...]
#   bash scripts/gpu_check.sh --dry-run OUT        # every stage's plumbing on the CPU (CI runs it)
#
# Uses $PYTHON, else the checkout's .venv, else python3.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-$( [ -x .venv/bin/python ] && echo .venv/bin/python || echo python3 )}
args=()
for a in "$@"; do args+=("$a"); done
exec "$PY" scripts/gpu_check.py "${args[@]}" --python "$PY"
