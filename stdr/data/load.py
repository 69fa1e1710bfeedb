"""Build a SceneData from the `data` config."""
from __future__ import annotations

import copy
import hashlib
import json
from pathlib import Path
from typing import Iterable, Optional

from ..errors import BadInput
from ..io.files import read_json, write_atomic
from .dnerf import SplitImages, _read_json, _resolve_image, load_dnerf, parse_background
from .fetch import DataError
from .images import image_channels
from .nerfies import capture_defaults, load_nerfies
from .procedural import SceneOptions, embedded_scene
from .stress import apply_stress, check_stress
from .types import SceneData
from .. import user_cache

FORMATS = ("procedural", "dnerf", "nerfies")


def cache_base() -> Path:
    """Where relative cache paths of the config (data.cache_dir, data.undistort_cache) live: the
    user cache ($XDG_CACHE_HOME/stdr, default ~/.cache/stdr), whether stdr is installed, installed
    editable or run from its checkout: a cache never lands in the installed source."""
    return user_cache()


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


# ------------------------------------------------------------------ a run's data, pinned
#: the run folder's record of the data it trained on (stdr-train writes it; readers check it)
RUN_DATA = "data.json"


def split_fingerprint(scene: SceneData, split: str) -> dict:
    """What identifies a split's data on disk: its frame count, the files' total bytes and a
    SHA-256 over each file's name and size (names relative to the scene folder). Reading no
    pixels, it is cheap; a replaced, resized or re-encoded image changes it."""
    root = Path(scene.root)
    lines, total = [], 0
    for name in sorted(f.name for f in scene.frames(split)):
        try:
            size = (root / name).stat().st_size
        except OSError:
            size = -1
        total += max(size, 0)
        lines.append(f"{name}\t{size}")
    return {"frames": len(lines), "bytes": total, "sha256": hashlib.sha256("\n".join(lines).encode()).hexdigest()}


def pin_run_data(run_dir: Path, cfg, scene: SceneData, base: str | Path | None) -> None:
    """At the start of training: a new run records its scene folder (absolute, and data.path as
    given) and its splits' fingerprints in run_dir/data.json; a resumed run is checked against it
    (BadInput naming both when the data changed: training on would mix two scenes)."""
    run_dir = Path(run_dir)
    rec = read_run_data(run_dir)
    prints = {sp: split_fingerprint(scene, sp) for sp, frames in scene.splits.items() if frames}
    if rec is not None:
        check_run_data(run_dir, rec, scene, prints)
        return
    write_atomic(run_dir / RUN_DATA, json.dumps({"root": str(Path(scene.root).resolve()), "path": cfg.path,
                                                 "base": None if base is None else str(base), "splits": prints},
                                                indent=1), site="config")


def read_run_data(run_dir: Path) -> Optional[dict]:
    """run_dir/data.json, or None for a run trained before it was written."""
    path = Path(run_dir) / RUN_DATA
    if not path.is_file():
        return None
    rec = read_json(path, "run data record")
    if not isinstance(rec, dict) or not isinstance(rec.get("splits"), dict):
        raise BadInput(f"{path}: not a run's data record (root, splits); it is written by stdr-train")
    return rec


def check_run_data(run_dir: Path, rec: dict, scene: SceneData, prints: Optional[dict] = None) -> None:
    """Every split both have: the scene's fingerprint equals the one the run recorded; else one
    BadInput naming the run, the folder read and how to point at the right one."""
    prints = prints or {sp: split_fingerprint(scene, sp) for sp, frames in scene.splits.items() if frames}
    for sp, fp in prints.items():
        was = rec["splits"].get(sp)
        if was is not None and was != fp:
            raise BadInput(
                f"{run_dir}: the data at {scene.root} is not what this run trained on: its {sp} split has "
                f"{fp['frames']} frames, {fp['bytes']:,} bytes here and had {was['frames']} frames, "
                f"{was['bytes']:,} bytes in {rec['root']} (data.path {rec.get('path')!r}). Point data.path at the "
                f"run's scene (its folder as it was at {rec['root']}), or evaluate a run of this data")


def load_run_scene(run_dir: Path, cfg, splits: Iterable[str], base: str | Path | None = None, seed: int = 0) -> SceneData:
    """The scene of a trained run (stdr-eval, stdr-view, stdr-render, stdr-tool pack): the folder
    the run recorded in data.json while it is there (whatever the working folder), else data.path
    as the config gives it; then checked against the run's fingerprints (check_run_data)."""
    rec = read_run_data(run_dir)
    data = cfg.data if hasattr(cfg, "data") else cfg
    if rec is not None and data.format != "procedural" and Path(rec["root"]).is_dir():
        data = copy.deepcopy(data)
        data.path = rec["root"]
    scene = load_scene(data, splits, base=base, seed=seed)
    if rec is not None:
        check_run_data(run_dir, rec, scene)
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
        try:  # the loader's own checks, as stdr-train applies them (times, fields of view, one image size)
            load_dnerf(folder, ("train", "val", "test"), max_width=8)
        except (FileNotFoundError, ValueError, KeyError) as e:
            raise DataError(f"{folder} is not a D-NeRF scene stdr-train reads: {e}") from None
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
        _nerfies_loads(folder, [int(s.name[:-1]) for s in scales if s.name[:-1].isdigit()])
        return n
    raise ValueError(f"unknown format {fmt!r}: dnerf or nerfies")


def _nerfies_loads(folder: Path, image_scales: list[int]) -> None:
    """The Nerfies loader's own checks, as stdr-train applies them (the split, times, cameras,
    lens, normalization, points), at every rgb/<N>x scale (images at 8 px: decoding is checked
    above). The split mode is the capture's own (capture.json), else `ids` where dataset.json
    holds val_ids, else `interp`."""
    defaults = capture_defaults(folder)
    split_mode = defaults.get("split_mode")
    if split_mode is None:
        try:
            split_mode = "ids" if json.loads((folder / "dataset.json").read_text()).get("val_ids") else "interp"
        except (json.JSONDecodeError, AttributeError) as e:
            raise DataError(f"{folder / 'dataset.json'}: not a JSON object ({e})") from None
    for scale in image_scales:
        try:
            load_nerfies(folder, ("train", "test"), split_mode=split_mode, image_scale=scale, max_width=8)
        except (FileNotFoundError, ValueError, KeyError) as e:
            raise DataError(f"{folder} is not a Nerfies-format scene stdr-train reads (data.split_mode={split_mode}, "
                            f"data.image_scale={scale}): {e}") from None


def detect_format(folder: Path) -> Optional[str]:
    if (Path(folder) / "transforms_train.json").is_file():
        return "dnerf"
    if (Path(folder) / "dataset.json").is_file():
        return "nerfies"
    return None
