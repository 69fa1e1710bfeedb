# shellcheck shell=bash
# Sourced at the start of a job on a GPU machine without network access (bash):
#   source scripts/gpu_env.sh && <the commands of docs/install.md, "A GPU machine without network access">
# installs build/gpucarry/wheels into /tmp/site (the image lacks hydra, its joblib launcher, omegaconf, antlr4, plyfile),
# puts it and the tree on PYTHONPATH, shares one extension build between the check and the queue's
# runs (STDR_EXT_DIR=build/ext, built here once: CUDA and CPU), and prints the GPU.
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site \
  build/gpucarry/wheels/*.whl || return 5
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 STDR_EXT_DIR=$PWD/build/ext
export STDR_LPIPS_WEIGHTS=$PWD/build/gpucarry/weights
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader || return 3
python3 -c "from stdr import extension as e; e.load_extension('cuda'); e.load_extension('cpu')" > /tmp/stdr_build.log 2>&1 \
  || { tail -40 /tmp/stdr_build.log; return 4; }
stdr-tool() { python3 -m stdr.cli.tool "$@"; }   # the entry point, without installing the package
