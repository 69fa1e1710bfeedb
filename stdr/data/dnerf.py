"""D-NeRF loader: transforms_{train,val,test}.json + RGBA PNGs, Blender/OpenGL cameras."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Iterable, Optional

import numpy as np
import torch

from ..errors import BadInput, MissingInput, MissingKey
from ..cameras import Camera, focal_from_fov, opengl_c2w_to_opencv_w2c
from .checks import check_fov, check_intrinsics, check_pose, check_time
from .images import composite, read_image, resize
from .types import Frame, SceneData

BACKGROUNDS = {"white": (1.0, 1.0, 1.0), "black": (0.0, 0.0, 0.0)}


def parse_background(bg) -> tuple[float, float, float]:
    if isinstance(bg, str):
        if bg not in BACKGROUNDS:
            raise BadInput(f"data.background={bg!r}: use 'white', 'black' or [r, g, b] in [0, 1]")
        return BACKGROUNDS[bg]
    vals = tuple(float(x) for x in bg)
    if len(vals) != 3 or not all(0.0 <= v <= 1.0 for v in vals):
        raise BadInput(f"data.background={bg!r}: expected three values in [0, 1]")
    return vals


def _read_json(path: Path) -> dict:
    if not path.is_file():
        raise MissingInput(f"{path} not found: a D-NeRF scene folder holds "
                                "transforms_train.json, transforms_val.json and transforms_test.json")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise BadInput(f"{path}: malformed JSON at line {e.lineno} column {e.colno}: {e.msg}") from None


def _resolve_image(root: Path, file_path: str, json_path: Path, i: int) -> Path:
    p = (root / file_path).resolve()
    if not p.is_relative_to(root.resolve()):
        raise BadInput(f"{json_path}: frames[{i}].file_path={file_path!r} points outside the scene folder")
    if p.suffix == "":
        for ext in (".png", ".jpg", ".jpeg"):
            if p.with_suffix(ext).is_file():
                return p.with_suffix(ext)
        p = p.with_suffix(".png")
    if not p.is_file():
        raise MissingInput(f"{json_path}: frames[{i}] image {file_path!r} not found (looked for {p})")
    return p


class SplitImages:
    """The images of one D-NeRF split as they are read: none listed twice (a broken conversion
    or a copy-paste in the JSON), and all with an alpha channel or none (RGBA frames are
    composited over data.background, RGB ones are not: a mix trains on two backgrounds). Either
    is an error naming both frames (the loader and `stdr-data verify`)."""

    def __init__(self, json_path: Path):
        self.jp = json_path
        self.seen: dict[Path, int] = {}
        self.first: Optional[tuple[bool, int, str]] = None

    def add(self, i: int, path: Path, channels: int) -> None:
        if path in self.seen:
            raise BadInput(f"{self.jp}: frames[{i}] and frames[{self.seen[path]}] both use the image {path.name}: "
                           "each frame of a split has its own image; fix the file_path of one of them")
        self.seen[path] = i
        alpha = channels == 4
        if self.first is None:
            self.first = (alpha, i, path.name)
        elif self.first[0] != alpha:
            def has(a: bool) -> str:
                return "has an alpha channel" if a else "has none"
            raise BadInput(f"{self.jp}: frames[{i}] ({path.name}) {has(alpha)} but frames[{self.first[1]}] "
                           f"({self.first[2]}) {has(self.first[0])}: a D-NeRF split's images are all RGBA (composited "
                           "over data.background) or all RGB; convert the odd ones")


def output_size(width: int, height: int, resolution_scale: float, max_width: Optional[int]) -> tuple[int, int]:
    """Image size after `resolution_scale`, then capped at `max_width` (aspect kept)."""
    if resolution_scale <= 0:
        raise BadInput(f"data.resolution_scale must be > 0, got {resolution_scale}")
    s = resolution_scale
    if max_width and width * s > max_width:
        s = max_width / width
    return max(1, int(round(width * s))), max(1, int(round(height * s)))


def load_dnerf_split(root: str | Path, split: str, background=(1.0, 1.0, 1.0),
                     resolution_scale: float = 1.0, max_width: Optional[int] = None) -> list[Frame]:
    root = Path(root)
    jp = root / f"transforms_{split}.json"
    meta = _read_json(jp)
    if not isinstance(meta, dict):
        raise BadInput(f"{jp}: expected an object with camera_angle_x and frames, got a {type(meta).__name__}")
    for key in ("camera_angle_x", "frames"):
        if key not in meta:
            raise MissingKey(f"{jp}: missing key {key!r}")
    if not isinstance(meta["frames"], list) or not meta["frames"]:
        raise BadInput(f"{jp}: 'frames' must be a non-empty list")
    fov_x = check_fov(meta["camera_angle_x"], jp, "camera_angle_x")
    frames, size0, name0, images = [], None, None, SplitImages(jp)
    for i, fr in enumerate(meta["frames"]):
        if not isinstance(fr, dict):
            raise BadInput(f"{jp}: frames[{i}] must be an object with file_path, time and transform_matrix, "
                           f"got {fr!r:.40}")
        for key in ("file_path", "transform_matrix"):
            if key not in fr:
                raise MissingKey(f"{jp}: frames[{i}] is missing key {key!r}")
        if "time" not in fr:
            raise MissingKey(f"{jp}: frames[{i}] has no 'time'; D-NeRF frames need a time in [0, 1]")
        if not isinstance(fr["file_path"], str) or not fr["file_path"]:
            raise BadInput(f"{jp}: frames[{i}].file_path={fr['file_path']!r:.40} is not a file path")
        where = f"{jp}: frames[{i}] ({fr['file_path']})"
        t = check_time(fr["time"], f"{jp}: frames[{i}]")
        try:
            c2w = np.asarray(fr["transform_matrix"], dtype=np.float64)
        except (TypeError, ValueError):
            raise BadInput(f"{where}: transform_matrix is not a matrix of numbers") from None
        if c2w.shape not in ((4, 4), (3, 4)):
            raise BadInput(f"{jp}: frames[{i}].transform_matrix must be 4x4 or 3x4, got shape {c2w.shape}")
        check_pose(c2w[:3, :3], c2w[:3, 3], where, "transform_matrix")
        ip = _resolve_image(root, fr["file_path"], jp, i)
        img = read_image(ip)
        images.add(i, ip, img.shape[2])
        H0, W0 = img.shape[:2]
        if size0 is None:
            size0, name0 = (W0, H0), ip.name
        elif (W0, H0) != size0:
            raise BadInput(f"{ip}: image is {W0}x{H0} but {name0} is {size0[0]}x{size0[1]}; "
                             "all frames of a D-NeRF scene must have one size")
        R, tvec = opengl_c2w_to_opencv_w2c(c2w)
        fx = focal_from_fov(fov_x, W0)
        fy = focal_from_fov(check_fov(meta["camera_angle_y"], jp, "camera_angle_y"), H0) if "camera_angle_y" in meta else fx
        check_intrinsics(fx, fy, W0 / 2.0, H0 / 2.0, W0, H0, where)
        cam = Camera(R=torch.from_numpy(R).float(), t=torch.from_numpy(tvec).float(), fx=fx, fy=fy,
                     cx=W0 / 2.0, cy=H0 / 2.0, width=W0, height=H0)
        W, H = output_size(W0, H0, resolution_scale, max_width)
        if (W, H) != (W0, H0):
            img = resize(img, W, H)
            cam = cam.scaled(W / W0, H / H0)
        rgb, alpha = composite(img, background)
        frames.append(Frame(camera=cam, image=torch.from_numpy(np.ascontiguousarray(rgb)), time=t,
                            name=str(ip.relative_to(root.resolve()) if ip.is_absolute() else ip),
                            alpha=None if alpha is None else torch.from_numpy(np.ascontiguousarray(alpha))))
    return frames


def load_dnerf(root: str | Path, splits: Iterable[str] = ("train", "test"), background="white",
               resolution_scale: float = 1.0, max_width: Optional[int] = None) -> SceneData:
    root = Path(root)
    if not root.is_dir():
        raise MissingInput(f"D-NeRF scene folder not found: {root} (set data.path)")
    bg = parse_background(background)
    data = {s: load_dnerf_split(root, s, bg, resolution_scale, max_width) for s in dict.fromkeys(splits)}
    return SceneData(root=str(root), splits=data, background=bg, meta={"format": "dnerf"})
