"""Lens model of the Nerfies camera format and its undistortion onto a pinhole camera.

Pixel convention (as in cameras.py, Nerfies and COLMAP): the centre of pixel (i, j) is at
continuous coordinates (i + 0.5, j + 0.5). The lens model is OpenCV's (k1, k2, k3 radial,
p1, p2 tangential) applied to normalized image coordinates, followed by

    u = fx * x_d + skew * y_d + cx,    v = fy * y_d + cy,    fy = fx * pixel_aspect_ratio.

`undistortion()` picks a pinhole camera of the same size whose every pixel sees a point inside
the source image (the largest axis-aligned rectangle inside the undistorted image outline), and
the per-pixel source coordinates for cv2.remap.
"""
from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Optional

import cv2
import numpy as np

from ..io.files import write_atomic, write_png
from .images import read_image

CACHE_VERSION = 2  # the undistortion cache's: bump when the cached content or manifest layout changes


@dataclass(frozen=True)
class LensCamera:
    """Intrinsics with skew and distortion (the Nerfies camera minus its pose)."""

    fx: float
    fy: float
    cx: float
    cy: float
    skew: float
    k: tuple[float, float, float]   # radial k1, k2, k3
    p: tuple[float, float]          # tangential p1, p2
    width: int
    height: int

    @property
    def has_distortion(self) -> bool:
        return any(v != 0.0 for v in self.k + self.p)

    @classmethod
    def pinhole(cls, fx: float, fy: float, cx: float, cy: float, width: int, height: int) -> "LensCamera":
        return cls(fx, fy, cx, cy, 0.0, (0.0, 0.0, 0.0), (0.0, 0.0), width, height)

    @classmethod
    def from_dict(cls, d: dict) -> "LensCamera":
        return cls(**{**d, "k": tuple(d["k"]), "p": tuple(d["p"])})

    @property
    def is_pinhole(self) -> bool:
        return not self.has_distortion and self.skew == 0.0

    def scaled(self, width: int, height: int) -> "LensCamera":
        """The camera for the image resized to width x height (focal, centre and skew scale)."""
        rx, ry = width / self.width, height / self.height
        return replace(self, fx=self.fx * rx, fy=self.fy * ry, cx=self.cx * rx, cy=self.cy * ry,
                       skew=self.skew * rx, width=width, height=height)

    def distort(self, xy: np.ndarray) -> np.ndarray:
        """Undistorted normalized coordinates [N, 2] -> distorted normalized coordinates [N, 2]."""
        x, y = xy[..., 0], xy[..., 1]
        k1, k2, k3 = self.k
        p1, p2 = self.p
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        yd = y * radial + 2.0 * p2 * x * y + p1 * (r2 + 2.0 * y * y)
        return np.stack([xd, yd], -1)

    def undistort_normalized(self, xy_d: np.ndarray, iters: int = 30, tol: float = 1e-10) -> np.ndarray:
        """Invert `distort` by Newton's method (with a numerical Jacobian). [N, 2] -> [N, 2]."""
        xy_d = np.asarray(xy_d, dtype=np.float64)
        xy = xy_d.copy()
        h = 1e-7
        for _ in range(iters):
            f = self.distort(xy) - xy_d
            if np.abs(f).max(initial=0.0) < tol:
                break
            jx = (self.distort(xy + [h, 0.0]) - self.distort(xy - [h, 0.0])) / (2 * h)  # d f / d x
            jy = (self.distort(xy + [0.0, h]) - self.distort(xy - [0.0, h])) / (2 * h)  # d f / d y
            a, b, c, d = jx[:, 0], jy[:, 0], jx[:, 1], jy[:, 1]
            det = a * d - b * c
            if np.any(np.abs(det) < 1e-12):
                raise ValueError("lens distortion is not invertible over the image (Jacobian vanishes); "
                                 "check the camera's radial/tangential distortion coefficients")
            xy = xy - np.stack([(d * f[:, 0] - b * f[:, 1]) / det, (a * f[:, 1] - c * f[:, 0]) / det], -1)
        err = np.abs(self.distort(xy) - xy_d).max(initial=0.0)
        if err > 1e-6:
            raise ValueError(f"undistortion did not converge (residual {err:.2e}); the distortion "
                             "coefficients fold the image over itself")
        return xy

    def pixels_to_normalized(self, uv: np.ndarray) -> np.ndarray:
        """Pixel coordinates [N, 2] -> distorted normalized coordinates [N, 2]."""
        y = (uv[:, 1] - self.cy) / self.fy
        x = (uv[:, 0] - self.cx - self.skew * y) / self.fx
        return np.stack([x, y], -1)

    def normalized_to_pixels(self, xy_d: np.ndarray) -> np.ndarray:
        """Distorted normalized coordinates [N, 2] -> pixel coordinates [N, 2]."""
        u = self.fx * xy_d[:, 0] + self.skew * xy_d[:, 1] + self.cx
        v = self.fy * xy_d[:, 1] + self.cy
        return np.stack([u, v], -1)

    def project(self, x_cam: np.ndarray) -> np.ndarray:
        """Camera-space points [N, 3] (z forward) -> pixel coordinates [N, 2] through the lens."""
        xy = x_cam[:, :2] / x_cam[:, 2:3]
        return self.normalized_to_pixels(self.distort(xy))


