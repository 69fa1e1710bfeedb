"""Stress transforms: a harder training set derived from any scene at load time.

`data.stress.*` keys (StressConfig) act on the *training* split only, seeded, in this order:
1. frames whose time lies in `drop_times` = [t0, t1] are dropped (evaluation frames inside the
   window then test times never seen in training);
2. frames whose time lies in `sparse_times` are kept with probability `sparse_keep` (non-uniform
   time sampling: dense outside the window, sparse inside);
3. a random `keep_fraction` of what is left is kept (exactly round(fraction * n) frames);
4. camera pose noise: each camera turns about a random axis through its centre by an angle drawn
   from N(0, pose_rot_deg^2), and its centre moves by a Gaussian offset whose RMS length is
   pose_trans x the scene radius (1.1 x the largest distance of a training camera centre from
   their mean, the extent densification uses);
5. time jitter: each time gets N(0, time_jitter^2) added, clipped to [0, 1].

The evaluation splits are never touched. What was done is summarised in scene.meta["stress"],
which metrics.json records under `data`.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, List, Optional

import numpy as np
import torch

from ..geometry import so3_exp
from .types import Frame, SceneData
from ..gaussians import scene_extent


@dataclass
class StressConfig:
    """data.stress: a stressed training set (every key off by default)."""

    drop_times: Optional[List[float]] = None    # [t0, t1]: training frames with t0 <= time <= t1 are dropped
    sparse_times: Optional[List[float]] = None  # [t0, t1]: training frames there are kept with prob. sparse_keep
    sparse_keep: float = 1.0
    keep_fraction: float = 1.0                  # keep this fraction of the training frames (at random)
    pose_rot_deg: float = 0.0                   # std of each camera's rotation noise, degrees
    pose_trans: float = 0.0                     # RMS camera-centre offset, as a fraction of the scene radius
    time_jitter: float = 0.0                    # std of the noise added to each normalized time
    seed: Optional[int] = None                  # null: the run's seed
    # how tables name it (stdr/configs/stress/<label>_<level>.yaml set both); no effect on the data
    label: str = "none"
    level: int = 0


def is_active(cfg) -> bool:
    return bool(cfg.drop_times or cfg.sparse_times or cfg.keep_fraction != 1.0 or cfg.pose_rot_deg
                or cfg.pose_trans or cfg.time_jitter)


def _window(value, key: str) -> Optional[tuple[float, float]]:
    if value is None:
        return None
    w = [float(v) for v in value]
    if len(w) != 2 or not 0.0 <= w[0] < w[1] <= 1.0:
        raise ValueError(f"data.stress.{key}={list(value)}: give [t0, t1] with 0 <= t0 < t1 <= 1 "
                         "(times are normalized to [0, 1])")
    return w[0], w[1]


def thinned_window(stress) -> Optional[tuple[float, float]]:
    """The time window a stress thins out of the training set: drop_times (no frame kept there)
    or sparse_times (a few kept); None for the other stresses. `stress` is a data.stress config
    or the plain mapping of a run's config.yaml (studies/stability.py)."""
    for key in ("drop_times", "sparse_times"):
        if stress.get(key):
            return _window(stress.get(key), key)
    return None


def check_stress(cfg) -> None:
    """Errors that name the key, for values that cannot work."""
    _window(cfg.drop_times, "drop_times")
    _window(cfg.sparse_times, "sparse_times")
    if not 0.0 <= cfg.sparse_keep <= 1.0:
        raise ValueError(f"data.stress.sparse_keep={cfg.sparse_keep}: must be in [0, 1]")
    if not 0.0 < cfg.keep_fraction <= 1.0:
        raise ValueError(f"data.stress.keep_fraction={cfg.keep_fraction}: must be in (0, 1]")
    for k in ("pose_rot_deg", "pose_trans", "time_jitter"):
        if getattr(cfg, k) < 0:
            raise ValueError(f"data.stress.{k}={getattr(cfg, k)}: must be 0 or more")


def scene_radius(frames: list[Frame]) -> float:
    return scene_extent(np.stack([f.camera.center.double().cpu().numpy() for f in frames]))


