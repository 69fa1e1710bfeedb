"""The capture's settings (CaptureConfig) and its input: the frames of a phone video or an image
folder, each window of `stride` frames giving its first or its sharpest (stdr.data.capture, stage 1)."""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import cv2
import numpy as np

from ..errors import UserError
from ..io.files import write_png

VIDEO_SUFFIXES = (".mp4", ".mov", ".m4v", ".avi", ".mkv", ".webm")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
SELECT_MODES = ("sharpest", "uniform")
MATCHERS = ("auto", "exhaustive", "sequential")


class CaptureError(UserError, RuntimeError):
    """A capture that cannot become a dataset; the message says why and what to try."""


@dataclass
class CaptureConfig:
    frames: Optional[int] = 150       # about this many frames kept (None: every frame / image)
    select: str = "sharpest"           # sharpest | uniform: which frame of each stride window is kept
    max_size: int = 960                # long side in pixels after downscaling (0: keep)
    val_every: int = 8                 # every k-th frame (by rank, offset k // 2) is held out
    matcher: str = "auto"              # auto: exhaustive up to exhaustive_max frames, else sequential
    exhaustive_max: int = 150
    overlap: int = 10                  # sequential matching: neighbours on each side
    vocab_tree: Optional[str] = None   # sequential matching: loop detection with this vocabulary tree
    min_registered: float = 0.7        # fail when SfM registers a smaller share of the frames
    camera_model: str = "OPENCV"
    seed: int = 0
    threads: int = -1                  # pycolmap's threads (-1: all cores)

    def check(self) -> None:
        if self.frames is not None and self.frames < 3:
            raise CaptureError(f"--frames {self.frames}: a capture needs at least 3 frames")
        if self.select not in SELECT_MODES:
            raise CaptureError(f"--select {self.select!r}: use one of {', '.join(SELECT_MODES)}")
        if self.matcher not in MATCHERS:
            raise CaptureError(f"--matcher {self.matcher!r}: use one of {', '.join(MATCHERS)}")
        if self.val_every < 2:
            raise CaptureError(f"--val-every {self.val_every}: at least 2 (every k-th frame is held out)")
        if not 0.0 < self.min_registered <= 1.0:
            raise CaptureError(f"--min-registered {self.min_registered}: a share in (0, 1]")
        if self.max_size < 0:
            raise CaptureError(f"--max-size {self.max_size}: 0 (keep) or a positive number of pixels")
        if self.vocab_tree is not None and not Path(self.vocab_tree).is_file():
            raise CaptureError(f"--vocab-tree {self.vocab_tree}: file not found (COLMAP's vocabulary tree "
                               "for loop detection; leave it out to match sequentially without loops)")


@dataclass
class FrameRecord:
    id: str               # output id (rgb/1x/<id>.png, camera/<id>.json)
    source: str           # source file name (images) or frame index (video)
    source_index: int     # index among the source's frames (decode order) or images (name order)
    time_sec: float       # presentation time (video) or rank (images)
    sharpness: float      # variance of the Laplacian of the grey image (after downscaling)
    registered: bool = False


def sharpness(img: np.ndarray) -> float:
    """Variance of the Laplacian of the grey image (higher: sharper)."""
    grey = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY) if img.ndim == 3 else img
    return float(cv2.Laplacian(grey, cv2.CV_64F).var())


def downscale(img: np.ndarray, max_size: int) -> np.ndarray:
    h, w = img.shape[:2]
    if not max_size or max(h, w) <= max_size:
        return img
    s = max_size / max(h, w)
    return cv2.resize(img, (max(1, round(w * s)), max(1, round(h * s))), interpolation=cv2.INTER_AREA)


def _stride(n: int, target: Optional[int]) -> int:
    return 1 if (target is None or n <= target) else math.ceil(n / target)


def progress_bar(total, desc):
    from tqdm import tqdm
    return tqdm(total=total, desc=f"[capture] {desc}", unit="frame", leave=True, mininterval=1.0)


def _windows(items, stride: int, select: str, image_of=lambda it: it):
    """Yield the kept (index, item, sharpness) of each window of `stride` consecutive (index, item)
    pairs: its first (uniform) or its sharpest item."""
    best, start = None, None
    for i, it in items:
        w = i // stride
        if start is not None and w != start:
            yield best
            best = None
        start = w
        if select == "uniform":
            if best is None:
                best = (i, it, sharpness(image_of(it)))
        else:
            s = sharpness(image_of(it))
            if best is None or s > best[2]:
                best = (i, it, s)
    if best is not None:
        yield best


