"""A phone video or a folder of images to a dataset in the Nerfies format (`stdr-data capture`).

Stages, each timed and recorded in the output's `capture.json`:

1. frames: a video is decoded with PyAV; about `frames` of its frames are kept at a fixed stride,
   each window of `stride` consecutive frames giving either its first frame (`select=uniform`)
   or its sharpest (`select=sharpest`, variance of the Laplacian). Every kept frame keeps its
   presentation time; frames are downscaled to `max_size` pixels on the long side. An image
   folder is taken in name order (time = rank) with the same stride and downscaling.
2. sfm: pycolmap on the CPU: SIFT features with one shared OPENCV camera, exhaustive matching for
   up to `exhaustive_max` frames, else sequential matching (loop detection when a vocabulary tree
   file is given), incremental mapping; the model with the most registered frames is kept.
3. undistort: COLMAP's undistortion onto a pinhole camera (images and model).
4. write: the Nerfies layout the loader reads (stdr.data.nerfies): rgb/1x/<id>.png,
   camera/<id>.json, dataset.json (every `val_every`-th frame held out), metadata.json
   (time_id in milliseconds from the first registered frame, or the image's index for a folder;
   warp_id = appearance_id = rank),
   scene.json (centre and scale from the points and cameras, near/far), points.npy (the sparse
   points with track length >= 3 and reprojection error <= 2 px), colmap/sparse/0 (the pinhole
   model) and capture.json (settings, per-frame source and time, SfM statistics, timings, and
   the loader settings `stdr-train experiment=nerfies_<baseline> data.path=DIR` picks up).

The output folder is written under DIR.partial and renamed into place at the end: a failure
leaves no half-written dataset. pycolmap's API changed between 3.x and 4.x (docs/data.md); this
module is written against pycolmap 4.2 (the `capture` extra pins it).
"""
from __future__ import annotations

import json
import math
import shutil
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Optional

import cv2
import numpy as np

from ..errors import UserError
from .checks import check_intrinsics, check_pose

PYCOLMAP_VERSION = "4.2.1"  # the version this module is written and tested against (pyproject: extra `capture`)
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


def _progress(total, desc):
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
    if not cv2.imwrite(str(path), cv2.cvtColor(img, cv2.COLOR_RGB2BGR)):
        raise CaptureError(f"could not write {path}")


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
        bar = _progress(n, f"frames of {video.name} (every {stride})")

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
    bar = _progress(len(paths), f"images of {folder.name} (every {stride})")

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
def _pycolmap():
    try:
        import pycolmap
    except ImportError:
        raise CaptureError("camera poses need pycolmap: pip install 'stdr[capture]' "
                           f"(pins pycolmap=={PYCOLMAP_VERSION})") from None
    if not getattr(_pycolmap, "quiet", False):  # COLMAP's per-image INFO lines: warnings and errors only
        pycolmap.logging.minloglevel = 1
        _pycolmap.quiet = True
    major = int(pycolmap.__version__.split(".")[0])
    if major < 4:
        raise CaptureError(f"pycolmap {pycolmap.__version__} is installed; stdr-data capture is written for the "
                           f"4.x API (extract_features without camera_model, pairing options): "
                           f"pip install pycolmap=={PYCOLMAP_VERSION}")
    return pycolmap


