"""Shared pieces of the Hydra entry points."""
from __future__ import annotations

import os
from pathlib import Path

from ..config import CONFIG_DIR as _CONFIG_DIR

CONFIG_DIR = str(_CONFIG_DIR)


def use_fast_allocator_hint() -> None:
    """Say once how to get the measured 2x CPU speed-up from tcmalloc when it is not in use."""
    lib = "/usr/lib/x86_64-linux-gnu/libtcmalloc_minimal.so.4"
    if "tcmalloc" not in os.environ.get("LD_PRELOAD", "") and Path(lib).is_file():
        print(f"[stdr] hint: CPU training runs faster with LD_PRELOAD={lib} (scripts/run.sh sets it)")


def reproducible_blas() -> None:
    """Turn on oneMKL's conditional numerical reproducibility (CNR) mode unless the user chose
    one. Without it (CNR:OFF, the default) oneMKL documents that results may differ from run to
    run with the inputs' memory alignment. AUTO keeps the fastest code path for this CPU; it cost
    nothing measurable and gave the same bits here (docs/performance.md, "Determinism"). MKL
    reads it at its first call, so this runs before any training work."""
    os.environ.setdefault("MKL_CBWR", "AUTO")


def compose_config(overrides=(), config_name: str = "train", return_hydra_config: bool = False):
    """The config `stdr-train` (config_name="train") or `stdr-eval` ("eval") would run with these
    command-line overrides, composed with Hydra's compose API: for scripts, notebooks and tests
    (return_hydra_config: with the `hydra` node, e.g. a launcher's or a sweep's settings)."""
    from hydra import compose, initialize_config_dir

    from ..config import register
    register()
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base=None):
        return compose(config_name, overrides=list(overrides), return_hydra_config=return_hydra_config)