def _write_png(path: Path, img: np.ndarray) -> None:
    write_png(path, cv2.cvtColor(img, cv2.COLOR_RGB2BGR), "frames")


def video_frames(video: Path, out: Path, cfg: CaptureConfig) -> list[FrameRecord]:
    """Decode `video`, keep one frame per stride window, save them as out/<id>.png (RGB)."""
    try:
        import av
    except ImportError:
        raise CaptureError("reading a video needs PyAV: pip install 'stdr[capture]' (or pip install av)") from None
    try:
        container = av.open(str(video))
    except Exception as e:  # noqa: BLE001 - PyAV raises many error types for unreadable files
        raise CaptureError(f"{video}: not a readable video ({type(e).__name__}: {e})") from None
    with container:
        if not container.streams.video:
            raise CaptureError(f"{video}: has no video stream")
        stream = container.streams.video[0]
        n = stream.frames
        if not n:  # the container does not say: count the packets
            n = sum(1 for p in container.demux(stream) if p.size)
            container.seek(0)
        stride = _stride(n, cfg.frames)
        tb = float(stream.time_base) if stream.time_base else None
        t0 = None
        records: list[FrameRecord] = []
        bar = progress_bar(n, f"frames of {video.name} (every {stride})")

        def decoded():
            nonlocal t0
            for i, fr in enumerate(container.decode(stream)):
                bar.update(1)
                img = fr.to_ndarray(format="rgb24")
                rot = int(getattr(fr, "rotation", 0) or 0) % 360
                if rot:  # display matrix: rotate counter-clockwise by `rot` degrees to show upright
                    img = np.ascontiguousarray(np.rot90(img, k=rot // 90))
                pts = fr.pts if fr.pts is not None else i
                sec = pts * tb if tb else i / float(stream.average_rate or 30)
                t0 = sec if t0 is None else t0
                yield i, (downscale(img, cfg.max_size), sec - t0)

        for i, (img, sec), score in _windows(decoded(), stride, cfg.select, image_of=lambda it: it[0]):
            fid = f"{i:06d}"
            _write_png(out / f"{fid}.png", img)
            records.append(FrameRecord(id=fid, source=f"frame {i}", source_index=i, time_sec=float(sec),
                                       sharpness=score))
        bar.close()
    if len(records) < 3:
        raise CaptureError(f"{video}: only {len(records)} frame(s) decoded; a capture needs at least 3")
    return records


def folder_frames(folder: Path, out: Path, cfg: CaptureConfig) -> list[FrameRecord]:
    """The images of `folder` in name order (time = rank), one per stride window, as out/<id>.png."""
    paths = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())
    if len(paths) < 3:
        raise CaptureError(f"{folder}: {len(paths)} image(s) ({', '.join(IMAGE_SUFFIXES)}); a capture needs at least 3")
    stems = [p.stem for p in paths]
    keep_names = len(set(stems)) == len(stems) and all(s.replace("_", "").replace("-", "").isalnum() for s in stems)
    stride = _stride(len(paths), cfg.frames)
    bar = progress_bar(len(paths), f"images of {folder.name} (every {stride})")

    def read():
        size = None
        for i, p in enumerate(paths):
            bar.update(1)
            img = cv2.imread(str(p), cv2.IMREAD_COLOR)
            if img is None:
                raise CaptureError(f"could not decode image {p} (corrupt or unsupported format)")
            size = size or (img.shape[:2], p.name)
            if img.shape[:2] != size[0]:  # every image, as it is read
                raise CaptureError(f"{p}: {img.shape[1]}x{img.shape[0]} pixels, but {size[1]} is "
                                   f"{size[0][1]}x{size[0][0]}; one camera needs one image size")
            yield i, downscale(cv2.cvtColor(img, cv2.COLOR_BGR2RGB), cfg.max_size)

    records = []
    for i, img, score in _windows(read(), stride, cfg.select):
        fid = stems[i] if keep_names else f"{i:06d}"
        _write_png(out / f"{fid}.png", img)
        records.append(FrameRecord(id=fid, source=paths[i].name, source_index=i, time_sec=float(i), sharpness=score))
    bar.close()
    return records


# ----------------------------------------------------------------------------- structure from motion