def run_sfm(image_dir: Path, work: Path, names: list[str], cfg: CaptureConfig, log=print):
    """Features, matches and incremental mapping on the CPU; returns (the largest model, stats)."""
    pc = _pycolmap()
    db = work / "database.db"
    if db.exists():
        db.unlink()
    pc.set_random_seed(cfg.seed)
    stats: dict = {}
    t = time.perf_counter()
    reader = pc.ImageReaderOptions(camera_model=cfg.camera_model)
    pc.extract_features(db, image_dir, image_names=names, camera_mode=pc.CameraMode.SINGLE, reader_options=reader,
                        extraction_options=pc.FeatureExtractionOptions(num_threads=cfg.threads), device=pc.Device.cpu)
    stats["features_s"] = time.perf_counter() - t
    log(f"[capture] features: {len(names)} images, {stats['features_s']:.1f} s")
    matcher = cfg.matcher if cfg.matcher != "auto" else ("exhaustive" if len(names) <= cfg.exhaustive_max
                                                         else "sequential")
    t = time.perf_counter()
    mopt = pc.FeatureMatchingOptions(num_threads=cfg.threads)
    if matcher == "exhaustive":
        pc.match_exhaustive(db, matching_options=mopt, device=pc.Device.cpu)
    else:
        pairing = pc.SequentialPairingOptions(overlap=cfg.overlap, quadratic_overlap=True,
                                              loop_detection=cfg.vocab_tree is not None)
        if cfg.vocab_tree is not None:
            pairing.vocab_tree_path = str(cfg.vocab_tree)
        pc.match_sequential(db, matching_options=mopt, pairing_options=pairing, device=pc.Device.cpu)
    stats["matcher"] = matcher + (" + loop detection" if (matcher == "sequential" and cfg.vocab_tree) else "")
    stats["matching_s"] = time.perf_counter() - t
    log(f"[capture] matching ({stats['matcher']}): {stats['matching_s']:.1f} s")
    t = time.perf_counter()
    # mapping on one thread: COLMAP's multi-threaded mapping and bundle adjustment gave other
    # cameras from run to run on the same frames (92 or 100 registered; once a camera 60 degrees
    # off). On one thread, with the seed, three captures of the toy video agreed on every camera
    # they share within 0.25 % of the track's extent and 0.37 degrees (the features and matching,
    # on --threads threads, are not bit-identical; docs/data.md)
    opts = pc.IncrementalPipelineOptions(random_seed=cfg.seed, num_threads=1)
    (work / "sparse").mkdir(parents=True, exist_ok=True)
    bar = _progress(len(names), "mapping (registered frames)")
    models = pc.incremental_mapping(db, image_dir, work / "sparse", options=opts,
                                    next_image_callback=lambda: bar.update(1))
    bar.close()
    stats["mapping_s"] = time.perf_counter() - t
    if not models:
        raise CaptureError(f"SfM registered no frames of {len(names)} ({image_dir}): the frames share too few "
                           "features. Try: a capture that moves the camera slowly around the subject with "
                           "texture in view, more frames (--frames), --matcher exhaustive, less downscaling "
                           "(--max-size)")
    best = max(models, key=lambda k: models[k].num_reg_images())
    rec = models[best]
    stats.update(models=len(models), registered=rec.num_reg_images(), frames=len(names),
                 points=rec.num_points3D(), mean_reprojection_error_px=rec.compute_mean_reprojection_error(),
                 mean_track_length=rec.compute_mean_track_length())
    log(f"[capture] mapping: {stats['registered']}/{len(names)} frames registered in the largest of "
        f"{stats['models']} model(s), {stats['points']:,} points, reprojection error "
        f"{stats['mean_reprojection_error_px']:.2f} px, {stats['mapping_s']:.1f} s")
    return rec, work / "sparse" / str(best), stats


#: a registered frame is dropped when its camera disagrees with both neighbours along the video by
#: more than these: its viewing direction by TURN_DEG beyond the neighbours' own turn, or its centre
#: by JUMP times the larger of the neighbours' distance and the median step between frames
TURN_DEG, JUMP = 20.0, 3.0


