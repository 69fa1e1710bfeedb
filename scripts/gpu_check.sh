#!/usr/bin/env bash
# The checks that need an NVIDIA GPU, in one go (CI has none): build the CUDA rasterizer, run the
# CUDA tests (parity with the reference and the CPU backend, training and resume on the GPU),
# time the rasterizer, and train one D-NeRF scene per baseline with and without STDR on the GPU.
#
#   bash scripts/gpu_check.sh OUT_DIR [DNERF_SCENE_DIR]
#
# Everything it prints also lands in OUT_DIR (logs, bench JSON/Markdown, each run's metrics.json).
# STDR_GPU_CHECK_STEPS picks steps (default "env build tests bench train"); STDR_GPU_CHECK_BASELINES
# the baselines trained (default "deform scgs spgs 4dgs"). Uses the python on PATH (python3).
set -uo pipefail
cd "$(dirname "$0")/.."
OUT=${1:?usage: gpu_check.sh OUT_DIR [DNERF_SCENE_DIR]}
SCENE=${2:-}
PY=${PYTHON:-python3}
STEPS=${STDR_GPU_CHECK_STEPS:-env build tests bench train}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1
has() { [[ " $STEPS " == *" $1 "* ]]; }
status=0

if has env; then
  { nvidia-smi -L; nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.sm,clocks.max.sm --format=csv
    $PY -c "import torch, platform; print('torch', torch.__version__, 'cuda', torch.version.cuda, torch.cuda.get_device_name(0), 'python', platform.python_version())"
    nvcc --version | tail -2; } 2>&1 | tee "$OUT/env.txt"
fi
if has build; then
  SECONDS=0
  $PY -m stdr.cli.build 2>&1 | tee "$OUT/build.log" || status=1
  echo "[gpu_check] build: ${SECONDS} s" | tee -a "$OUT/build.log"
fi
if has tests; then
  # the CUDA tests and everything that touches devices or backends
  $PY -m pytest -q -rs -p no:cacheprovider tests/test_compiled.py tests/test_device.py tests/test_render.py \
    2>&1 | tee "$OUT/pytest_cuda.log" || status=1
fi
if has bench; then
  # % of peak against the GPU's fp32 rate (STDR_GPU_PEAK_GFLOPS; 67000 = H100 SXM, non-tensor fp32);
  # the pure-torch reference runs on the GPU too, at the smallest size
  $PY -m stdr.tools.bench_rasterizer --backends cuda reference --reference-device cuda --max-ref-n 10000 \
    --n 10000 100000 1000000 --res 400 800 --repeats 20 --peak-gflops "${STDR_GPU_PEAK_GFLOPS:-67000}" \
    --json "$OUT/bench_cuda.json" --markdown "$OUT/bench_cuda.md" 2>&1 | tee "$OUT/bench.log" || status=1
fi
if has train && [ -n "$SCENE" ]; then
  for b in ${STDR_GPU_CHECK_BASELINES:-deform scgs spgs 4dgs}; do
    for exp in dnerf_$b dnerf_${b}_stdr; do
      run="$OUT/train_$exp"
      $PY -m stdr.cli.train experiment=$exp budget=cpu device=cuda data.path="$SCENE" train.progress=false \
        data.name="$(basename "$SCENE")" hydra.run.dir="$run" > "$OUT/train_$exp.log" 2>&1 || status=1
      echo "[gpu_check] $exp: $(grep -h 'PSNR' "$OUT/train_$exp.log" | tail -1)"
    done
  done
fi
exit $status
