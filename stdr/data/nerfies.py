"""Loader for the Nerfies on-disk format (NeRF-DS, HyperNeRF, Nerfies captures).

Layout (docs/data.md): dataset.json (ids, train_ids, val_ids), metadata.json ({id: {time_id |
warp_id, appearance_id, camera_id}}), scene.json (center, scale, near, far), camera/<id>.json,
rgb/<N>x/<id>.png, optional points.npy and colmap/sparse/0.

Nothing is inferred from folder names: the split rule (`split_mode`), the image folder
(`image_scale`), the time key, the scene normalization, the source of the intrinsics and what to
do with lens distortion are arguments, and every choice is recorded in `SceneData.meta`.
"""
from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Iterable, Optional

import cv2
import numpy as np
import torch

from ..errors import BadInput, MissingInput, MissingKey
from ..cameras import Camera
from .checks import check_pose, need_key, numbers
from .colmap import ColmapModel, read_model
from .dnerf import output_size
from .distortion import LensCamera, UndistortCache
from .lenses import lens_from_camera_json, lens_from_colmap, scale_for
from .images import read_image, resize
from .types import Frame, SceneData

log = logging.getLogger(__name__)

SPLIT_MODES = ("ids", "interp")
TIME_KEYS = ("auto", "time_id", "warp_id")
DISTORTION_MODES = ("undistort", "error", "ignore")
INTRINSICS_SOURCES = ("camera", "colmap")
POINTS_SOURCES = ("auto", "points_npy", "colmap", "none")
HELD_OUT = ("test", "val")  # both names address the held-out frames
COLMAP_DIR = "colmap/sparse/0"


def _read_json(path: Path, what: str) -> dict:
    if not path.is_file():
        raise MissingInput(f"{path} not found: {what}")
    try:
        doc = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise BadInput(f"{path}: malformed JSON at line {e.lineno} column {e.colno}: {e.msg}") from None
    if not isinstance(doc, dict):
        raise BadInput(f"{path}: expected a JSON object, got a {type(doc).__name__}")
    return doc


def _choice(name: str, value, allowed) -> None:
    if value not in allowed:
        raise BadInput(f"data.{name}={value!r}: use one of {', '.join(map(str, allowed))}")


def capture_defaults(root: Path) -> dict:
    """The loader settings a scene made by `stdr-data capture` names in its capture.json
    ({"loader": {"split_mode": ..., "image_scale": ...}}); {} for any other scene. They fill
    data.split_mode and data.image_scale only where those are null, and the run's data meta
    records that they did (`settings_from_capture_json`)."""
    path = root / "capture.json"
    if not path.is_file():
        return {}
    loader = _read_json(path, "").get("loader", {})
    if not isinstance(loader, dict):
        raise BadInput(f"{path}: 'loader' must be a mapping {{split_mode, image_scale}}")
    bad = sorted(set(loader) - {"split_mode", "image_scale"})
    if bad:
        raise BadInput(f"{path}: unknown loader setting(s) {bad}; capture.json names split_mode and image_scale")
    return dict(loader)


# ----------------------------------------------------------------------------- splits and time
def split_ids(dataset: dict, path: Path, mode: str) -> tuple[list[str], list[str]]:
    """(train ids, held-out ids) under `split_mode`.

    ids: dataset.json's train_ids / val_ids. interp: every 4th id of `ids` for training and the
    ids two after those for testing (the HyperNeRF interpolation protocol: test times are unseen).
    """
    _choice("split_mode", mode, SPLIT_MODES)
    ids = [str(i) for i in need_key(dataset, "ids", path)]
    if len(set(ids)) != len(ids):
        raise BadInput(f"{path}: 'ids' has duplicates")
    if mode == "interp":
        return ids[::4], ids[2::4]
    train = [str(i) for i in need_key(dataset, "train_ids", path, " (data.split_mode=ids needs it; "
                                   "data.split_mode=interp splits 'ids' instead)")]
    val = [str(i) for i in dataset.get("val_ids", [])]
    unknown = sorted(set(train + val) - set(ids))
    if unknown:
        raise BadInput(f"{path}: train_ids/val_ids name ids that are not in 'ids': {unknown[:5]}")
    both = sorted(set(train) & set(val))
    if both:
        raise BadInput(f"{path}: {len(both)} ids are in both train_ids and val_ids (e.g. {both[0]}); "
                         "the held-out frames would be trained on")
    if not train:
        raise BadInput(f"{path}: train_ids is empty")
    return train, val