def track_outliers(ids: list[str], centres: np.ndarray, forwards: np.ndarray) -> dict[str, str]:
    """Frames (in video order) whose registered camera disagrees with its neighbours': {id: why}.
    centres, forwards: [N, 3] camera centres and unit viewing directions. A camera that SfM placed
    wrongly sits off the smooth track of a hand-held video; its neighbours agree with each other."""
    n = len(ids)
    if n < 3:
        return {}
    steps = np.linalg.norm(np.diff(centres, axis=0), axis=1)
    med = float(np.median(steps)) if len(steps) else 0.0
    out = {}
    for i in range(n):
        nb = [j for j in (i - 1, i + 1) if 0 <= j < n]
        if len(nb) == 2:
            a, b = nb
            mid_dir = forwards[a] + forwards[b]
            mid_dir = mid_dir / max(np.linalg.norm(mid_dir), 1e-12)
            own_turn = _angle(forwards[a], forwards[b])
            turn = _angle(forwards[i], mid_dir)
            jump = float(np.linalg.norm(centres[i] - 0.5 * (centres[a] + centres[b])))
            scale = max(float(np.linalg.norm(centres[b] - centres[a])), med)
        else:  # the first or last frame: against its one neighbour and the one after it
            a = nb[0]
            c = a + (a - i)
            own_turn = _angle(forwards[a], forwards[c]) if 0 <= c < n else 0.0
            turn = _angle(forwards[i], forwards[a])
            jump = float(np.linalg.norm(centres[i] - centres[a]))
            scale = max(float(np.linalg.norm(centres[c] - centres[a])) if 0 <= c < n else 0.0, med)
        if turn > TURN_DEG + own_turn:
            out[ids[i]] = f"looks {turn:.0f} degrees away from its neighbours' direction"
        elif scale > 0 and jump > JUMP * scale:
            out[ids[i]] = f"sits {jump / scale:.1f}x the neighbours' spacing off their track"
    return out


def _angle(u: np.ndarray, v: np.ndarray) -> float:
    c = float(np.dot(u, v) / max(np.linalg.norm(u) * np.linalg.norm(v), 1e-12))
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def registered_track(rec, records: list[FrameRecord]) -> tuple[list[str], np.ndarray, np.ndarray]:
    """(ids in video order, camera centres [N, 3], viewing directions [N, 3]) of the registered frames."""
    by_id = {img.name[:-4]: img for img in rec.images.values() if img.has_pose}
    ids = [r.id for r in sorted(records, key=lambda r: r.source_index) if r.id in by_id]
    cs, fs = [], []
    for i in ids:
        pose = by_id[i].cam_from_world()
        R = np.asarray(pose.rotation.matrix(), dtype=np.float64)
        t = np.asarray(pose.translation, dtype=np.float64)
        cs.append(-R.T @ t)
        fs.append(R[2])  # the camera's +z axis in the world
    return ids, np.asarray(cs).reshape(-1, 3), np.asarray(fs).reshape(-1, 3)


def _ranges(ids: list[str]) -> str:
    return ", ".join(ids[:12]) + (f" ... ({len(ids)} in all)" if len(ids) > 12 else "")


def check_registered(records: list[FrameRecord], registered: set[str], cfg: CaptureConfig) -> None:
    missing = [r.id for r in records if r.id not in registered]
    share = len(registered) / len(records)
    if share < cfg.min_registered:
        raise CaptureError(
            f"SfM registered {len(registered)} of {len(records)} frames ({share:.0%} < --min-registered "
            f"{cfg.min_registered:.0%}); not registered: {_ranges(missing)}. Try: --matcher exhaustive, more "
            "frames (--frames) so neighbours overlap more, --select sharpest against motion blur, less "
            "downscaling (--max-size), or trim the part of the video where the camera turns fast or views "
            "a blank wall; --min-registered lowers the bar")


# ----------------------------------------------------------------------------- writing
def _scene_box(points: np.ndarray, centres: np.ndarray):
    """Nerfies' normalization: the box of the points (1st..99th percentile) and the cameras;
    centre = its middle, scale = 1 / its diagonal."""
    pts = points if len(points) else centres
    lo = np.minimum(np.percentile(pts, 1, axis=0), centres.min(0))
    hi = np.maximum(np.percentile(pts, 99, axis=0), centres.max(0))
    centre = (lo + hi) / 2
    diag = float(np.linalg.norm(hi - lo))
    if not diag > 0:
        raise CaptureError("the cameras and points span no volume (every camera at one point?)")
    return centre, 1.0 / diag, lo, hi


