"""Build a SceneData from the `data` config."""
from __future__ import annotations

from pathlib import Path
from typing import Iterable

from .dnerf import load_dnerf
from .procedural import SceneOptions, embedded_scene
from .types import SceneData

FORMATS = ("procedural", "dnerf")


def project_root() -> Path:
    return Path(__file__).resolve().parents[2]


def resolve_data_path(path: str, base: str | Path | None = None) -> Path:
    p = Path(path).expanduser()
    if not p.is_absolute():
        p = Path(base or Path.cwd()) / p
    return p.resolve()


def scene_folder(cfg, base: str | Path | None = None) -> Path:
    """The on-disk D-NeRF-format folder the config points at (generating the embedded scene)."""
    if cfg.format == "procedural":
        opts = SceneOptions(**dict(cfg.procedural))
        cache = Path(cfg.cache_dir)
        if not cache.is_absolute():
            cache = project_root() / cache
        return embedded_scene(cache, opts)
    if cfg.format == "dnerf":
        if not cfg.path:
            raise ValueError("data.path is not set: point it at a D-NeRF scene folder "
                             "(the one holding transforms_train.json)")
        return resolve_data_path(cfg.path, base)
    raise ValueError(f"data.format={cfg.format!r} is not one of {FORMATS}")


def load_scene(cfg, splits: Iterable[str], base: str | Path | None = None) -> SceneData:
    folder = scene_folder(cfg, base)
    scene = load_dnerf(folder, splits, background=cfg.background,
                       resolution_scale=cfg.resolution_scale, max_width=cfg.max_width)
    scene.meta["name"] = cfg.name
    return scene
