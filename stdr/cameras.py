"""Pinhole cameras in the OpenCV convention (x right, y down, z forward), world-to-camera.

Pixel convention: continuous image coordinates put the *centre* of pixel (i, j) at
(i + 0.5, j + 0.5), so a principal point of (W/2, H/2) is the exact image centre. This is the
convention of gsplat and of NeRF-style loaders that cast rays through (i + 0.5, j + 0.5).
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch
from torch import Tensor


@dataclass(frozen=True)
class Camera:
    """One pinhole camera. `R`, `t` map world to camera: x_cam = R @ x_world + t."""

    R: Tensor  # [3, 3]
    t: Tensor  # [3]
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def __post_init__(self):
        if tuple(self.R.shape) != (3, 3) or tuple(self.t.shape) != (3,):
            raise ValueError(f"Camera needs R [3,3] and t [3], got {tuple(self.R.shape)}, {tuple(self.t.shape)}")
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"Camera needs a positive image size, got {self.width}x{self.height}")

    @property
    def K(self) -> Tensor:  # [3, 3]
        return torch.tensor([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]],
                            dtype=self.R.dtype, device=self.R.device)

    @property
    def viewmat(self) -> Tensor:  # [4, 4] world -> camera
        m = torch.eye(4, dtype=self.R.dtype, device=self.R.device)
        m[:3, :3] = self.R
        m[:3, 3] = self.t
        return m

    @property
    def center(self) -> Tensor:  # [3] camera centre in world coordinates
        return -self.R.T @ self.t

    def to(self, device: torch.device | str) -> "Camera":
        """The same camera with R and t on `device`."""
        return replace(self, R=self.R.to(device), t=self.t.to(device))

    def scaled(self, sx: float, sy: float | None = None) -> "Camera":
        """The same camera for an image resized by (sx, sy); intrinsics scale with it."""
        sy = sx if sy is None else sy
        w, h = int(round(self.width * sx)), int(round(self.height * sy))
        # Scale by the exact size ratio that rounding produced, so that the image edges map
        # onto the image edges.
        rx, ry = w / self.width, h / self.height
        return replace(self, fx=self.fx * rx, fy=self.fy * ry, cx=self.cx * rx, cy=self.cy * ry,
                       width=w, height=h)

    def project(self, x_world: Tensor) -> tuple[Tensor, Tensor]:
        """Pixel coordinates [N, 2] and depths [N] of world points [N, 3]."""
        xc = x_world @ self.R.T + self.t
        z = xc[:, 2]
        u = self.fx * xc[:, 0] / z + self.cx
        v = self.fy * xc[:, 1] / z + self.cy
        return torch.stack([u, v], -1), z


# Blender/OpenGL camera axes are (x right, y up, z backward); OpenCV's are (x right, y down,
# z forward). The two differ by a rotation of pi about x: flip the signs of y and z.
_GL_TO_CV = np.diag([1.0, -1.0, -1.0])


def opengl_c2w_to_opencv_w2c(c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Convert a Blender/OpenGL camera-to-world matrix [4,4] (or [3,4]) to OpenCV world-to-camera.

    Returns (R [3,3], t [3]) with x_cam = R @ x_world + t. Unlike the conversion copied through the
    3DGS forks, this keeps the sign of every translation component (theirs flips t_x and t_y,
    which only goes unnoticed for cameras that look at the origin).
    """
    c2w = np.asarray(c2w, dtype=np.float64)
    if c2w.shape not in ((4, 4), (3, 4)):
        raise ValueError(f"transform_matrix must be 4x4 or 3x4, got shape {c2w.shape}")
    R_c2w_cv = c2w[:3, :3] @ _GL_TO_CV  # camera axes in OpenCV convention, as world vectors
    center = c2w[:3, 3]
    R = R_c2w_cv.T
    t = -R @ center
    return R, t


def focal_from_fov(fov: float, size: int) -> float:
    """Focal length in pixels for a full field of view `fov` (radians) across `size` pixels."""
    return 0.5 * size / float(np.tan(0.5 * fov))
