"""Build a SceneData from the `data` config."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Iterable, Optional

from ..errors import BadInput
from .dnerf import SplitImages, _read_json, _resolve_image, load_dnerf, parse_background
from .fetch import DataError
from .images import image_channels
from .nerfies import load_nerfies
from .procedural import SceneOptions, embedded_scene
from .stress import apply_stress, check_stress
from .types import SceneData
from .. import source_checkout, user_cache

FORMATS = ("procedural", "dnerf", "nerfies")


def cache_base() -> Path:
    """Where relative cache paths of the config (data.cache_dir, data.undistort_cache) live: the
    source checkout when stdr runs from one (pyproject.toml beside the package), else the user
    cache ($XDG_CACHE_HOME/stdr, default ~/.cache/stdr), so an installed wheel never writes into
    site-packages."""
    return source_checkout() or user_cache()


def resolve_data_path(path: str, base: str | Path | None = None) -> Path:
    p = Path(path).expanduser()
    if not p.is_absolute():
        p = Path(base or Path.cwd()) / p
    return p.resolve()


def repo_path(path: str) -> Path:
    """A cache path from the config: relative paths are under `cache_base()`."""
    p = Path(path).expanduser()
    return p if p.is_absolute() else cache_base() / p


def scene_folder(cfg, base: str | Path | None = None) -> Path:
    """The scene folder the config points at (generating the embedded scene)."""
    if cfg.format == "procedural":
        opts = SceneOptions(**dict(cfg.procedural))
        return embedded_scene(repo_path(cfg.cache_dir), opts)
    if cfg.format in ("dnerf", "nerfies"):
        if not cfg.path:
            what = ("a D-NeRF scene folder (the one holding transforms_train.json)" if cfg.format == "dnerf"
                    else "a Nerfies-format scene folder (the one holding dataset.json)")
            raise BadInput(f"data.path is not set: point it at {what}")
        return resolve_data_path(cfg.path, base)
    raise BadInput(f"data.format={cfg.format!r} is not one of {FORMATS}")


def load_scene(cfg, splits: Iterable[str], base: str | Path | None = None, seed: int = 0) -> SceneData:
    """The scene `cfg` (the data config) points at, with `splits` loaded; data.stress (seeded
    with `seed` unless it names its own) then transforms the training split."""
    check_stress(cfg.stress)  # before any image is read
    folder = scene_folder(cfg, base)
    if cfg.format == "nerfies":
        scene = load_nerfies(folder, splits, split_mode=cfg.split_mode, image_scale=cfg.image_scale,
                             time_key=cfg.time_key, normalize_scene=cfg.normalize_scene,
                             distortion=cfg.distortion, intrinsics=cfg.intrinsics,
                             points_source=cfg.points_source, background=parse_background(cfg.background),
                             resolution_scale=cfg.resolution_scale, max_width=cfg.max_width,
                             cache_dir=repo_path(cfg.undistort_cache) if cfg.undistort_cache else None)
    else:
        scene = load_dnerf(folder, splits, background=cfg.background,
                           resolution_scale=cfg.resolution_scale, max_width=cfg.max_width)
    scene.meta["name"] = cfg.name
    apply_stress(scene, cfg.stress, seed)
    return scene


# ------------------------------------------------------------------ a scene folder's layout
def verify_scene(folder: Path, fmt: str) -> int:
    """Check a scene folder against its loader's needs; returns the number of images checked.
    Raises DataError naming the first missing piece."""
    folder = Path(folder)
    if fmt == "dnerf":
        n = 0
        for split in ("train", "val", "test"):
            jp = folder / f"transforms_{split}.json"
            try:
                frames = _read_json(jp).get("frames")
                if not frames:
                    raise DataError(f"{jp}: no frames")
                images = SplitImages(jp)
                for i, fr in enumerate(frames):
                    ip = _resolve_image(folder, fr["file_path"], jp, i)
                    images.add(i, ip, image_channels(ip))  # every image decoded, as the loader will
                    n += 1
            except (FileNotFoundError, ValueError, KeyError) as e:
                raise DataError(f"{folder} is not a complete D-NeRF scene: {e}") from None
        return n
    if fmt == "nerfies":
        need = ["dataset.json", "metadata.json", "scene.json"]
        missing = [f for f in need if not (folder / f).is_file()]
        if missing:
            raise DataError(f"{folder} is not a Nerfies-format scene: missing {', '.join(missing)}")
        try:
            ids = json.loads((folder / "dataset.json").read_text())["ids"]
        except (json.JSONDecodeError, KeyError) as e:
            raise DataError(f"{folder / 'dataset.json'}: no readable 'ids' list ({e})") from None
        scales = sorted(p for p in (folder / "rgb").glob("*x") if p.is_dir())
        if not scales:
            raise DataError(f"{folder}: no rgb/<N>x image folder")
        n = 0
        for i in ids:
            if not (folder / "camera" / f"{i}.json").is_file():
                raise DataError(f"{folder}: camera/{i}.json missing (id listed in dataset.json)")
            found = [p for s in scales for p in (s / f"{i}.png", s / f"{i}.jpg") if p.is_file()]
            if not found:
                raise DataError(f"{folder}: no image of id {i} under rgb/*x/")
            for p in found:  # decoded, as the loader will
                try:
                    image_channels(p)
                except ValueError as e:
                    raise DataError(f"{folder} is not a complete Nerfies-format scene: {e}") from None
            n += 1
        return n
    raise ValueError(f"unknown format {fmt!r}: dnerf or nerfies")


def detect_format(folder: Path) -> Optional[str]:
    if (Path(folder) / "transforms_train.json").is_file():
        return "dnerf"
    if (Path(folder) / "dataset.json").is_file():
        return "nerfies"
    return None
