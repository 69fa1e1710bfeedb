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
import shutil
import time
from dataclasses import asdict
from pathlib import Path
from typing import Optional

import numpy as np

from .capture_input import (VIDEO_SUFFIXES, CaptureConfig, CaptureError, FrameRecord, progress_bar, folder_frames,
                            video_frames)
from .checks import check_intrinsics, check_pose
from ..errors import IO_FIXES, IOFault, io_fault
from ..io.files import failpoint

PYCOLMAP_VERSION = "4.2.1"  # the version this module is written and tested against (pyproject: extra `capture`)
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
    bar = progress_bar(len(names), "mapping (registered frames)")
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
    try:
        return _capture_into(part, source, out, kind, cfg, keep_work, log)
    except BaseException as e:
        if keep_work:  # kept for a look at what the stages left
            log(f"[capture] failed; the stages' files are kept in {part} (--keep-work)")
        else:  # a failed capture leaves nothing behind: neither OUT nor OUT.partial
            shutil.rmtree(part, ignore_errors=True)
        if isinstance(e, OSError) and not isinstance(e, IOFault) and e.errno in IO_FIXES:
            raise io_fault(e, e.filename if e.filename is not None else out) from None  # one line naming the path
        raise


def _capture_into(part: Path, source: Path, out: Path, kind: str, cfg: CaptureConfig, keep_work: bool, log) -> dict:
    """capture's stages, written under `part` and renamed to `out` at the end."""
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
    failpoint("capture", part / "capture.json")
    if out.exists():
        shutil.rmtree(out)
    part.replace(out)
    log(f"[capture] done: {out} ({stats['registered']} frames, {info['num_points']:,} points); train with "
        f"stdr-train experiment=nerfies_deform data.path={out}")
    return info


# ----------------------------------------------------------------------------- checking against known cameras
