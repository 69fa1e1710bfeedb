"""`stdr-build`: compile the rasterizer extensions ahead of time (otherwise built on first use).

    stdr-build            # the CPU backend, and the CUDA backend when torch has CUDA
    stdr-build --verbose  # show the compiler's output

Exits non-zero when a backend that this machine should have cannot be built.
"""
from __future__ import annotations

import argparse
import sys
import time

import torch

from .. import extension


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="stdr-build", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--verbose", action="store_true", help="print the compiler's output")
    args = ap.parse_args(argv)
    kinds = ["cpu"] + (["cuda"] if torch.cuda.is_available() and torch.version.cuda else [])
    print(f"[stdr-build] cache: {extension.cache_root()} (set STDR_EXT_DIR to move it)")
    failed = False
    for kind in kinds:
        t0 = time.perf_counter()
        try:
            mod = extension.load_extension(kind, verbose=args.verbose)
        except extension.BuildError as e:
            print(f"[stdr-build] {kind}: FAILED: {e}", file=sys.stderr)
            failed = True
            continue
        print(f"[stdr-build] {kind}: ok ({time.perf_counter() - t0:.1f} s) {mod.__file__}")
    if "cuda" not in kinds:
        print("[stdr-build] cuda: skipped (torch has no CUDA on this machine)")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
