"""Camera paths in nerfstudio's camera_path.json format (read by `stdr-render --path`, written by
the viewer's "camera path" panel and by `write_camera_path`).

The format (nerfstudio viewer's render panel, read by ns-render):
  {"camera_type": "perspective", "render_width": W, "render_height": H, "fps": F, "seconds": S,
   "camera_path": [{"camera_to_world": [16 floats, row-major 4x4], "fov": vertical degrees,
                    "aspect": W / H, "render_time": t in [0, 1]}, ...], "keyframes": [...], ...}

Conventions, as nerfstudio reads the file: `camera_to_world` has OpenGL camera axes (x right, y
up, z backwards); `fov` is the vertical field of view, fx = fy = (H / 2) / tan(fov / 2), the
principal point is the image centre; the per-entry `aspect` is ignored (render_width/height
win); `render_time` is used only when every entry has it. Poses are in the run's world frame,
which is the frame the viewer shows (a Nerfies scene's is normalized by its scene.json; a path
drawn in nerfstudio's own viewer lives in nerfstudio's frame and would need its
dataparser_transforms.json undone first, which stdr does not do).
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from ..cameras import Camera
from ..data.colmap import qvec_to_rotmat
from ..io.files import make_folder, write_atomic
from .core import _matrix_to_quat

GL_FROM_CV = np.diag([1.0, -1.0, -1.0])  # OpenCV camera axes (x right, y down, z forward) <-> OpenGL's


@dataclass
class CameraPath:
    cameras: list[Camera]
    times: list[float]
    fps: float


def _float(v, where: str) -> float:
    try:
        f = float(v)
    except (TypeError, ValueError):
        raise ValueError(f"{where}: expected a number, got {v!r}") from None
    if not math.isfinite(f):
        raise ValueError(f"{where}: not a finite number ({v!r})")
    return f


def camera_from_c2w_gl(c2w: np.ndarray, fov_y_deg: float, width: int, height: int) -> Camera:
    """Our camera (world-to-camera R, t in OpenCV axes) from an OpenGL camera-to-world matrix."""
    c2w = np.asarray(c2w, dtype=np.float64)
    R_c2w = c2w[:3, :3] @ GL_FROM_CV
    R = R_c2w.T
    t = -R @ c2w[:3, 3]
    f = (height / 2.0) / math.tan(math.radians(fov_y_deg) / 2.0)
    return Camera(R=torch.tensor(R, dtype=torch.float32), t=torch.tensor(t, dtype=torch.float32), fx=f, fy=f,
                  cx=width / 2.0, cy=height / 2.0, width=int(width), height=int(height))


def c2w_gl_from_camera(cam: Camera) -> np.ndarray:
    """The OpenGL camera-to-world 4x4 of our camera."""
    R = cam.R.detach().double().cpu().numpy()
    t = cam.t.detach().double().cpu().numpy()
    out = np.eye(4)
    out[:3, :3] = R.T @ GL_FROM_CV
    out[:3, 3] = -R.T @ t
    return out


def fov_y_deg(cam: Camera) -> float:
    return math.degrees(2.0 * math.atan((cam.height / 2.0) / cam.fy))


def read_camera_path(path: str | Path, width: Optional[int] = None) -> CameraPath:
    """The cameras and times of a camera_path.json. `width` rescales the render size (aspect kept).
    Entries without `render_time` (any of them): times run evenly from 0 to 1 along the path."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"camera path {path} not found")
    try:
        d = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}: malformed JSON at line {e.lineno} column {e.colno}: {e.msg}") from None
    if not isinstance(d, dict) or not isinstance(d.get("camera_path"), list) or not d["camera_path"]:
        raise ValueError(f"{path}: expected nerfstudio's camera path format with a non-empty 'camera_path' list "
                         "(entries with camera_to_world, fov, render_time)")
    ctype = d.get("camera_type", "perspective")
    if ctype != "perspective":
        raise ValueError(f"{path}: camera_type {ctype!r}; stdr renders perspective cameras only")
    for k in ("render_width", "render_height"):
        if k not in d:
            raise ValueError(f"{path}: missing key {k!r} (the image size of the path's frames)")
    W, H = int(_float(d["render_width"], f"{path}: render_width")), int(_float(d["render_height"], f"{path}: render_height"))
    if W < 1 or H < 1:
        raise ValueError(f"{path}: render_width and render_height must be positive, got {W} x {H}")
    if width is not None:
        W, H = int(width), max(1, int(round(width * H / W)))
    entries = d["camera_path"]
    cams = []
    for i, e in enumerate(entries):
        where = f"{path}: camera_path[{i}]"
        if not isinstance(e, dict) or "camera_to_world" not in e or "fov" not in e:
            raise ValueError(f"{where}: needs camera_to_world (16 numbers) and fov (vertical degrees)")
        m = np.asarray([_float(v, where + ".camera_to_world") for v in np.ravel(e["camera_to_world"])])
        if m.size not in (12, 16):
            raise ValueError(f"{where}: camera_to_world has {m.size} numbers; expected 16 (row-major 4x4)")
        m = np.vstack([m.reshape(-1, 4)[:3], [0.0, 0.0, 0.0, 1.0]])
        Rm = m[:3, :3]
        if abs(np.linalg.det(Rm) - 1.0) > 1e-3 or np.abs(Rm.T @ Rm - np.eye(3)).max() > 1e-3:
            raise ValueError(f"{where}: the rotation part of camera_to_world is not a rotation "
                             "(scaled or mirrored?); stdr expects poses in the run's world frame")
        fov = _float(e["fov"], where + ".fov")
        if not 0.0 < fov < 180.0:
            raise ValueError(f"{where}: fov {fov} is not a vertical field of view in degrees (0, 180)")
        cams.append(camera_from_c2w_gl(m, fov, W, H))
    if all(isinstance(e, dict) and "render_time" in e for e in entries):
        times = [_float(e["render_time"], f"{path}: camera_path[{i}].render_time") for i, e in enumerate(entries)]
        bad = [t for t in times if not 0.0 <= t <= 1.0]
        if bad:
            raise ValueError(f"{path}: render_time {bad[0]} outside [0, 1]")
    else:
        times = list(np.linspace(0.0, 1.0, len(entries))) if len(entries) > 1 else [0.0]
    fps = d.get("fps")
    if fps is None and d.get("seconds"):
        fps = len(entries) / _float(d["seconds"], f"{path}: seconds")
    fps = _float(fps if fps is not None else 30.0, f"{path}: fps")
    if fps <= 0:
        raise ValueError(f"{path}: fps must be positive, got {fps}")
    return CameraPath(cameras=cams, times=[float(t) for t in times], fps=fps)


