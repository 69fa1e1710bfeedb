#!/usr/bin/env bash
# build/gpucarry: what a GPU machine without network access needs beside the checkout (docs/install.md,
# "A GPU machine without network access"):
# the four 400² D-NeRF scenes, the LPIPS-alex weights, and wheels (Python 3.12) of the packages the
# machine's image lacks. About 45 MB; copy it over with the checkout.
#
#   bash scripts/gpu_payload.sh [SHARED]     # SHARED: the folder with data/dnerf and weights/lpips (../shared)
set -euo pipefail
cd "$(dirname "$0")/.."
S=${1:-../shared}
G=build/gpucarry
for f in "$S/weights/lpips/alexnet_features.pth" "$S/weights/lpips/lpips_v0.1_alex_lin.pth"; do
  [ -f "$f" ] || { echo "gpu_payload: $f is missing (give the shared folder as the first argument)" >&2; exit 2; }
done
SCENES="bouncingballs hellwarrior jumpingjacks standup"
for s in $SCENES; do
  [ -f "$S/data/dnerf/$s/transforms_train.json" ] || { echo "gpu_payload: no D-NeRF scene at $S/data/dnerf/$s" >&2; exit 2; }
done
rm -rf "$G"   # only once every input is there
mkdir -p "$G/weights" "$G/wheels"
for s in $SCENES; do cp -r "$S/data/dnerf/$s" "$G/"; done
cp "$S/weights/lpips/alexnet_features.pth" "$S/weights/lpips/lpips_v0.1_alex_lin.pth" "$G/weights/"
chmod -R u+w "$G"
PIP="python3 -m pip"
$PIP download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
  --platform manylinux_2_28_x86_64 --platform manylinux2014_x86_64 -d "$G/wheels" \
  hydra-core==1.3.2 omegaconf==2.3.0 plyfile==1.1.3 hydra-joblib-launcher==1.2.0 joblib==1.6.0 cloudpickle==3.1.3
$PIP wheel -q --no-deps -w "$G/wheels" antlr4-python3-runtime==4.9.3   # an sdist upstream: built here
ls "$G/wheels"
du -sh "$G"
