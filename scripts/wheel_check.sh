#!/usr/bin/env bash
# The wheel round trip: build stdr's wheel, install it into a fresh venv outside the checkout, and
# from there train the embedded demo for a few hundred steps and tabulate it with stdr-eval.
# It proves that an installed copy has its configs and kernel sources, and writes nothing into
# the checkout or site-packages (caches go to XDG_CACHE_HOME, here WORK/cache).
#
#   bash scripts/wheel_check.sh WORK          # WORK: an empty scratch folder outside the checkout
#
# The fresh venv gets stdr from the wheel only; its dependencies (torch, hydra, ...) are borrowed
# from the checkout's .venv through a .pth line (pip does not re-download them), so what is tested
# is the package, not the package index. The suite runs it (tests/test_install.py).
set -euo pipefail
here=$(cd "$(dirname "$0")/.." && pwd)
WORK=${1:?usage: wheel_check.sh WORK}
mkdir -p "$WORK"
WORK=$(cd "$WORK" && pwd)
case "$WORK/" in "$here"/*) echo "[wheel] WORK=$WORK is inside the checkout; use a folder outside it" >&2; exit 2;; esac
VPY=$here/.venv/bin/python
[ -x "$VPY" ] || { echo "[wheel] no $VPY: run bash scripts/setup.sh first" >&2; exit 2; }

echo "[wheel] building the wheel"
"$VPY" -m pip wheel -q --no-deps --no-build-isolation -w "$WORK/dist" "$here"
whl=$(ls "$WORK"/dist/stdr-*.whl)
echo "[wheel] $whl: $(unzip -l "$whl" | grep -c 'stdr/configs/.*\.yaml') config files, $(unzip -l "$whl" | grep -c 'stdr/csrc/') kernel sources"

echo "[wheel] a fresh venv with the wheel"
base=$("$VPY" -c "import sys; print(sys.base_prefix)")/bin/python3
"$base" -m venv "$WORK/venv"
site=$("$WORK/venv/bin/python" -c "import sysconfig; print(sysconfig.get_paths()['purelib'])")
"$VPY" -c "import sysconfig; print(sysconfig.get_paths()['purelib'])" > "$site/borrowed_deps.pth"
"$WORK/venv/bin/python" -m pip install -q --no-deps --no-index "$whl"
# the installed package's files (bytecode caches aside), compared after the runs
installed() { (cd "$site" && find stdr -path '*/__pycache__' -prune -o -print | LC_ALL=C sort); }
installed > "$WORK/installed.before"

cd "$WORK"  # outside the checkout from here on
export XDG_CACHE_HOME=$WORK/cache  # the scene, LPIPS lookup and compiled kernels all go under it
unset STDR_EXT_DIR
unset STDR_LPIPS_WEIGHTS
"$WORK/venv/bin/python" - <<'EOF'
import stdr, sys
from pathlib import Path
from stdr.config import CONFIG_DIR
assert Path(stdr.__file__).resolve().is_relative_to(Path(sys.prefix).resolve()), f"stdr imported from {stdr.__file__}"
assert stdr.source_checkout() is None, stdr.source_checkout()
assert (CONFIG_DIR / "train.yaml").is_file() and (CONFIG_DIR / "budget" / "demo.yaml").is_file(), CONFIG_DIR
print(f"[wheel] stdr {stdr.__version__} from {Path(stdr.__file__).parent}, configs in {CONFIG_DIR}")
EOF
echo "[wheel] stdr-train: the embedded demo, 300 steps"
"$WORK/venv/bin/stdr-train" experiment=embedded_deform_stdr budget=demo optim.iterations=300 baseline.warmup=100 train.progress=false \
  eval.save_images=false hydra.run.dir="$WORK/run" > "$WORK/train.log" 2>&1 || { tail -30 "$WORK/train.log"; exit 1; }
grep "\[stdr\] test: PSNR" "$WORK/train.log"
echo "[wheel] stdr-eval"
"$WORK/venv/bin/stdr-eval" "$WORK/run" out="$WORK/table" > "$WORK/eval.log" 2>&1 || { tail -30 "$WORK/eval.log"; exit 1; }
grep "deform+STDR" "$WORK/eval.log" | head -2
[ -d "$WORK/cache/stdr/data/embedded" ] || { echo "[wheel] the embedded scene was not cached under XDG_CACHE_HOME" >&2; exit 1; }
installed > "$WORK/installed.after"
if ! diff "$WORK/installed.before" "$WORK/installed.after" > "$WORK/installed.diff"; then
  echo "[wheel] the runs wrote into the installed package ($site/stdr):" >&2; head -20 "$WORK/installed.diff" >&2; exit 1
fi
echo "[wheel] site-packages unchanged ($(wc -l < "$WORK/installed.after") entries under $site/stdr)"
echo "[wheel] ok"
