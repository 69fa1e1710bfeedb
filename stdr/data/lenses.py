"""The intrinsics of a Nerfies-format capture (stdr.data.nerfies): from its camera files or from
the COLMAP model they were made from, and the check that an image folder holds the scale asked for.

Every number is checked (finite, positive focal lengths, the principal point inside the image) and
kept: principal point, pixel aspect ratio, skew and lens distortion (stdr.data.distortion.LensCamera).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import BadInput, MissingKey
from .checks import check_intrinsics, need_key, numbers
from .colmap import ColmapModel
from .distortion import LensCamera


def lens_from_camera_json(cam: dict, path: Path) -> LensCamera:
    """The 1x intrinsics of a Nerfies camera file (checked: finite, positive focal lengths, the
    principal point inside the image_size it gives)."""
    f = float(numbers(need_key(cam, "focal_length", path), path, "focal_length"))
    pp = list(numbers(need_key(cam, "principal_point", path), path, "principal_point", (2,)))
    size = list(numbers(need_key(cam, "image_size", path), path, "image_size", (2,)))
    if any(v != int(v) or v < 1 for v in size):
        raise BadInput(f"{path}: image_size={size} must be two whole numbers >= 1 [w, h]")
    radial = list(numbers(cam.get("radial_distortion", [0.0, 0.0, 0.0]), path, "radial_distortion", (-1,)))
    if not 1 <= len(radial) <= 3:
        raise BadInput(f"{path}: radial_distortion must hold k1[, k2[, k3]], got {radial}")
    radial = (radial + [0.0, 0.0])[:3]
    tang = list(numbers(cam.get("tangential_distortion", cam.get("tangential", [0.0, 0.0])), path,
                        "tangential_distortion", (2,)))
    par = float(numbers(cam.get("pixel_aspect_ratio", 1.0), path, "pixel_aspect_ratio"))
    skew = float(numbers(cam.get("skew", 0.0), path, "skew"))
    if f <= 0 or par <= 0:
        raise BadInput(f"{path}: focal_length and pixel_aspect_ratio must be positive")
    check_intrinsics(f, f * par, float(pp[0]), float(pp[1]), int(size[0]), int(size[1]), str(path))
    return LensCamera(fx=f, fy=f * par, cx=float(pp[0]), cy=float(pp[1]), skew=skew,
                      k=tuple(float(v) for v in radial), p=tuple(float(v) for v in tang),
                      width=int(size[0]), height=int(size[1]))


def lens_from_colmap(model: ColmapModel, image_name: str, folder: Path) -> LensCamera:
    """The intrinsics COLMAP estimated for one image (at the size COLMAP saw)."""
    img = next((im for im in model.images.values() if Path(im.name).stem == image_name), None)
    if img is None:
        raise MissingKey(f"{folder}: no image named {image_name}.* in the COLMAP model; "
                       "use data.intrinsics=camera")
    c = model.cameras[img.camera_id]
    p = c.params
    z = 0.0
    table = {
        "SIMPLE_PINHOLE": lambda: (p[0], p[0], p[1], p[2], (z, z, z), (z, z)),
        "PINHOLE": lambda: (p[0], p[1], p[2], p[3], (z, z, z), (z, z)),
        "SIMPLE_RADIAL": lambda: (p[0], p[0], p[1], p[2], (p[3], z, z), (z, z)),
        "RADIAL": lambda: (p[0], p[0], p[1], p[2], (p[3], p[4], z), (z, z)),
        "OPENCV": lambda: (p[0], p[1], p[2], p[3], (p[4], p[5], z), (p[6], p[7])),
        "FULL_OPENCV": lambda: (p[0], p[1], p[2], p[3], (p[4], p[5], p[8]), (p[6], p[7])),
    }
    if c.model not in table or (c.model == "FULL_OPENCV" and np.any(p[9:] != 0)):
        raise BadInput(f"{folder}: COLMAP camera model {c.model} is not supported; "
                         "use data.intrinsics=camera")
    fx, fy, cx, cy, k, tp = table[c.model]()
    return LensCamera(float(fx), float(fy), float(cx), float(cy), 0.0, tuple(map(float, k)),
                      tuple(map(float, tp)), c.width, c.height)


def scale_for(w1: int, h1: int, w: int, h: int, image_scale: int, img_path: Path, cam_path: Path) -> None:
    """Raise unless (w, h) is the 1x size divided by image_scale (either rounding)."""
    ew, eh = w1 / image_scale, h1 / image_scale
    if abs(w - ew) >= 1.0 or abs(h - eh) >= 1.0:
        raise BadInput(f"{img_path}: image is {w}x{h}, but {cam_path.name} gives image_size "
                         f"{w1}x{h1}, so rgb/{image_scale}x should hold {ew:g}x{eh:g} images; "
                         "check data.image_scale and that the rgb folders are not mixed up")