def frame_times(metadata: dict, ids: list[str], path: Path, time_key: str) -> tuple[dict[str, float], str]:
    """Normalized times {id: t in [0, 1]} = key / max(key over `ids`), and the key used.

    time_key=auto reads `time_id`, falling back to `warp_id` when no entry has a time_id (the
    original Nerfies release and phone captures have only warp_id).
    """
    _choice("time_key", time_key, TIME_KEYS)
    missing = [i for i in ids if i not in metadata]
    if missing:
        raise MissingKey(f"{path}: no entry for id {missing[0]!r} ({len(missing)} ids missing)")
    key = time_key
    if key == "auto":
        has = [("time_id" in metadata[i]) for i in ids]
        if all(has):
            key = "time_id"
        elif not any(has):
            key = "warp_id"
        else:
            bad = ids[has.index(False)]
            raise MissingKey(f"{path}: some entries have 'time_id' and some not (e.g. {bad!r}); "
                           "set data.time_key=warp_id to use warp_id for all")
    raw = {}
    for i in ids:
        v = need_key(metadata[i], key, path, f" in entry {i!r} (data.time_key={time_key})")
        if not isinstance(v, (int, float)) or v < 0 or int(v) != v:
            raise BadInput(f"{path}: entry {i!r} has {key}={v!r}; expected a non-negative integer")
        raw[i] = int(v)
    top = max(raw.values())
    if top == 0:
        raise BadInput(f"{path}: every frame has {key}=0; a dynamic scene needs more than one time")
    return {i: v / top for i, v in raw.items()}, key


# ----------------------------------------------------------------------------- points
def load_points(root: Path, source: str, model: Optional[ColmapModel]):
    """(points [P, 3], colours [P, 3] in [0, 1] or None, source used) in the data's world frame."""
    _choice("points_source", source, POINTS_SOURCES)
    npy = root / "points.npy"
    if source == "none":
        return None, None, "none"
    if source in ("auto", "points_npy") and npy.is_file():
        pts = np.load(npy, allow_pickle=False)
        if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0:
            raise BadInput(f"{npy}: expected a non-empty [P, 3] array, got shape {pts.shape}")
        return pts.astype(np.float64), None, "points_npy"
    if source == "points_npy":
        raise MissingInput(f"{npy} not found (data.points_source=points_npy)")
    if model is None:
        if source == "colmap":
            raise MissingInput(f"{root / COLMAP_DIR}: no COLMAP model (data.points_source=colmap)")
        return None, None, "none"
    return model.xyz.copy(), model.rgb.astype(np.float32) / 255.0, "colmap"


# ----------------------------------------------------------------------------- the loader
def _settings(root: Path, split_mode: Optional[str], image_scale) -> tuple[str, int, dict]:
    """(split_mode, image_scale, the ones taken from the capture's capture.json): the keys a
    Nerfies scene needs, from the arguments or else from a capture's own record of them."""
    defaults = capture_defaults(root)
    used = {}
    if split_mode is None and "split_mode" in defaults:
        split_mode = used["split_mode"] = defaults["split_mode"]
    if image_scale is None and "image_scale" in defaults:
        image_scale = used["image_scale"] = defaults["image_scale"]
    if split_mode is None:
        raise BadInput("data.split_mode is not set: use 'ids' (dataset.json train_ids/val_ids: NeRF-DS, "
                       "HyperNeRF vrig) or 'interp' (every 4th frame trains, +2 tests: HyperNeRF interp)")
    if image_scale is None or int(image_scale) != image_scale or image_scale < 1:
        raise BadInput(f"data.image_scale={image_scale!r}: set the integer N of the rgb/<N>x folder to load")
    return split_mode, int(image_scale), used


def _normalization(spath: Path, normalize_scene: bool) -> tuple[np.ndarray, float]:
    """scene.json's (center, scale), or the raw world frame's (0, 1)."""
    if not normalize_scene:
        return np.zeros(3), 1.0
    sc = _read_json(spath, "set data.normalize_scene=false to use the raw world frame")
    center = np.asarray(need_key(sc, "center", spath), dtype=np.float64)
    scale = float(need_key(sc, "scale", spath))
    if center.shape != (3,) or not scale > 0:
        raise BadInput(f"{spath}: center must have 3 values and scale must be positive")
    return center, scale