def camera_path_dict(cameras: list[Camera], times: list[float], fps: float = 30.0,
                     keyframes: Optional[list[tuple[Camera, float]]] = None) -> dict:
    """nerfstudio's camera_path.json content for `cameras` (all of one size) at `times`."""
    if not cameras or len(cameras) != len(times):
        raise ValueError("camera_path_dict: one time per camera, at least one camera")
    W, H = cameras[0].width, cameras[0].height
    if any((c.width, c.height) != (W, H) for c in cameras):
        raise ValueError("camera_path_dict: every camera of a path has the same image size")

    def entry(c: Camera, t: float) -> dict:
        return {"camera_to_world": c2w_gl_from_camera(c).ravel().tolist(), "fov": fov_y_deg(c), "aspect": W / H,
                "render_time": float(t)}
    kf = keyframes if keyframes is not None else []
    return {
        "default_fov": fov_y_deg(cameras[0]), "default_time": float(times[0]), "default_transition_sec": 2.0,
        "keyframes": [{"matrix": c2w_gl_from_camera(c).ravel().tolist(), "fov": fov_y_deg(c), "aspect": W / H,
                       "override_transition_enabled": False, "override_transition_sec": None,
                       "render_time": float(t), "override_time_enabled": True} for c, t in kf],
        "camera_type": "perspective", "render_height": int(H), "render_width": int(W), "fps": float(fps),
        "seconds": len(cameras) / float(fps), "is_cycle": False, "smoothness_value": 0.0,
        "camera_path": [entry(c, t) for c, t in zip(cameras, times)],
    }


def write_camera_path(path: str | Path, cameras: list[Camera], times: list[float], fps: float = 30.0,
                      keyframes: Optional[list[tuple[Camera, float]]] = None) -> Path:
    path = Path(path)
    make_folder(path.parent)
    write_atomic(path, json.dumps(camera_path_dict(cameras, times, fps, keyframes), indent=1), "camera_path")
    return path


def _slerp(q0: np.ndarray, q1: np.ndarray, u: float) -> np.ndarray:
    d = float(np.dot(q0, q1))
    if d < 0:
        q1, d = -q1, -d
    if d > 0.9995:
        q = q0 + u * (q1 - q0)
        return q / np.linalg.norm(q)
    th = math.acos(d)
    return (math.sin((1 - u) * th) * q0 + math.sin(u * th) * q1) / math.sin(th)


def interpolate(keyframes: list[tuple[Camera, float]], frames: int) -> tuple[list[Camera], list[float]]:
    """`frames` cameras and times along keyframes (camera, time): centres, field of view and time
    linear, orientation by spherical interpolation, evenly in keyframe index."""
    if len(keyframes) < 2:
        raise ValueError("a camera path needs at least two keyframes")
    if frames < 2:
        raise ValueError(f"frames {frames}: at least 2")
    W, H = keyframes[0][0].width, keyframes[0][0].height
    qs = [_matrix_to_quat(c.R.detach().double().cpu().numpy()) for c, _ in keyframes]
    cs = [c.center.detach().double().cpu().numpy() for c, _ in keyframes]
    fovs = [fov_y_deg(c) for c, _ in keyframes]
    cams, times = [], []
    for s in np.linspace(0.0, len(keyframes) - 1, frames):
        i = min(int(s), len(keyframes) - 2)
        u = float(s - i)
        R = qvec_to_rotmat(_slerp(qs[i], qs[i + 1], u))
        c = (1 - u) * cs[i] + u * cs[i + 1]
        fov = (1 - u) * fovs[i] + u * fovs[i + 1]
        f = (H / 2.0) / math.tan(math.radians(fov) / 2.0)
        cams.append(Camera(R=torch.tensor(R, dtype=torch.float32), t=torch.tensor(-R @ c, dtype=torch.float32),
                           fx=f, fy=f, cx=W / 2.0, cy=H / 2.0, width=W, height=H))
        times.append((1 - u) * keyframes[i][1] + u * keyframes[i + 1][1])
    return cams, times
