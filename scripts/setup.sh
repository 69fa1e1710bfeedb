#!/usr/bin/env bash
# One-time set-up from a clean clone: a local venv (.venv) with torch and stdr installed.
#  - Machine without a GPU: the CPU build of torch (torch==2.13.0); a CUDA build is never pulled.
#  - Machine with an NVIDIA GPU: the torch you already have is kept (the venv sees the system
#    site-packages). If none is importable, a CUDA build that the driver can run is installed:
#    the driver's CUDA version (nvidia-smi) picks the newest PyTorch wheel index
#    (download.pytorch.org/whl/cuXYZ, from STDR_CUDA_TAGS) that is not newer than it.
#    STDR_TORCH_INDEX=<url> names the index yourself.
#  - tcmalloc (Debian libtcmalloc-minimal4) is installed when run as root with apt, because
#    torch CPU code runs 2-2.5x faster with it; scripts/run.sh preloads it. STDR_NO_APT=1 skips.
# Re-running is cheap: each step is skipped when already done.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
TORCH_SPEC=${STDR_TORCH:-torch==2.13.0}

has_gpu() { command -v nvidia-smi >/dev/null 2>&1 && nvidia-smi -L >/dev/null 2>&1; }
# the highest CUDA version the driver supports, as an integer (12.8 -> 128); empty if unknown
driver_cuda() { nvidia-smi 2>/dev/null | sed -n 's/.*CUDA Version: *\([0-9]*\)\.\([0-9]\).*/\1\2/p' | head -1; }
CUDA_TAGS=${STDR_CUDA_TAGS:-cu130 cu129 cu128 cu126 cu124 cu121 cu118}

install_cuda_torch() {
  if [ -n "${STDR_TORCH_INDEX:-}" ]; then
    echo "[setup] installing $TORCH_SPEC from $STDR_TORCH_INDEX"
    pip install -q "$TORCH_SPEC" --index-url "$STDR_TORCH_INDEX"
    return
  fi
  local drv tag
  drv=$(driver_cuda)
  for tag in $CUDA_TAGS; do
    if [ -n "$drv" ] && [ "${tag#cu}" -gt "$drv" ]; then
      continue  # newer than the driver can run
    fi
    echo "[setup] installing $TORCH_SPEC for $tag (driver supports CUDA ${drv:-?})"
    if pip install -q "$TORCH_SPEC" --index-url "https://download.pytorch.org/whl/$tag"; then
      return
    fi
  done
  echo "[setup] warning: no CUDA wheel index of ($CUDA_TAGS) fitting the driver (CUDA ${drv:-unknown}) has" \
       "$TORCH_SPEC; installing the package registry's default build. Set STDR_TORCH_INDEX if it does not" \
       "run on this driver" >&2
  pip install -q "$TORCH_SPEC"
}

if [ ! -x .venv/bin/python ]; then
  if has_gpu && "$PY" -c "import torch" >/dev/null 2>&1; then
    echo "[setup] GPU machine with torch $("$PY" -c 'import torch; print(torch.__version__)'): keeping it"
    "$PY" -m venv --system-site-packages .venv
  else
    "$PY" -m venv .venv
  fi
fi
pip() { .venv/bin/python -m pip "$@"; }

if ! .venv/bin/python -c "import torch" >/dev/null 2>&1; then
  if has_gpu; then
    install_cuda_torch
  else
    echo "[setup] installing the CPU build of $TORCH_SPEC"
    # A local CPU wheel (pip's find-links) if there is one, its dependencies then from the usual
    # index (the installed CPU build already satisfies the pin); else PyTorch's CPU index.
    # Never PyPI's CUDA build.
    if pip install -q --no-deps --no-index "$TORCH_SPEC" 2>/dev/null; then
      pip install -q "$TORCH_SPEC"
    else
      pip install -q "$TORCH_SPEC" --index-url https://download.pytorch.org/whl/cpu
    fi
  fi
fi
if ! has_gpu && .venv/bin/python -c "import torch,sys; sys.exit(0 if torch.version.cuda else 1)" 2>/dev/null; then
  echo "[setup] warning: the venv's torch is a CUDA build on a machine without a GPU" >&2
fi
if has_gpu && ! .venv/bin/python -c "import torch,sys; sys.exit(0 if torch.cuda.is_available() else 1)" 2>/dev/null; then
  echo "[setup] warning: this machine has a GPU but the venv's torch cannot use it (a CPU build, or a CUDA" \
       "build newer than the driver): training falls back to device=cpu under device=auto. Remove .venv and" \
       "re-run with STDR_TORCH_INDEX=https://download.pytorch.org/whl/cuXYZ" >&2
fi

pip install -q -e ".[test,capture]"

if [ "${STDR_NO_APT:-0}" != 1 ] && [ ! -f /usr/lib/x86_64-linux-gnu/libtcmalloc_minimal.so.4 ] \
   && [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
  echo "[setup] installing libtcmalloc-minimal4 (faster torch on the CPU)"
  (apt-get install -y -q libtcmalloc-minimal4 >/dev/null 2>&1 \
    || (apt-get update -q >/dev/null 2>&1 && apt-get install -y -q libtcmalloc-minimal4 >/dev/null 2>&1)) \
    || echo "[setup] tcmalloc not installed (optional)"
fi
# Compile the rasterizer now (cached; otherwise it is built on first use). A failure is not
# fatal: render.backend=auto then falls back to the pure-torch reference with a warning.
.venv/bin/stdr-build || echo "[setup] warning: compiled rasterizer not built; the reference backend will be used" >&2
.venv/bin/python -c "import torch, stdr; print(f'[setup] ok: torch {torch.__version__}, cuda={torch.cuda.is_available()}, stdr {stdr.__version__}')"
