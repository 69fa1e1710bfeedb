"""What the viewer and the videos render, without any web code: a run opened for viewing, camera
conversions to and from viser's convention, and the views (RGB, depth, alpha, STDR's mask at t,
the motion branch's static/dynamic split) as uint8 images.

Every view renders through `DynamicGaussians.render` / `render_gaussians`, the same path as
stdr-eval, on the run's device with its configured backend.
"""
from __future__ import annotations

import sys

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from ..errors import BadInput, MissingInput
from ..cameras import Camera
from ..data.colmap import qvec_to_rotmat
from ..data.types import Frame
from ..data.load import load_run_scene
from ..store import load_config
from ..device import resolve_device
from ..compression.file import compact_source_note
from ..model import model_from_checkpoint
from ..io.checkpoint import load_checkpoint, CKPT
from ..render.sh import rgb_to_sh
from ..plugins.stdr.mask import mask_at
from ..plugins.stdr.mask import COND_KEY, MASK_KEY

VIEWS = ("rgb", "depth", "alpha", "mask", "dynamic")
SPLITS = ("train", "val", "test")


@dataclass
class ViewRun:
    """A trained run opened for viewing: its model (eval mode) and, when the data is reachable,
    the frames of each split (cameras, times, ground truth)."""

    run_dir: Path
    cfg: object
    model: object
    frames: dict[str, list[Frame]] = field(default_factory=dict)
    data_note: Optional[str] = None  # why there are no dataset cameras, when there are none

    @property
    def has_stdr(self) -> bool:
        return self.model.plugin("stdr") is not None

    def cameras(self) -> list[tuple[str, Frame]]:
        """(label, frame) of every dataset camera, test first (the viewer starts at the first)."""
        out = []
        for s in ("test", "val", "train"):
            out += [(f"{s} {i}: t={f.time:.3f}", f) for i, f in enumerate(self.frames.get(s, []))]
        return out

    def default_camera(self, width: Optional[int] = None) -> tuple[Camera, float]:
        """The first test camera (else val, train) and its time; without data, a camera looking at
        the Gaussians' centroid from 3 x their spread along -z."""
        cams = self.cameras()
        if cams:
            f = cams[0][1]
            cam = f.camera if width is None else scale_to_width(f.camera, width)
            return cam, f.time
        means = self.model.params["means"].detach().float().cpu()
        c = means.mean(0)
        r = float((means - c).norm(dim=-1).quantile(0.9)) or 1.0
        w = width or 400
        pos = c.numpy() - np.array([0.0, 0.0, 3.0 * r])
        return camera_from_viser(np.array([1.0, 0.0, 0.0, 0.0]), pos, np.deg2rad(50.0), w, w), 0.5


def open_run(run_dir: str | Path, device: Optional[str] = None, base: Optional[str] = None,
             splits=SPLITS, model_file: Optional[str | Path] = None) -> ViewRun:
    """The model of a run folder (config.yaml + checkpoints/last.pt, or `model_file`: e.g. the
    run's compact model file model.stdrc) on `device` (default: the run's own), and the frames of
    `splits` when its data can be read; errors name what is missing."""

    rd = Path(run_dir)
    if not rd.is_dir():
        raise MissingInput(f"{rd}: no such folder (give a run directory: the folder with config.yaml "
                                "and checkpoints/last.pt that stdr-train wrote)")
    ckpt = Path(model_file) if model_file is not None else rd / CKPT
    if model_file is not None and not ckpt.is_file():
        raise MissingInput(f"--model {ckpt}: no such file (a compact model file is written by stdr-tool pack RUN)")
    missing = [p for p in ("config.yaml", CKPT) if not (rd / p).is_file() and not (p == CKPT and model_file)]
    if missing:
        raise MissingInput(f"{rd} is not a trained run: {', '.join(missing)} missing (a run directory of "
                                "stdr-train holds config.yaml and checkpoints/last.pt)")
    cfg = load_config(rd / "config.yaml")
    if device is not None:
        cfg.device = device
    dev = resolve_device(cfg.device)
    ck = load_checkpoint(ckpt)
    model = model_from_checkpoint(ck, dev, cfg, path=str(ckpt))
    note = compact_source_note(ckpt) if model_file is not None else ""
    if note:
        print(f"[stdr] {note}", file=sys.stderr, flush=True)
    model.eval()
    run = ViewRun(rd, cfg, model)
    try:
        scene = load_run_scene(rd, cfg, tuple(splits), base=base, seed=cfg.seed)
        run.frames = {s: v for s, v in scene.splits.items() if v}
    except (FileNotFoundError, ValueError, KeyError, OSError) as e:
        run.data_note = f"the run's data could not be read ({e}); no dataset cameras"
    return run


