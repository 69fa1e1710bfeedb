"""Image reading and resizing shared by the loaders."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ..errors import BadInput, MissingInput


def read_image(path: Path) -> np.ndarray:
    """uint8/uint16 image -> float32 [H, W, C] in [0, 1], C in {3, 4} (RGB(A) order)."""
    if not path.is_file():
        raise MissingInput(f"image not found: {path}")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise BadInput(f"could not decode image {path} (corrupt or unsupported format)")
    scale = 65535.0 if img.dtype == np.uint16 else 255.0
    img = img.astype(np.float32) / scale
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, -1)
    if img.shape[2] == 4:
        img = img[..., [2, 1, 0, 3]]
    elif img.shape[2] == 3:
        img = img[..., ::-1]
    else:
        raise BadInput(f"{path}: expected 1, 3 or 4 channels, got {img.shape[2]}")
    return np.ascontiguousarray(img)


def image_channels(path: Path) -> int:
    """Decode the image at `path` as the loaders do (read_image) and return its channel count
    (3 or 4); a file that does not decode is a BadInput naming it."""
    return read_image(Path(path)).shape[2]


def composite(rgba: np.ndarray, background) -> tuple[np.ndarray, np.ndarray | None]:
    """Straight-alpha RGBA [H, W, 4] over a background colour -> (RGB, alpha); RGB passes through."""
    if rgba.shape[2] == 3:
        return rgba, None
    a = rgba[..., 3:4]
    rgb = rgba[..., :3] * a + np.asarray(background, np.float32) * (1.0 - a)
    return rgb, a[..., 0]


def resize(img: np.ndarray, width: int, height: int) -> np.ndarray:
    if img.shape[1] == width and img.shape[0] == height:
        return img
    out = cv2.resize(img, (width, height), interpolation=cv2.INTER_AREA)
    return out if out.ndim == img.ndim else out[..., None]