class _FrameReader:
    """One frame of a Nerfies scene: its camera file, image, lens (undistorted or not) and time,
    in the normalized world frame and at the output size. `notes` collects what was checked or
    ignored once (the intrinsics check, an ignored distortion) for SceneData.meta."""

    def __init__(self, root: Path, dpath: Path, image_scale: int, intrinsics: str, distortion: str, model,
                 cache: UndistortCache, times: dict, center: np.ndarray, scale: float, resolution_scale: float,
                 max_width: Optional[int]):
        self.root, self.dpath, self.image_scale = root, dpath, image_scale
        self.img_dir, self.colmap_dir = root / "rgb" / f"{image_scale}x", root / COLMAP_DIR
        self.intrinsics, self.distortion, self.model, self.cache = intrinsics, distortion, model, cache
        self.times, self.center, self.scale = times, center, scale
        self.resolution_scale, self.max_width = resolution_scale, max_width
        self.notes: dict = {}

    def _image_path(self, fid: str) -> Path:
        ip = self.img_dir / f"{fid}.png"
        if not ip.is_file():
            alt = [p for p in (self.img_dir / f"{fid}.jpg", self.img_dir / f"{fid}.jpeg") if p.is_file()]
            if not alt:
                raise MissingInput(f"image for id {fid!r} not found: {ip}")
            ip = alt[0]
        return ip

    def _lens(self, fid: str, lens: LensCamera, w: int, h: int, cpath: Path) -> LensCamera:
        """The lens at the image's size: camera/<id>.json's, or COLMAP's (data.intrinsics=colmap);
        the first frame's two are compared once, and a difference over 0.5 % is warned about."""
        if self.intrinsics == "colmap":
            return lens_from_colmap(self.model, fid, self.colmap_dir).scaled(w, h)
        if self.model is not None and "intrinsics_check" not in self.notes:
            other = lens_from_colmap(self.model, fid, self.colmap_dir).scaled(w, h)
            rel = max(abs(other.fx / lens.fx - 1), abs(other.fy / lens.fy - 1))
            self.notes["intrinsics_check"] = {"camera_json": [lens.fx, lens.fy, lens.cx, lens.cy],
                                              "colmap": [other.fx, other.fy, other.cx, other.cy],
                                              "max_rel_focal_diff": rel}
            if rel > 5e-3:
                log.warning("%s: focal lengths (fx, fy) = (%.2f, %.2f) differ from the COLMAP model's "
                            "(%.2f, %.2f) by %.1f%%; set data.intrinsics=colmap to use COLMAP's "
                            "(docs/data.md)", cpath, lens.fx, lens.fy, other.fx, other.fy, 100 * rel)
        return lens

    def _pinhole(self, fid: str, ip: Path, lens: LensCamera, w: int, h: int, cpath: Path):
        """(image, pinhole camera): as read for a pinhole lens or data.distortion=ignore, else
        undistorted (cached), or an error with data.distortion=error."""
        if lens.is_pinhole or self.distortion == "ignore":
            if not lens.is_pinhole and "ignored" not in self.notes:
                self.notes["ignored"] = {"k": lens.k, "p": lens.p, "skew": lens.skew}
                log.warning("%s: lens distortion k=%s p=%s skew=%g IGNORED (data.distortion=ignore); "
                            "geometry is wrong away from the image centre", cpath, lens.k, lens.p, lens.skew)
            return read_image(ip), LensCamera.pinhole(lens.fx, lens.fy, lens.cx, lens.cy, w, h)
        if self.distortion == "error":
            raise BadInput(f"{cpath}: the camera has lens distortion (radial {list(lens.k)}, tangential "
                           f"{list(lens.p)}, skew {lens.skew}); set data.distortion=undistort to "
                           "undistort the images once (cached), or data.distortion=ignore to reproduce "
                           "the peers' pinhole approximation")
        return self.cache.get(fid, ip, lens)

    def frame(self, fid: str) -> Frame:
        cpath = self.root / "camera" / f"{fid}.json"
        cam = _read_json(cpath, f"every id needs a camera file (id {fid!r} from {self.dpath.name})")
        R = numbers(need_key(cam, "orientation", cpath), cpath, "orientation", (3, 3), finite=False)
        pos = numbers(need_key(cam, "position", cpath), cpath, "position", (3,), finite=False)
        check_pose(R, pos, f"{cpath} (id {fid!r})", "camera (orientation, position)")
        lens1 = lens_from_camera_json(cam, cpath)
        ip = self._image_path(fid)
        hdr = cv2.imread(str(ip), cv2.IMREAD_UNCHANGED)
        if hdr is None:
            raise BadInput(f"could not decode image {ip} (corrupt or unsupported format)")
        h, w = hdr.shape[:2]
        scale_for(lens1.width, lens1.height, w, h, self.image_scale, ip, cpath)
        img, pin = self._pinhole(fid, ip, self._lens(fid, lens1.scaled(w, h), w, h, cpath), w, h, cpath)
        img = img[..., :3]
        c_world = (pos - self.center) * self.scale
        camera = Camera(R=torch.from_numpy(R).float(), t=torch.from_numpy(-R @ c_world).float(), fx=pin.fx,
                        fy=pin.fy, cx=pin.cx, cy=pin.cy, width=pin.width, height=pin.height)
        W, H = output_size(w, h, self.resolution_scale, self.max_width)
        if (W, H) != (w, h):
            img = resize(img, W, H)
            camera = camera.scaled(W / w, H / h)
        return Frame(camera=camera, image=torch.from_numpy(np.ascontiguousarray(img)), time=self.times[fid],
                     name=f"rgb/{self.image_scale}x/{ip.name}")