# ------------------------------------------------------------------ cameras
def _matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """wxyz of a rotation matrix (Shepperd's method, w >= 0)."""
    R = np.asarray(R, dtype=np.float64)
    tr = np.trace(R)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + R[i, i] - R[j, j] - R[k, k])
        q = [0.0] * 4
        q[0] = (R[k, j] - R[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (R[j, i] + R[i, j]) / s
        q[1 + k] = (R[k, i] + R[i, k]) / s
    q = np.array(q)
    return q if q[0] >= 0 else -q


def camera_from_viser(wxyz, position, fov_y: float, width: int, height: int) -> Camera:
    """Our world-to-camera pinhole from viser's camera: orientation wxyz = R_world_camera,
    position = the camera centre, vertical field of view (radians), OpenCV axes in both; the
    principal point at the image centre, square pixels."""
    Rwc = qvec_to_rotmat(np.asarray(wxyz))
    R = Rwc.T
    t = -R @ np.asarray(position, dtype=np.float64)
    f = 0.5 * height / np.tan(0.5 * fov_y)
    return Camera(R=torch.tensor(R, dtype=torch.float32), t=torch.tensor(t, dtype=torch.float32),
                  fx=float(f), fy=float(f), cx=0.5 * width, cy=0.5 * height, width=int(width), height=int(height))


def camera_to_viser(cam: Camera) -> tuple[np.ndarray, np.ndarray, float]:
    """(wxyz, position, vertical fov in radians) of a camera, for viser (the inverse of
    camera_from_viser for a centred principal point and square pixels)."""
    R = cam.R.detach().double().cpu().numpy()
    return _matrix_to_quat(R.T), cam.center.detach().double().cpu().numpy(), float(2 * np.arctan(0.5 * cam.height / cam.fy))


def look_at_point(run: ViewRun, cam: Camera) -> np.ndarray:
    """The point `cam` looks at, at the depth of the Gaussians' centroid along its axis [3]."""
    R_wc = cam.R.detach().double().cpu().numpy().T
    c = cam.center.detach().double().cpu().numpy()
    centroid = run.model.params["means"].detach().double().mean(0).cpu().numpy()
    return c + max(float((centroid - c) @ R_wc[:, 2]), 1e-3) * R_wc[:, 2]


def scale_to_width(cam: Camera, width: int) -> Camera:
    """The camera for an image `width` pixels wide (aspect kept; intrinsics scale with it)."""
    return cam if width == cam.width else cam.scaled(width / cam.width)


def with_size(cam: Camera, width: int, height: int) -> Camera:
    """The same pose and vertical field of view at another image size (viser's canvas)."""
    s = height / cam.height
    return replace(cam, fx=cam.fx * s, fy=cam.fy * s, cx=0.5 * width, cy=0.5 * height, width=int(width),
                   height=int(height))


# ------------------------------------------------------------------ views
def _colormap(x: torch.Tensor, name: str = "turbo") -> torch.Tensor:
    """[..., 3] colours in [0, 1] of values x in [0, 1] (matplotlib's colormap, 256 entries)."""
    import matplotlib
    lut = torch.tensor(matplotlib.colormaps[name](np.linspace(0, 1, 256))[:, :3], dtype=torch.float32,
                       device=x.device)
    return lut[(x.clamp(0, 1) * 255).round().long()]


def to_uint8(img: torch.Tensor) -> np.ndarray:
    """[H, W, 3] float in [0, 1] -> uint8 numpy (round to nearest)."""
    return (img.detach().clamp(0, 1) * 255.0 + 0.5).to(torch.uint8).cpu().numpy()


def _recoloured(model, t: float, values: torch.Tensor, camera: Camera):
    """Every Gaussian at time t with its canonical opacity (the mask not applied, so switched-off
    Gaussians stay visible) and the colour of `values` [N] in [0, 1] (turbo)."""
    g, _ = model.deformed_rows(t, cull=False)
    n = g.means.shape[0]
    sh = torch.zeros_like(g.sh)
    sh[:, 0] = rgb_to_sh(_colormap(values.reshape(n).float()))
    g = g._replace(opacities=torch.sigmoid(model.params["opacities"].detach()).reshape(n), sh=sh)
    return model.render_gaussians(g, camera)


@torch.no_grad()
def render_view(model, camera: Camera, t: float, view: str = "rgb") -> np.ndarray:
    """uint8 [H, W, 3]: rgb (what stdr-eval renders), depth (expected depth / alpha, turbo, near
    = red... far = blue, empty pixels black), alpha (accumulated opacity, grey), mask (STDR: each
    Gaussian coloured by its mask value at t, blue 0 ... red 1) or dynamic (STDR after the freeze:
    each Gaussian coloured by its motion-branch probability d_i, blue static ... red moving)."""
    if view not in VIEWS:
        raise BadInput(f"view {view!r} is not one of {VIEWS}")
    if view in ("rgb", "depth", "alpha"):
        out = model.render(camera, t)
        if view == "rgb":
            return to_uint8(out.image)
        if view == "alpha":
            return to_uint8(out.alpha[..., None].expand(-1, -1, 3))
        a = out.alpha
        d = out.depth / a.clamp_min(1e-6)
        hit = a > 0.05
        if hit.any():
            lo, hi = torch.quantile(d[hit].float(), torch.tensor([0.02, 0.98], device=d.device))
            x = 1.0 - (d - lo) / (hi - lo).clamp_min(1e-6)
        else:
            x = torch.zeros_like(d)
        img = _colormap(x) * hit[..., None]
        return to_uint8(img)
    stdr = model.plugin("stdr")
    if stdr is None:
        raise BadInput(f"view {view!r} needs an STDR run (stdr.enabled=true); this run has no STDR plug-in")
    params = model.params
    if view == "mask":
        if MASK_KEY not in params:
            if COND_KEY in params:  # a compact file with stdr_mask: derived keeps the field's output only
                raise BadInput("view 'mask': this compact file stores the separated field's output in place of "
                                 "STDR's mask (stdr_mask: derived); view the run's checkpoint for the mask, or "
                                 "write the file with the mask (stdr-tool pack RUN --codec stdr_mask=q8)")
            raise BadInput("view 'mask': this STDR run has no mask (stdr.mask=false)")
        return to_uint8(_recoloured(model, t, mask_at(params[MASK_KEY].detach(), t, stdr.knots), camera).image)
    model.conditioning(model.step)  # sets the motion branch's d_i (after the freeze)
    d = stdr.last_dynamic
    if d is None or d.shape[0] != params["means"].shape[0]:
        raise BadInput("view 'dynamic': the motion branch exists after STDR's freeze (stdr.freeze_at) with "
                         "the separated field on; this run has none")
    return to_uint8(_recoloured(model, t, d[:, 0], camera).image)


def available_views(run: ViewRun) -> list[str]:
    """The views this run can show (mask and dynamic need STDR, dynamic its frozen field)."""
    views = ["rgb", "depth", "alpha"]
    if run.has_stdr:
        if MASK_KEY in run.model.params:
            views.append("mask")
        p = run.model.plugin("stdr")
        if p.field is not None and p.phase(run.model.step).name == "FROZEN":
            views.append("dynamic")
    return views


def unfinished_note(model, what: str) -> str:
    """One line when `model` (loaded from a run's checkpoint) stopped before its config's
    optim.iterations (train.stop_at, a deadline, a kill, or still training); "" otherwise."""
    total = int(model.cfg.optim.iterations)
    if int(model.step) >= total:
        return ""
    return (f"{what} is of an unfinished run: its model is at iteration {model.step} of {total} "
            "(resume the run to finish it)")
