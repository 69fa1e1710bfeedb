"""The one camera/frame type every loader yields."""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Optional

import numpy as np
from torch import Tensor

from ..cameras import Camera


@dataclass
class Frame:
    camera: Camera
    image: Tensor            # [H, W, 3] float in [0, 1], composited over the dataset background
    time: float              # normalized to [0, 1]
    name: str                # file the image came from, relative to the dataset root
    alpha: Optional[Tensor] = None  # [H, W] in [0, 1] when the source has an alpha channel

    def to(self, device) -> "Frame":
        """The frame with its image (and alpha) and camera on `device`."""
        return replace(self, camera=self.camera.to(device), image=self.image.to(device),
                       alpha=None if self.alpha is None else self.alpha.to(device))


@dataclass
class SceneData:
    """A loaded scene: frames per split and what training needs to know about it."""

    root: str
    splits: dict[str, list[Frame]]
    background: tuple[float, float, float]
    init_points: Optional[np.ndarray] = None  # [P, 3] from the data, when it has any
    init_colors: Optional[np.ndarray] = None  # [P, 3] in [0, 1], when the points come with colours
    meta: dict = field(default_factory=dict)

    def to(self, device) -> "SceneData":
        """Move every frame's image and camera to `device`, once (in place; returns self)."""
        for name, frames in self.splits.items():
            self.splits[name] = [f.to(device) for f in frames]
        return self

    def frames(self, split: str) -> list[Frame]:
        if split not in self.splits:
            raise KeyError(f"split {split!r} not loaded from {self.root}; available: {sorted(self.splits)}")
        return self.splits[split]

    def train_times(self) -> np.ndarray:
        """Sorted distinct training timestamps (STDR's K columns)."""
        return np.unique(np.array([f.time for f in self.frames("train")], dtype=np.float64))

    def camera_centers(self, split: str = "train") -> np.ndarray:
        return np.stack([f.camera.center.double().cpu().numpy() for f in self.frames(split)])