def apply_stress(scene: SceneData, cfg, seed: int) -> dict[str, Any]:
    """Replace scene.splits["train"] by its stressed version (see the module doc); returns (and
    stores in scene.meta["stress"]) the keys and what they did."""
    check_stress(cfg)
    if not is_active(cfg):
        return {}
    out: dict[str, Any] = {"keys": {k: v if v is None or isinstance(v, (str, int, float)) else [float(x) for x in v]
                                    for k in StressConfig.__dataclass_fields__ for v in [getattr(cfg, k)]},
                           "seed": int(cfg.seed if cfg.seed is not None else seed)}
    scene.meta["stress"] = out
    if "train" not in scene.splits:  # e.g. stdr-eval, which loads the evaluation split alone
        return out
    rng = np.random.default_rng(out["seed"])
    frames = list(scene.splits["train"])
    n0 = len(frames)
    drop, sparse = _window(cfg.drop_times, "drop_times"), _window(cfg.sparse_times, "sparse_times")
    if drop is not None:
        frames = [f for f in frames if not drop[0] <= f.time <= drop[1]]
    n_drop = n0 - len(frames)
    if sparse is not None:
        u = rng.random(len(frames))
        frames = [f for f, x in zip(frames, u) if not (sparse[0] <= f.time <= sparse[1]) or x < cfg.sparse_keep]
    n_sparse = n0 - n_drop - len(frames)
    if cfg.keep_fraction < 1.0:
        k = int(round(cfg.keep_fraction * len(frames)))
        keep = np.sort(rng.permutation(len(frames))[:k])
        frames = [frames[i] for i in keep]
    if len(frames) < 2:
        raise ValueError(f"data.stress leaves {len(frames)} of {n0} training frames in {scene.root} (drop_times="
                         f"{cfg.drop_times}, sparse_times={cfg.sparse_times} x {cfg.sparse_keep}, keep_fraction="
                         f"{cfg.keep_fraction}): keep at least 2")
    out["train_frames"] = {"before": n0, "dropped_window": n_drop, "dropped_sparse": n_sparse, "kept": len(frames)}
    if cfg.pose_rot_deg or cfg.pose_trans:
        radius = scene_radius(scene.splits["train"])
        angles, shifts, noisy = [], [], []
        for f in frames:
            cam = f.camera
            R = cam.R.double().cpu().numpy()
            c = cam.center.double().cpu().numpy()
            axis = rng.normal(size=3)
            axis /= np.linalg.norm(axis)
            ang = np.deg2rad(rng.normal(0.0, cfg.pose_rot_deg)) if cfg.pose_rot_deg else 0.0
            d = rng.normal(0.0, cfg.pose_trans * radius / np.sqrt(3.0), size=3) if cfg.pose_trans else np.zeros(3)
            # the camera turns about its own centre: world-to-camera R' = R @ dR^T
            R2 = R @ so3_exp(torch.tensor(axis * ang, dtype=torch.float64)).numpy().T
            c2 = c + d
            t2 = -R2 @ c2
            noisy.append(replace(f, camera=replace(cam, R=torch.as_tensor(R2, dtype=cam.R.dtype).to(cam.R.device),
                                                   t=torch.as_tensor(t2, dtype=cam.t.dtype).to(cam.t.device))))
            angles.append(abs(np.rad2deg(ang)))
            shifts.append(float(np.linalg.norm(d)))
        frames = noisy
        out["pose_noise"] = {"scene_radius": radius, "rotation_deg_mean": float(np.mean(angles)),
                             "rotation_deg_max": float(np.max(angles)),
                             "shift_rms": float(np.sqrt(np.mean(np.square(shifts))))}
    if cfg.time_jitter:
        dt = rng.normal(0.0, cfg.time_jitter, size=len(frames))
        frames = [replace(f, time=float(np.clip(f.time + x, 0.0, 1.0))) for f, x in zip(frames, dt)]
        out["time_jitter_abs_mean"] = float(np.mean(np.abs(dt)))
    scene.splits["train"] = frames
    return out
