"""stdr-render: videos of a trained run (imageio: MP4 with the ffmpeg writer of imageio-ffmpeg, a
dependency; GIF with --format gif or where that writer is missing; the file's suffix and the
printed line say which).

* time: a time sweep t = 0 ... 1 from a fixed camera (the first test camera);
* orbit: the camera turns about the scene while time advances, around the point the first test
  camera looks at (at the Gaussians' depth), about that camera's up axis;
* compare: ground truth | render | error (|difference| x 4) side by side along a split's frames,
  in time order;
* a camera path (`--path camera_path.json`, nerfstudio's format: stdr.view.camera_path): its
  cameras at their times, at the path's fps.
Every frame is `stdr.view.core.render_view` of the chosen view (rgb, depth, alpha, mask, dynamic).
"""
from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from .core import ViewRun, look_at_point, render_view, scale_to_width, to_uint8
from ..geometry import so3_exp
from ..io.files import atomic_path, make_folder

KINDS = ("time", "orbit", "compare")


def _even(img: np.ndarray) -> np.ndarray:
    """Pad to even height and width (H.264 in yuv420p needs them) with edge pixels."""
    h, w = img.shape[:2]
    return np.pad(img, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge") if (h % 2 or w % 2) else img


def mp4_available() -> bool:
    try:
        import imageio_ffmpeg  # noqa: F401
    except ImportError:
        return False
    return True


def write_video(frames: list[np.ndarray], stem: Path, fps: float, fmt: str = "auto") -> Path:
    """frames (uint8 [H, W, 3], all the same size) to stem.mp4 (fmt auto with an ffmpeg writer,
    or mp4) or stem.gif; returns the path written."""
    import imageio.v2 as imageio
    if not frames:
        raise ValueError("no frames to write")
    if fmt not in ("auto", "mp4", "gif"):
        raise ValueError(f"--format {fmt!r}: auto, mp4 or gif")
    if fmt == "mp4" and not mp4_available():
        raise RuntimeError("--format mp4 needs an ffmpeg writer: pip install imageio-ffmpeg (or --format gif)")
    use_mp4 = fmt == "mp4" or (fmt == "auto" and mp4_available())
    make_folder(stem.parent)
    path = stem.with_suffix(".mp4" if use_mp4 else ".gif")
    with atomic_path(path, "video") as tmp:  # the previous video stays until the new one is complete
        if use_mp4:
            with imageio.get_writer(tmp, fps=fps, codec="libx264", quality=8, macro_block_size=1,
                                    ffmpeg_params=["-pix_fmt", "yuv420p"]) as w:
                for f in frames:
                    w.append_data(_even(f))
        else:
            imageio.mimsave(tmp, frames, duration=1000.0 / fps, loop=0)
    return path


def _rotate_about(cam, pivot: np.ndarray, axis: np.ndarray, angle: float):
    """The camera turned by `angle` about the line through `pivot` along `axis` (world frame)."""
    D = so3_exp(torch.tensor(axis / np.linalg.norm(axis) * angle, dtype=torch.float64)).numpy()  # world rotation
    R = cam.R.detach().double().cpu().numpy()
    c = cam.center.detach().double().cpu().numpy()
    c2 = pivot + D @ (c - pivot)
    R2 = R @ D.T
    t2 = -R2 @ c2
    return replace(cam, R=torch.tensor(R2, dtype=cam.R.dtype), t=torch.tensor(t2, dtype=cam.t.dtype))


def time_sweep(run: ViewRun, frames: int, width: int, view: str = "rgb") -> list[np.ndarray]:
    cam, _ = run.default_camera()
    cam = scale_to_width(cam, width).to(run.model.device)
    return [render_view(run.model, cam, float(t), view) for t in np.linspace(0.0, 1.0, frames)]


def orbit(run: ViewRun, frames: int, width: int, view: str = "rgb", turns: float = 1.0) -> list[np.ndarray]:
    cam, _ = run.default_camera()
    cam = scale_to_width(cam, width)
    pivot = look_at_point(run, cam)
    up = -cam.R.detach().double().cpu().numpy().T[:, 1]
    out = []
    for k, t in enumerate(np.linspace(0.0, 1.0, frames)):
        c = _rotate_about(cam, pivot, up, 2 * math.pi * turns * k / frames)
        out.append(render_view(run.model, c.to(run.model.device), float(t), view))
    return out


def compare(run: ViewRun, width: int, split: str = "test", view: str = "rgb") -> list[np.ndarray]:
    frames = sorted(run.frames.get(split, []), key=lambda f: f.time)
    if not frames:
        raise ValueError(f"compare: no {split!r} frames (the run's data could not be read, or the split is empty)"
                         + (f": {run.data_note}" if run.data_note else ""))
    out = []
    for f in frames:
        cam = scale_to_width(f.camera, width)
        img = render_view(run.model, cam.to(run.model.device), f.time, view)
        gt = f.image.permute(2, 0, 1)[None].float()
        gt = torch.nn.functional.interpolate(gt, size=(cam.height, cam.width), mode="area")[0].permute(1, 2, 0)
        gt8 = to_uint8(gt)
        err = np.clip(np.abs(img.astype(np.int16) - gt8.astype(np.int16)) * 4, 0, 255).astype(np.uint8)
        out.append(np.concatenate([gt8, img, err], 1))
    return out


def path_frames(run: ViewRun, cameras, times, view: str = "rgb") -> list[np.ndarray]:
    """One frame per camera of a camera path (stdr.view.camera_path), each at its time."""
    return [render_view(run.model, c.to(run.model.device), float(t), view) for c, t in zip(cameras, times)]


def render_videos(run: ViewRun, out: Path, kinds=KINDS, width: int | None = None, frames: int = 60,
                  fps: float = 15.0, view: str = "rgb", split: str = "test", fmt: str = "auto") -> dict[str, Path]:
    """Write each of `kinds` as out/<kind>_<view>.<mp4|gif>; returns {kind: path}."""
    bad = [k for k in kinds if k not in KINDS]
    if bad:
        raise ValueError(f"--kinds {','.join(bad)}: choose from {', '.join(KINDS)}")
    if frames < 2:
        raise ValueError(f"--frames {frames}: at least 2")
    if fps <= 0:
        raise ValueError(f"--fps {fps}: must be positive")
    width = width or run.default_camera()[0].width
    paths = {}
    for k in kinds:
        imgs = (time_sweep(run, frames, width, view) if k == "time" else orbit(run, frames, width, view)
                if k == "orbit" else compare(run, width, split, view))
        paths[k] = write_video(imgs, Path(out) / f"{k}_{view}", fps, fmt)
    return paths