def valid_rectangle(lens: LensCamera, samples: int = 256) -> tuple[float, float, float, float]:
    """(x0, x1, y0, y1): the largest axis-aligned rectangle, in undistorted normalized coordinates,
    whose points all see the inside of the source image (edges of the outline sampled densely)."""
    W, H = lens.width, lens.height
    s = np.linspace(0.0, 1.0, samples)
    edges = {
        "left": np.stack([np.zeros_like(s), s * H], -1), "right": np.stack([np.full_like(s, W), s * H], -1),
        "top": np.stack([s * W, np.zeros_like(s)], -1), "bottom": np.stack([s * W, np.full_like(s, H)], -1),
    }
    und = {k: lens.undistort_normalized(lens.pixels_to_normalized(v)) for k, v in edges.items()}
    x0, x1 = und["left"][:, 0].max(), und["right"][:, 0].min()
    y0, y1 = und["top"][:, 1].max(), und["bottom"][:, 1].min()
    if not (x1 > x0 and y1 > y0):
        raise ValueError("the undistorted image outline contains no rectangle; distortion too strong")
    return float(x0), float(x1), float(y0), float(y1)


def undistortion(lens: LensCamera) -> tuple[LensCamera, np.ndarray, np.ndarray]:
    """The pinhole camera of the undistorted image and the cv2.remap maps (float32 [H, W] each).

    The output has the source size; its pixel grid spans the valid rectangle edge to edge, so
    fx and fy may differ slightly (non-square pixels are exact for the rasterizer). Raises if a
    pixel would sample outside the source image.
    """
    W, H = lens.width, lens.height
    x0, x1, y0, y1 = valid_rectangle(lens)
    for _ in range(20):
        fx, fy = W / (x1 - x0), H / (y1 - y0)
        pin = LensCamera.pinhole(fx=fx, fy=fy, cx=-x0 * fx, cy=-y0 * fy, width=W, height=H)
        u, v = np.meshgrid(np.arange(W, dtype=np.float64) + 0.5, np.arange(H, dtype=np.float64) + 0.5)
        xy = np.stack([(u.ravel() - pin.cx) / pin.fx, (v.ravel() - pin.cy) / pin.fy], -1)
        src = lens.normalized_to_pixels(lens.distort(xy))
        # Pixel centres of the source lie in [0.5, W - 0.5]; allow the half pixel to the edge.
        if (src[:, 0].min() >= -1e-6 and src[:, 0].max() <= W + 1e-6
                and src[:, 1].min() >= -1e-6 and src[:, 1].max() <= H + 1e-6):
            break
        # The outline is not convex enough for the edge-sampled rectangle: shrink it by 0.5%.
        cx_, cy_, hw, hh = (x0 + x1) / 2, (y0 + y1) / 2, (x1 - x0) / 2 * 0.995, (y1 - y0) / 2 * 0.995
        x0, x1, y0, y1 = cx_ - hw, cx_ + hw, cy_ - hh, cy_ + hh
    else:
        raise ValueError("could not find an undistorted pinhole camera that stays inside the image")
    # cv2.remap addresses pixel centres at integer coordinates.
    map_x = (src[:, 0] - 0.5).reshape(H, W).astype(np.float32)
    map_y = (src[:, 1] - 0.5).reshape(H, W).astype(np.float32)
    return pin, map_x, map_y


def remap(img: np.ndarray, map_x: np.ndarray, map_y: np.ndarray) -> np.ndarray:
    """Resample img [H, W, C] at the map coordinates (bilinear, edge pixels replicated)."""
    out = cv2.remap(img, map_x, map_y, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out if out.ndim == img.ndim else out[..., None]


# ----------------------------------------------------------------------------- undistortion cache
def _sha1(data: bytes) -> str:
    return hashlib.sha1(data).hexdigest()


class UndistortCache:
    """Undistorted images as 16-bit PNGs with a manifest per image; a manifest mismatch (source
    bytes, lens, version) recomputes. One folder per scene path and image scale."""

    def __init__(self, root: Optional[Path], scene: Path, image_scale: int):
        self.dir = None
        if root is not None:
            key = _sha1(str(scene.resolve()).encode())[:10]
            self.dir = root / f"{scene.name}-{key}" / f"{image_scale}x"
        self.maps: dict[LensCamera, tuple[LensCamera, np.ndarray, np.ndarray]] = {}
        self.hits = 0
        self.misses = 0

    def _map(self, lens: LensCamera):
        if lens not in self.maps:
            self.maps[lens] = undistortion(lens)
        return self.maps[lens]

    def get(self, frame_id: str, src: Path, lens: LensCamera) -> tuple[np.ndarray, LensCamera]:
        raw = src.read_bytes()
        manifest = {"version": CACHE_VERSION, "source_sha1": _sha1(raw), "lens": asdict(lens)}
        if self.dir is not None:
            png, js = self.dir / f"{frame_id}.png", self.dir / f"{frame_id}.json"
            if png.is_file() and js.is_file():
                try:
                    saved = json.loads(js.read_text())
                except json.JSONDecodeError:
                    saved = {}
                if {k: saved.get(k) for k in manifest} == json.loads(json.dumps(manifest)):
                    try:
                        pin = LensCamera.from_dict(saved["pinhole"])
                    except (KeyError, TypeError):  # unreadable manifest: recompute below
                        pin = None
                    if pin is not None:
                        self.hits += 1
                        return read_image(png), pin
        pin, mx, my = self._map(lens)
        img = remap(read_image(src), mx, my)  # [H, W, C] RGB(A), float in [0, 1]
        self.misses += 1
        if self.dir is not None:
            self.dir.mkdir(parents=True, exist_ok=True)
            out = np.clip(np.round(img * 65535.0), 0, 65535).astype(np.uint16)
            write_png(png, out[..., [2, 1, 0, 3]] if out.shape[2] == 4 else out[..., ::-1], "cache")
            write_atomic(js, json.dumps({**manifest, "pinhole": asdict(pin)}, indent=1), "cache")
        return np.ascontiguousarray(img), pin
