"""Procedural dynamic scenes in D-NeRF format, rendered by analytic ray casting (not Gaussians).

The default scene: a checkered base box, an arm (a striped box) that swings about a hinge on
top of the base, and a textured ball bouncing beside it. Lambertian shading under a fixed
light, RGBA with a transparent background, 2x2 supersampled edges, and a different camera per
frame on a sphere around the origin, as in D-NeRF. Test and val times are never train times.
Deterministic for a given set of options.
"""
from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ..io.files import write_png

LIGHT = np.array([0.4, 0.3, 0.85]) / np.linalg.norm([0.4, 0.3, 0.85])


@dataclass
class SceneOptions:
    n_train: int = 60
    n_val: int = 10
    n_test: int = 10
    resolution: int = 128
    motion: str = "swing"          # swing: arm swings, ball bounces | jump: static arm, the ball
                                   # jumps between two places (the ghosting case: JUMP_A / JUMP_B)
    motion_speed: float = 1.0      # cycles of the arm swing (or of the jump) over t in [0, 1]
    swing_degrees: float = 30.0    # arm swing amplitude (60 makes the arm vanish in short runs)
    arm_half_width: float = 0.15
    bounce_height: float = 0.8
    time_sampling: str = "uniform"  # "uniform" or "random" train times
    camera_radius: float = 3.3
    camera_angle_x: float = 0.6911112070083618  # as in D-NeRF
    seed: int = 0

    def key(self) -> str:
        return hashlib.sha1(json.dumps(asdict(self), sort_keys=True).encode()).hexdigest()[:12]


def _box_hit(o, d, center, half, R):
    """Ray/oriented-box intersection. o, d [M, 3]; R [3, 3] box-to-world. Returns t [M], local p, n."""
    lo = (o - center) @ R  # world -> local (R orthonormal)
    ld = d @ R
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / ld
        t1, t2 = (-half - lo) * inv, (half - lo) * inv
    tmin = np.nanmax(np.minimum(t1, t2), axis=1)
    tmax = np.nanmin(np.maximum(t1, t2), axis=1)
    hit = (tmax >= tmin) & (tmin > 1e-6)
    t = np.where(hit, tmin, np.inf)
    p = lo + ld * np.where(hit, t, 0)[:, None]
    # normal: the axis where the local point sits on the face
    rel = np.abs(p) / half
    ax = np.argmax(rel, axis=1)
    n_local = np.zeros_like(p)
    n_local[np.arange(len(p)), ax] = np.sign(p[np.arange(len(p)), ax])
    return t, p, n_local @ R.T


def _sphere_hit(o, d, center, radius):
    oc = o - center
    b = np.sum(oc * d, 1)
    c = np.sum(oc * oc, 1) - radius ** 2
    disc = b * b - c
    hit = disc >= 0
    t = -b - np.sqrt(np.where(hit, disc, 0))
    hit &= t > 1e-6
    t = np.where(hit, t, np.inf)
    p = o + d * np.where(hit, t, 0)[:, None]
    return t, p, (p - center) / radius


