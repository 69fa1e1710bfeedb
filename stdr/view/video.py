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

import contextlib
import math
import time
from dataclasses import replace
from pathlib import Path
from typing import Iterable, Iterator, Optional

import numpy as np
import torch

from .core import ViewRun, look_at_point, render_view, scale_to_width, to_uint8
from ..geometry import so3_exp
from ..device import available_bytes
from ..errors import IO_FIXES, UserError
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


#: a video whose frames would take longer than this to render is announced before it starts
LONG_VIDEO_S = 3600.0


def write_video(frames: Iterable[np.ndarray], stem: Path, fps: float, fmt: str = "auto",
                total: Optional[int] = None, progress: bool = True, comment: str = "") -> Path:
    """frames (uint8 [H, W, 3], all the same size; any iterable: an MP4 encodes each as it comes,
    so memory stays flat in their number; Pillow keeps a GIF's frames until it writes the file) to stem.mp4 (fmt auto with an ffmpeg writer, or mp4) or
    stem.gif; returns the path written. `total`: the frame count, for the progress bar and for the
    note, after the first frame, of a video that will take more than an hour. The file is written
    beside its name and moved there only once the encoder has finished and the file reads back with
    every frame: a full disk, a file size limit or an encoder that died leaves the previous video
    and raises an error naming the path. `comment`: the file's comment metadata (the model's
    checkpoint, stdr.io.checkpoint.source_line)."""
    import imageio.v2 as imageio
    from tqdm import tqdm
    if fmt not in ("auto", "mp4", "gif"):
        raise ValueError(f"--format {fmt!r}: auto, mp4 or gif")
    if fmt == "mp4" and not mp4_available():
        raise RuntimeError("--format mp4 needs an ffmpeg writer: pip install imageio-ffmpeg (or --format gif)")
    use_mp4 = fmt == "mp4" or (fmt == "auto" and mp4_available())
    make_folder(stem.parent)
    path = stem.with_suffix(".mp4" if use_mp4 else ".gif")
    bar = tqdm(total=total, desc=path.name, unit="frame", disable=not progress or total is None, leave=False)
    n = 0
    with atomic_path(path, "video") as tmp:  # the previous video stays until the new one is complete
        if use_mp4:
            writer = imageio.get_writer(tmp, fps=fps, codec="libx264", quality=8, macro_block_size=1,
                                        ffmpeg_params=["-pix_fmt", "yuv420p", *(["-metadata", f"comment={comment}"]
                                                                                 if comment else [])])
        else:
            writer = imageio.get_writer(tmp, mode="I", duration=1000.0 / fps, loop=0,
                                        **({"comment": comment} if comment else {}))
        t0 = time.perf_counter()
        try:
            for f in frames:
                writer.append_data(_even(f) if use_mp4 else f)
                n += 1
                bar.update()
                if n == 1 and total and not use_mp4:
                    _check_gif_memory(path, f, total)
                if n == 1 and total and (time.perf_counter() - t0) * total > LONG_VIDEO_S:
                    secs = time.perf_counter() - t0
                    print(f"[stdr] {path}: {total:,} frames at about {secs:.2f} s each: about "
                          f"{secs * total / 3600:.1f} h (fewer frames, a smaller --width, or a GPU)", flush=True)
            writer.close()  # the encoder finishes the file (a GIF is written whole here)
        except BaseException as e:
            _abandon(writer)
            if isinstance(e, UserError):
                raise
            if isinstance(e, (BrokenPipeError, RuntimeError)) or (isinstance(e, OSError) and e.errno not in IO_FIXES):
                raise VideoError(f"{path}: the video encoder failed after {n} frame(s) ({e}); nothing was written "
                                 "(a full disk or a file size limit?)") from None
            raise
        finally:
            bar.close()
        if n == 0:
            raise ValueError("no frames to write")
        check_video(tmp, n, path)
    return path


def _check_gif_memory(path: Path, frame: np.ndarray, total: int) -> None:
    """A GIF's frames stay in memory until the file is written (Pillow): refuse, after the first
    frame, one that would take more than half the memory available, before the rest is rendered."""
    need, free = frame.nbytes * total, available_bytes(torch.device("cpu"))
    if free is not None and need > free / 2:
        h, w = frame.shape[:2]
        raise VideoError(f"{path}: a GIF holds every frame in memory until it is written: {total:,} frames of "
                         f"{w}x{h} need about {need / 2**30:.1f} GiB, and {free / 2**30:.1f} GiB is available. Write "
                         "an MP4 (pip install imageio-ffmpeg; it streams), or fewer --frames or a smaller --width")


def _abandon(writer) -> None:
    """Close a writer that failed, without writing what it still holds (Pillow keeps a GIF's
    frames until close) and without a second error from its finalizer."""
    inst = getattr(writer, "instance", None)
    pending = getattr(inst, "images_to_write", None)
    if isinstance(pending, list):
        pending.clear()
    with contextlib.suppress(Exception):
        writer.close()


