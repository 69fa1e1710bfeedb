"""Small configurations for tests, smoke checks and stdr-tool identity-check.

The embedded procedural scene at test size trains in seconds on a CPU, crosses every phase
boundary when given a short schedule, and needs no data files.
"""
from __future__ import annotations

import re
from pathlib import Path

from .store import compose_config
from .baselines import get_baseline

#: the embedded scene at 64 px with 40 training, 2 val and 4 test frames
TINY_SCENE = ["data.procedural.resolution=64", "data.procedural.n_train=40", "data.procedural.n_val=2",
              "data.procedural.n_test=4"]


make_cfg = compose_config  # `stdr-train`'s config for these overrides


_NESTED = re.compile(r"^\+?baseline\.(\w+)\.")


def applicable(overrides, baseline: str) -> list[str]:
    """`overrides` without the `baseline.<sub>.*` keys that baseline `baseline`'s config does not
    have (e.g. baseline.scgs.num_nodes for deform), so one short schedule serves every baseline.
    stdr-train itself rejects such keys."""
    fields = get_baseline(baseline).config.__dataclass_fields__
    return [o for o in overrides if not ((m := _NESTED.match(o)) and m.group(1) not in fields)]


def tiny_config(folder: str | Path, extra=()):
    """The tiny embedded scene (generated into folder/cache), 1500 initial Gaussians, no LPIPS,
    no images or progress bar, on the CPU (so that the suite's bit-exact comparisons mean the
    same on a machine with a GPU; the CUDA tests say device=cuda); `extra` overrides follow
    (those of other baselines' sub-configs are skipped: `applicable`)."""
    base = TINY_SCENE + [f"data.cache_dir={Path(folder) / 'cache'}", "device=cpu", "model.init_num=1500", "eval.lpips=false",
                         "train.progress=false", "eval.save_images=false", "train.image_every=0", *extra]
    name = make_cfg([o for o in base if not _NESTED.match(o)]).baseline.name
    return make_cfg(applicable(base, name))
