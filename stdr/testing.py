"""Small configurations for tests, smoke checks and scripts/identity_check.py.

The embedded procedural scene at test size trains in seconds on a CPU, crosses every phase
boundary when given a short schedule, and needs no data files.
"""
from __future__ import annotations

from pathlib import Path

from .cli.common import compose_config

#: the embedded scene at 64 px with 40 training, 2 val and 4 test frames
TINY_SCENE = ["data.procedural.resolution=64", "data.procedural.n_train=40", "data.procedural.n_val=2",
              "data.procedural.n_test=4"]


make_cfg = compose_config  # `stdr-train`'s config for these overrides


def tiny_config(folder: str | Path, extra=()):
    """The tiny embedded scene (generated into folder/cache), 1500 initial Gaussians, no LPIPS,
    no images or progress bar; `extra` overrides follow."""
    return make_cfg(TINY_SCENE + [
        f"data.cache_dir={Path(folder) / 'cache'}", "model.init_num=1500", "eval.lpips=false",
        "train.progress=false", "eval.save_images=false", "train.image_every=0", *extra])