def _rot_x(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


JUMP_A = np.array([0.8, 0.0, -0.2])   # the ball's place in the first half of each jump cycle
JUMP_B = np.array([-0.8, 0.0, -0.2])  # and in the second half


def jump_at_a(t, opt: SceneOptions):
    """motion=jump: True where the ball is at JUMP_A at time t (array or float)."""
    return np.mod(np.asarray(t) * opt.motion_speed, 1.0) < 0.5


def scene_state(t: float, opt: SceneOptions) -> dict:
    """Object poses at time t in [0, 1]."""
    if opt.motion not in ("swing", "jump"):
        raise ValueError(f"data.procedural.motion={opt.motion!r}: use 'swing' or 'jump'")
    hinge = np.array([0.0, 0.0, -0.45])
    if opt.motion == "jump":
        R_arm = np.eye(3)
        ball = JUMP_A if jump_at_a(t, opt) else JUMP_B
    else:
        swing = np.deg2rad(opt.swing_degrees) * np.sin(2 * np.pi * opt.motion_speed * t)
        bounce = opt.bounce_height * np.abs(np.sin(np.pi * opt.motion_speed * t * 2))
        R_arm = _rot_x(swing)
        ball = np.array([0.8, 0.0, -0.7 + 0.25 + bounce])
    return {
        "base": (np.array([0.0, 0.0, -0.7]), np.array([0.45, 0.45, 0.25]), np.eye(3)),
        "arm": (hinge + R_arm @ np.array([0.0, 0.0, 0.5]),
                np.array([opt.arm_half_width, opt.arm_half_width, 0.5]), R_arm),
        "ball": (ball, 0.25),
    }


def shade_rays(o: np.ndarray, d: np.ndarray, t: float, opt: SceneOptions) -> np.ndarray:
    """RGBA [M, 4] for rays o, d [M, 3] at time t."""
    st = scene_state(t, opt)
    hits = []
    c, h, R = st["base"]
    tb, pb, nb = _box_hit(o, d, c, h, R)
    chk = (np.floor(pb[:, 0] * 5) + np.floor(pb[:, 1] * 5) + np.floor(pb[:, 2] * 5)) % 2
    hits.append((tb, nb, np.where(chk[:, None] > 0, [0.2, 0.35, 0.8], [0.9, 0.9, 0.85])))
    c, h, R = st["arm"]
    ta, pa, na = _box_hit(o, d, c, h, R)
    band = np.floor((pa[:, 2] + 0.5) * 6) % 2
    hits.append((ta, na, np.where(band[:, None] > 0, [0.85, 0.15, 0.1], [0.95, 0.8, 0.1])))
    c, r = st["ball"]
    ts, ps, ns = _sphere_hit(o, d, c, r)
    u = np.arctan2(ns[:, 1], ns[:, 0]) / np.pi * 4
    v = np.arccos(np.clip(ns[:, 2], -1, 1)) / np.pi * 4
    chk = (np.floor(u) + np.floor(v)) % 2
    hits.append((ts, ns, np.where(chk[:, None] > 0, [0.1, 0.65, 0.25], [0.95, 0.95, 0.95])))
    T = np.stack([x[0] for x in hits], 1)
    k = np.argmin(T, 1)
    hit = np.isfinite(T[np.arange(len(k)), k])
    n = np.stack([x[1] for x in hits], 1)[np.arange(len(k)), k]
    albedo = np.stack([x[2] for x in hits], 1)[np.arange(len(k)), k]
    shade = 0.35 + 0.65 * np.clip(n @ LIGHT, 0, None)
    rgb = albedo * shade[:, None]
    return np.concatenate([np.where(hit[:, None], rgb, 0.0), hit[:, None].astype(np.float64)], 1)


def look_at_c2w(eye: np.ndarray) -> np.ndarray:
    """Blender/OpenGL camera-to-world looking at the origin, z up."""
    back = eye / np.linalg.norm(eye)
    right = np.cross([0.0, 0.0, 1.0], back)
    right /= np.linalg.norm(right)
    up = np.cross(back, right)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, up, back, eye
    return c2w


def render_frame(c2w: np.ndarray, t: float, opt: SceneOptions, ss: int = 2) -> np.ndarray:
    """RGBA uint8 [H, W, 4] (straight alpha) of the scene at time t seen from c2w (OpenGL)."""
    W = H = opt.resolution
    f = 0.5 * W / np.tan(0.5 * opt.camera_angle_x)
    s = (np.arange(W * ss) + 0.5) / ss
    u, v = np.meshgrid(s, s, indexing="xy")
    dirs_cam = np.stack([(u - W / 2) / f, -(v - H / 2) / f, -np.ones_like(u)], -1).reshape(-1, 3)
    d = dirs_cam @ c2w[:3, :3].T
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = np.broadcast_to(c2w[:3, 3], d.shape)
    rgba = shade_rays(o, d, t, opt).reshape(H, ss, W, ss, 4)
    premult = np.concatenate([rgba[..., :3] * rgba[..., 3:], rgba[..., 3:]], -1).mean((1, 3))
    a = premult[..., 3:]
    rgb = np.where(a > 0, premult[..., :3] / np.maximum(a, 1e-8), 0.0)
    return np.round(np.concatenate([rgb, a], -1).clip(0, 1) * 255).astype(np.uint8)


def _times(opt: SceneOptions, rng: np.random.Generator) -> dict[str, np.ndarray]:
    if opt.time_sampling == "uniform":
        train = np.linspace(0.0, 1.0, opt.n_train)
    elif opt.time_sampling == "random":
        train = np.sort(np.concatenate([[0.0, 1.0], rng.uniform(0, 1, opt.n_train - 2)]))
    else:
        raise ValueError(f"time_sampling={opt.time_sampling!r}: use 'uniform' or 'random'")
    out = {"train": train}
    gap = 0.25 / max(opt.n_train - 1, 1)
    for split, n in (("val", opt.n_val), ("test", opt.n_test)):
        t = np.sort(rng.uniform(0, 1, n))
        # keep every held-out time away from the train times (they must be unseen times)
        near = np.abs(t[:, None] - train[None]).min(1) < gap
        t = np.where(near, np.clip(t + 2 * gap, 0, 1), t)
        out[split] = t
    return out


def generate_scene(out_dir: str | Path, opt: SceneOptions | None = None) -> Path:
    """Write a D-NeRF-format scene to out_dir (transforms_*.json + RGBA PNGs)."""
    out = Path(out_dir)
    opt = opt or SceneOptions()
    rng = np.random.default_rng(opt.seed)
    times = _times(opt, rng)
    for split, ts in times.items():
        (out / split).mkdir(parents=True, exist_ok=True)
        frames = []
        for i, t in enumerate(ts):
            az = rng.uniform(0, 2 * np.pi)
            el = np.deg2rad(rng.uniform(10, 50))
            eye = opt.camera_radius * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
            c2w = look_at_c2w(eye)
            img = render_frame(c2w, float(t), opt)
            write_png(out / split / f"r_{i:03d}.png", img[..., [2, 1, 0, 3]], "cache")
            frames.append({"file_path": f"./{split}/r_{i:03d}", "time": float(t),
                           "transform_matrix": c2w.tolist()})
        (out / f"transforms_{split}.json").write_text(
            json.dumps({"camera_angle_x": opt.camera_angle_x, "frames": frames}, indent=1))
    (out / "generator.json").write_text(json.dumps(asdict(opt), indent=1))
    return out


def embedded_scene(cache_dir: str | Path, opt: SceneOptions | None = None) -> Path:
    """The scene for `opt`, generated into cache_dir/<options hash> on first use."""
    import os
    import shutil
    import tempfile

    opt = opt or SceneOptions()
    path = Path(cache_dir) / f"procedural-{opt.key()}"
    if not (path / "generator.json").is_file():
        # parallel jobs (a sweep) may generate the same scene at once: each writes its own
        # folder and renames it into place; the first complete one wins, the others are dropped
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=path.name + ".tmp-", dir=path.parent))
        try:
            generate_scene(tmp, opt)
        except BaseException:  # a full disk, an interrupt: no half scene stays in the cache
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        if path.exists() and not (path / "generator.json").is_file():
            shutil.rmtree(path, ignore_errors=True)  # an incomplete folder from an interrupted run
        try:
            os.rename(tmp, path)  # atomic; fails if another job's complete folder is there
        except OSError:
            if not (path / "generator.json").is_file():
                raise
        shutil.rmtree(tmp, ignore_errors=True)
    return path