def load_nerfies(root: str | Path, splits: Iterable[str] = ("train", "test"), *, split_mode: Optional[str],
                 image_scale: Optional[int], time_key: str = "auto", normalize_scene: bool = True,
                 distortion: str = "undistort", intrinsics: str = "camera", points_source: str = "auto",
                 background=(0.0, 0.0, 0.0), resolution_scale: float = 1.0, max_width: Optional[int] = None,
                 cache_dir: Optional[str | Path] = None) -> SceneData:
    root = Path(root)
    if not root.is_dir():
        raise MissingInput(f"Nerfies scene folder not found: {root} (set data.path)")
    split_mode, image_scale, defaults_used = _settings(root, split_mode, image_scale)
    for name, value, allowed in (("distortion", distortion, DISTORTION_MODES),
                                 ("intrinsics", intrinsics, INTRINSICS_SOURCES)):
        _choice(name, value, allowed)
    dpath, mpath, spath = root / "dataset.json", root / "metadata.json", root / "scene.json"
    dataset = _read_json(dpath, "a Nerfies scene folder holds dataset.json, metadata.json, scene.json, "
                         "camera/ and rgb/<N>x/")
    metadata = _read_json(mpath, "it maps every id to its time_id or warp_id")
    train_ids, held_ids = split_ids(dataset, dpath, split_mode)
    splits = list(dict.fromkeys(splits))
    for s in splits:
        if s != "train" and s not in HELD_OUT:
            raise BadInput(f"split {s!r}: a Nerfies scene has 'train' and the held-out frames "
                           "('test' or 'val', the same frames)")
        if s in HELD_OUT and not held_ids:
            raise BadInput(f"{dpath}: val_ids is empty, so there is nothing to evaluate on; "
                           "use data.split_mode=interp for a single-sequence capture")
    times, used_key = frame_times(metadata, train_ids + held_ids, mpath, time_key)
    center, scale = _normalization(spath, normalize_scene)
    colmap_dir = root / COLMAP_DIR
    model = read_model(colmap_dir) if (colmap_dir / "points3D.bin").is_file() else None
    if intrinsics == "colmap" and model is None:
        raise MissingInput(f"{colmap_dir}: data.intrinsics=colmap needs a COLMAP sparse model")
    img_dir = root / "rgb" / f"{image_scale}x"
    if not img_dir.is_dir():
        have = sorted(p.name for p in (root / "rgb").glob("*x")) if (root / "rgb").is_dir() else []
        raise MissingInput(f"{img_dir} not found (data.image_scale={image_scale}); this scene has "
                           f"rgb/{{{','.join(have)}}}")
    cache = UndistortCache(Path(cache_dir) if (cache_dir is not None and distortion == "undistort") else None,
                           root, image_scale)
    reader = _FrameReader(root, dpath, image_scale, intrinsics, distortion, model, cache, times, center, scale,
                          resolution_scale, max_width)
    data = {s: [reader.frame(i) for i in (train_ids if s == "train" else held_ids)] for s in splits}
    pts, cols, psrc = load_points(root, points_source, model)
    if pts is not None:
        pts = (pts - center) * scale
    notes = dict(reader.notes)
    if defaults_used:
        notes["settings_from_capture_json"] = defaults_used
    meta = {"format": "nerfies", "split_mode": split_mode, "image_scale": image_scale, "time_key": used_key,
            "normalize_scene": normalize_scene, "scene_center": center.tolist(), "scene_scale": scale,
            "distortion": distortion, "intrinsics": intrinsics, "points_source": psrc,
            "num_points": 0 if pts is None else int(len(pts)),
            "num_ids": {"train": len(train_ids), "held_out": len(held_ids)},
            "undistort_cache": {"hits": cache.hits, "misses": cache.misses,
                                "dir": None if cache.dir is None else str(cache.dir)}, **notes}
    return SceneData(root=str(root), splits=data, background=tuple(background), init_points=pts,
                     init_colors=cols, meta=meta)
