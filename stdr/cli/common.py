"""Shared pieces of the Hydra entry points."""
from __future__ import annotations

import os
from pathlib import Path

CONFIG_DIR = str(Path(__file__).resolve().parents[2] / "configs")


def use_fast_allocator_hint() -> None:
    """Say once how to get the measured 2x CPU speed-up from tcmalloc when it is not in use."""
    lib = "/usr/lib/x86_64-linux-gnu/libtcmalloc_minimal.so.4"
    if "tcmalloc" not in os.environ.get("LD_PRELOAD", "") and Path(lib).is_file():
        print(f"[stdr] hint: CPU training runs faster with LD_PRELOAD={lib} (scripts/run.sh sets it)")