class VideoError(UserError, OSError):
    """The encoder did not produce a complete video: the message names the file and the cause."""

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else "video error"


def check_video(tmp: Path, frames: int, path: Path) -> None:
    """The written file reads back whole: an MP4 with `frames` frames (ffmpeg counts the stream's
    packets), a GIF decoded to its end (Pillow merges identical consecutive frames into one
    longer frame, so a GIF may hold fewer); else VideoError naming `path`."""
    import imageio.v2 as imageio
    got, why = 0, ""
    try:
        if tmp.stat().st_size == 0:
            raise ValueError("the file is empty")
        with imageio.get_reader(tmp) as r:
            got = r.count_frames() if tmp.suffix == ".mp4" else sum(1 for _ in r)
        if tmp.suffix == ".gif":
            with open(tmp, "rb") as f:
                f.seek(-1, 2)
                if f.read(1) != b";":
                    raise ValueError("no GIF trailer: the file was cut short")
            if 1 <= got <= frames:
                got = frames  # decoded to its end, trailer and all: complete
    except Exception as e:  # noqa: BLE001 - any decoding failure is the file's
        why = f": {str(e).splitlines()[0] if str(e) else type(e).__name__}"
    if got != frames:
        raise VideoError(f"{path}: the encoder's file reads back with {got} of {frames} frames{why}; nothing was "
                         "written (a full disk or a file size limit?)")


def _rotate_about(cam, pivot: np.ndarray, axis: np.ndarray, angle: float):
    """The camera turned by `angle` about the line through `pivot` along `axis` (world frame)."""
    D = so3_exp(torch.tensor(axis / np.linalg.norm(axis) * angle, dtype=torch.float64)).numpy()  # world rotation
    R = cam.R.detach().double().cpu().numpy()
    c = cam.center.detach().double().cpu().numpy()
    c2 = pivot + D @ (c - pivot)
    R2 = R @ D.T
    t2 = -R2 @ c2
    return replace(cam, R=torch.tensor(R2, dtype=cam.R.dtype), t=torch.tensor(t2, dtype=cam.t.dtype))


def time_sweep(run: ViewRun, frames: int, width: int, view: str = "rgb") -> Iterator[np.ndarray]:
    cam, _ = run.default_camera()
    cam = scale_to_width(cam, width).to(run.model.device)
    return (render_view(run.model, cam, float(t), view) for t in np.linspace(0.0, 1.0, frames))


def orbit(run: ViewRun, frames: int, width: int, view: str = "rgb", turns: float = 1.0) -> Iterator[np.ndarray]:
    cam, _ = run.default_camera()
    cam = scale_to_width(cam, width)
    pivot = look_at_point(run, cam)
    up = -cam.R.detach().double().cpu().numpy().T[:, 1]
    for k, t in enumerate(np.linspace(0.0, 1.0, frames)):
        c = _rotate_about(cam, pivot, up, 2 * math.pi * turns * k / frames)
        yield render_view(run.model, c.to(run.model.device), float(t), view)


def compare(run: ViewRun, width: int, split: str = "test", view: str = "rgb") -> Iterator[np.ndarray]:
    frames = sorted(run.frames.get(split, []), key=lambda f: f.time)
    if not frames:
        raise ValueError(f"compare: no {split!r} frames (the run's data could not be read, or the split is empty)"
                         + (f": {run.data_note}" if run.data_note else ""))
    return (_compared(run, f, width, view) for f in frames)


def _compared(run: ViewRun, f, width: int, view: str) -> np.ndarray:
    """Ground truth | render | error (x 4) of one frame."""
    cam = scale_to_width(f.camera, width)
    img = render_view(run.model, cam.to(run.model.device), f.time, view)
    gt = f.image.permute(2, 0, 1)[None].float()
    gt = torch.nn.functional.interpolate(gt, size=(cam.height, cam.width), mode="area")[0].permute(1, 2, 0)
    gt8 = to_uint8(gt)
    err = np.clip(np.abs(img.astype(np.int16) - gt8.astype(np.int16)) * 4, 0, 255).astype(np.uint8)
    return np.concatenate([gt8, img, err], 1)


def path_frames(run: ViewRun, cameras, times, view: str = "rgb") -> Iterator[np.ndarray]:
    """One frame per camera of a camera path (stdr.view.camera_path), each at its time, rendered
    as the writer asks for it."""
    return (render_view(run.model, c.to(run.model.device), float(t), view) for c, t in zip(cameras, times))


def render_videos(run: ViewRun, out: Path, kinds=KINDS, width: int | None = None, frames: int = 60,
                  fps: float = 15.0, view: str = "rgb", split: str = "test", fmt: str = "auto",
                  comment: str = "") -> dict[str, Path]:
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
        total = len(run.frames.get(split, [])) if k == "compare" else frames
        paths[k] = write_video(imgs, Path(out) / f"{k}_{view}", fps, fmt, total=total, comment=comment)
    return paths