def _near_far(points: np.ndarray, Rs: np.ndarray, ts: np.ndarray):
    depth = np.einsum("nij,pj->npi", Rs, points)[..., 2] + ts[:, None, 2]
    d = depth[depth > 0]
    if len(d) == 0:
        return None, None
    return float(np.quantile(d, 0.001) * 0.8), float(np.quantile(d, 0.999) * 1.2)


def write_dataset(out: Path, records: list[FrameRecord], und_images: Path, und_model_dir: Path,
                  cfg: CaptureConfig, source: Path, kind: str, stats: dict, timings: dict,
                  keep: Optional[set] = None) -> dict:
    """The dataset folder from the undistorted model; `keep`: the frame ids to write (default: every
    registered one)."""
    pc = _pycolmap()
    rec = pc.Reconstruction(str(und_model_dir))
    by_name = {img.name: img for img in rec.images.values() if img.has_pose
               and (keep is None or img.name[:-4] in keep)}
    kept = [r for r in records if f"{r.id}.png" in by_name]
    (out / "rgb" / "1x").mkdir(parents=True)
    (out / "camera").mkdir()
    Rs, ts, centres = [], [], []
    for r in kept:
        img = by_name[f"{r.id}.png"]
        cam = rec.cameras[img.camera_id]
        if cam.model_name not in ("PINHOLE", "SIMPLE_PINHOLE"):
            raise CaptureError(f"undistortion left a {cam.model_name} camera (expected PINHOLE)")
        pose = img.cam_from_world()
        R = np.asarray(pose.rotation.matrix(), dtype=np.float64)
        t = np.asarray(pose.translation, dtype=np.float64)
        c = -R.T @ t
        where = f"{und_model_dir}: image {r.id}.png"
        check_pose(R, c, where, "COLMAP pose")  # what the loader will check, named here where it came from
        check_intrinsics(float(cam.focal_length_x), float(cam.focal_length_y), float(cam.principal_point_x),
                         float(cam.principal_point_y), int(cam.width), int(cam.height), where)
        Rs.append(R)
        ts.append(t)
        centres.append(c)
        fx, fy = float(cam.focal_length_x), float(cam.focal_length_y)
        camj = {"orientation": R.tolist(), "position": c.tolist(), "focal_length": fx,
                "principal_point": [float(cam.principal_point_x), float(cam.principal_point_y)],
                "skew": 0.0, "pixel_aspect_ratio": fy / fx, "radial_distortion": [0.0, 0.0, 0.0],
                "tangential_distortion": [0.0, 0.0], "image_size": [int(cam.width), int(cam.height)]}
        (out / "camera" / f"{r.id}.json").write_text(json.dumps(camj, indent=2))
        shutil.copy2(und_images / f"{r.id}.png", out / "rgb" / "1x" / f"{r.id}.png")
    Rs, ts, centres = np.stack(Rs), np.stack(ts), np.stack(centres)
    pts = [p for p in rec.points3D.values() if p.track.length() >= 3 and p.error <= 2.0]
    xyz = np.array([p.xyz for p in pts], dtype=np.float64).reshape(-1, 3)
    np.save(out / "points.npy", xyz)
    centre, scale, lo, hi = _scene_box(xyz, centres)
    near, far = _near_far(xyz, Rs, ts) if len(xyz) else (None, None)
    (out / "scene.json").write_text(json.dumps({
        "scale": scale, "center": centre.tolist(), "bbox": [lo.tolist(), hi.tolist()],
        "near": None if near is None else near * scale, "far": None if far is None else far * scale}, indent=2))
    ids = [r.id for r in kept]
    k = cfg.val_every
    val = [i for n, i in enumerate(ids) if n % k == k // 2]
    train = [i for i in ids if i not in set(val)]
    (out / "dataset.json").write_text(json.dumps({"count": len(ids), "num_exemplars": len(train), "ids": ids,
                                                  "train_ids": train, "val_ids": val}, indent=2))
    t_first = kept[0].time_sec
    meta = {r.id: {"time_id": int(round((r.time_sec - t_first) * 1000)) if kind == "video"
                   else int(r.time_sec - t_first),
                   "warp_id": n, "appearance_id": n, "camera_id": 0} for n, r in enumerate(kept)}
    if max(m["time_id"] for m in meta.values()) == 0:
        raise CaptureError("every registered frame has the same time; a dynamic scene needs more than one")
    (out / "metadata.json").write_text(json.dumps(meta, indent=2))
    (out / "colmap" / "sparse" / "0").mkdir(parents=True)
    rec.write(str(out / "colmap" / "sparse" / "0"))
    for r in records:
        r.registered = r.id in by_name
    info = {
        "format": 1, "source": str(source), "kind": kind, "pycolmap": pc.__version__, "settings": asdict(cfg),
        "split_rule": f"every {k}-th registered frame by rank (offset {k // 2}) is held out (val_ids)",
        "time_rule": ("time_id = milliseconds from the first registered frame (presentation times)"
                      if kind == "video" else "time_id = index of the image in name order, from the first "
                      "registered one"),
        "loader": {"split_mode": "ids", "image_scale": 1},
        "sfm": stats, "timings_s": timings, "num_points": int(len(xyz)),
        "frames": [asdict(r) for r in records],
    }
    (out / "capture.json").write_text(json.dumps(info, indent=2))
    return info


def capture(source: str | Path, out: str | Path, cfg: Optional[CaptureConfig] = None, *,
            overwrite: bool = False, keep_work: bool = False, log=print) -> dict:
    """Run every stage; returns the capture.json content. See the module docstring."""
    cfg = cfg or CaptureConfig()
    cfg.check()
    source, out = Path(source), Path(out)
    if not source.exists():
        raise CaptureError(f"{source}: not found (a video file or a folder of images)")
    kind = "images" if source.is_dir() else "video"
    if kind == "video" and source.suffix.lower() not in VIDEO_SUFFIXES:
        raise CaptureError(f"{source}: not a video ({', '.join(VIDEO_SUFFIXES)}) nor a folder of images")
    if out.exists() and not overwrite:
        raise CaptureError(f"{out} exists already; remove it, choose another --out, or pass --overwrite")
    _pycolmap()  # fail before the slow decoding
    part = out.with_name(out.name + ".partial")
    shutil.rmtree(part, ignore_errors=True)
    work = part / "work"
    (work / "images").mkdir(parents=True)
    timings: dict = {}
    t = time.perf_counter()
    records = (video_frames if kind == "video" else folder_frames)(source, work / "images", cfg)
    timings["frames"] = time.perf_counter() - t
    log(f"[capture] frames: {len(records)} kept, {timings['frames']:.1f} s")
    names = [f"{r.id}.png" for r in records]
    t = time.perf_counter()
    rec, model_dir, stats = run_sfm(work / "images", work, names, cfg, log)
    timings["sfm"] = time.perf_counter() - t
    registered = {img.name[:-4] for img in rec.images.values() if img.has_pose}
    dropped = track_outliers(*registered_track(rec, records))
    for fid, why in dropped.items():
        log(f"[capture] frame {fid} dropped: its camera {why} (a pose SfM got wrong)")
    registered -= set(dropped)
    stats["dropped"] = dropped
    check_registered(records, registered, cfg)
    if len(registered) < len(records):
        log(f"[capture] {len(records) - len(registered)} frame(s) not registered and left out: "
            f"{_ranges([r.id for r in records if r.id not in registered])}")
    t = time.perf_counter()
    pc = _pycolmap()
    und = work / "undistorted"
    pc.undistort_images(str(und), str(model_dir), str(work / "images"),
                        image_names=sorted(f"{i}.png" for i in registered))
    timings["undistort"] = time.perf_counter() - t
    log(f"[capture] undistort: {timings['undistort']:.1f} s")
    t = time.perf_counter()
    info = write_dataset(part, records, und / "images", und / "sparse", cfg, source, kind, stats, timings,
                         keep=registered)
    timings["write"] = time.perf_counter() - t
    info["timings_s"] = timings
    (part / "capture.json").write_text(json.dumps(info, indent=2))
    if keep_work:
        work.rename(part / "colmap" / "work")
    else:
        shutil.rmtree(work)
    if out.exists():
        shutil.rmtree(out)
    part.replace(out)
    log(f"[capture] done: {out} ({stats['registered']} frames, {info['num_points']:,} points); train with "
        f"stdr-train experiment=nerfies_deform data.path={out}")
    return info


# ----------------------------------------------------------------------------- checking against known cameras
def align_similarity(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity (s, R, t) with dst ~ s R src + t (Umeyama 1991); src, dst [N, 3], N >= 3."""
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) < 3:
        raise ValueError(f"align_similarity: two [N, 3] arrays with N >= 3, got {src.shape} and {dst.shape}")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    cov = b.T @ a / len(src)
    U, S, Vt = np.linalg.svd(cov)
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1
    R = U @ D @ Vt
    var = (a ** 2).sum() / len(src)
    s = float(np.trace(np.diag(S) @ D) / var)
    return s, R, mu_d - s * R @ mu_s


def camera_rays(cam: dict, points=((0.5, 0.5), (0.25, 0.25), (0.75, 0.25), (0.25, 0.75), (0.75, 0.75))) -> np.ndarray:
    """World directions [P, 3] of the rays through image points given as fractions of the image
    size, for a Nerfies camera file's content (its intrinsics and lens distortion applied)."""
    R = np.asarray(cam["orientation"], dtype=np.float64)
    f = float(cam["focal_length"])
    fy = f * float(cam.get("pixel_aspect_ratio", 1.0))
    cx, cy = cam["principal_point"]
    W, H = cam["image_size"]
    k = (list(cam.get("radial_distortion", [0.0, 0.0, 0.0])) + [0.0, 0.0])[:3]
    p = list(cam.get("tangential_distortion", [0.0, 0.0]))
    K = np.array([[f, float(cam.get("skew", 0.0)), cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    px = np.array([[[u * W, v * H]] for u, v in points], dtype=np.float64)
    xy = cv2.undistortPoints(px, K, np.array([k[0], k[1], p[0], p[1], k[2]]))[:, 0]
    d = np.concatenate([xy, np.ones((len(xy), 1))], 1) @ R  # R^T x for each row
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def ray_errors(cams_est: list[dict], cams_ref: list[dict]) -> dict:
    """Camera poses of an estimate against a reference (Nerfies camera files' content, matched
    by position), after the similarity that best maps the estimated centres onto the
    reference's. Centres: distance in units of the reference trajectory's extent (the largest
    distance between two reference centres). Orientation: the angle between the two world rays
    through the same image points (centre and quarter points), each camera with its own
    intrinsics and distortion, so that two solutions that trade a principal-point offset
    against a rotation (which look alike in the image) are compared by what they see."""
    c_est = np.stack([np.asarray(c["position"], np.float64) for c in cams_est])
    c_ref = np.stack([np.asarray(c["position"], np.float64) for c in cams_ref])
    s, A, t = align_similarity(c_est, c_ref)
    c_al = (s * (A @ c_est.T)).T + t
    extent = float(max(np.linalg.norm(c_ref[:, None] - c_ref[None], axis=-1).max(), 1e-12))
    pos = np.linalg.norm(c_al - c_ref, axis=1) / extent
    ang = np.array([np.degrees(np.arccos(np.clip(np.sum((camera_rays(a) @ A.T) * camera_rays(b), 1), -1, 1))).max()
                    for a, b in zip(cams_est, cams_ref)])
    return {"n": int(len(pos)), "scale": s, "extent": extent,
            "position_median": float(np.median(pos)), "position_max": float(pos.max()),
            "ray_median_deg": float(np.median(ang)), "ray_max_deg": float(ang.max())}
