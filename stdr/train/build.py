"""A run's parts, built from its config: the factory behind `Trainer`.

`build_run` seeds the generators, loads the scene onto the device, builds the model from the
initial points, the densification strategy and the guard, and gathers them with the optimizers in
the run's state (stdr.train.state.RunState), in an order that fixes every random draw of a run.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Optional

import numpy as np
import torch

from ..data.load import load_scene
from ..densify.strategy import build_strategy
from ..device import resolve_device
from ..gaussians import scene_extent
from ..metrics import fused_loss, image_loss, image_loss_compiled
from ..gaussians import check_init_fits, initial_points
from ..model import build_model
from ..render.compiled import camera_values
from ..validate import check_guard_config
from .guard import Guard, monitor_split, resolve_compiled_check, resolve_sync_free
from .optim import make_optimizers, net_groups, uses_fused_adam
from .state import CameraSampler, RunState


@dataclass
class RunParts:
    """What `Trainer` trains with: `state` holds what a checkpoint keeps; the rest is rebuilt from
    the config at every start."""

    device: torch.device
    fused_adam: bool            # optim.fused_adam where torch has the kernel
    monitor: Optional[str]      # the guard's divergence split (periodic evaluations only), or None
    scene: Any                  # stdr.data.load's Scene, its images on the device
    strategy: Any               # the densification strategy (densify=<name>)
    cull_train: bool            # render.cull=train
    fused_loss: bool            # the photometric loss as one compiled pass (optim.fused_loss)
    image_loss: Callable        # that loss, or its torch twin
    state: RunState
    net_groups: list[dict]      # the networks' parameter groups with their schedules


def build_run(cfg, run_dir: Path, splits=("train",), data_base: Optional[str] = None) -> RunParts:
    """The parts of a run of `cfg` writing into `run_dir` (created), with the scene's `splits`
    (those the evaluations during training and the guard read are added)."""
    run_dir.mkdir(parents=True, exist_ok=True)
    if cfg.train.threads > 0:
        torch.set_num_threads(cfg.train.threads)
    device = resolve_device(cfg.device)
    fused_adam = uses_fused_adam(cfg, device)
    torch.manual_seed(cfg.seed)  # also seeds every CUDA device
    np.random.seed(cfg.seed)
    if cfg.train.eval_every > 0 or cfg.train.eval_at_warmup_end:  # evaluations during training need it
        splits = tuple(dict.fromkeys((*splits, cfg.data.eval_split)))
    check_guard_config(cfg.train.guard)
    # the divergence detector (periodic evaluations only) reads its own split, never test's
    monitor = (monitor_split(cfg.train.guard, cfg.data.format)
               if cfg.train.guard.enabled and cfg.train.eval_every > 0 else None)
    if monitor is not None:
        splits = tuple(dict.fromkeys((*splits, monitor)))
    scene = load_scene(cfg.data, splits, base=data_base, seed=cfg.seed).to(device)  # images moved once
    for f in scene.frames("train"):  # each camera's host copy of its numbers, once (no sync in a step)
        camera_values(f.camera)
    has_train = "train" in scene.splits
    train_times = scene.train_times() if has_train else None
    check_init_fits(cfg.model, device)  # model.init_num that cannot fit: named, not an allocator's traceback
    pts, colors = initial_points(cfg.model, scene.init_points, scene.init_colors, cfg.seed, where=str(scene.root))
    background = torch.tensor(scene.background, dtype=torch.float32)
    model = build_model(cfg, train_times, background, device, pts, colors)
    strategy = build_strategy(cfg.densify)  # densify=<name> (stdr.densify.strategy)
    cull_train = model.cull_mode() == "train"
    if cull_train and strategy.count_invisible:
        raise ValueError("render.cull=train renders only the rows that can reach opacity 1/255, so "
                         "densification cannot count the others as seen: set densify.count_invisible=false "
                         "as well, or render.cull=eval to cull outside training only")
    extent = scene_extent(scene.camera_centers("train")) if has_train else 1.0
    white = all(float(c) >= 1.0 for c in scene.background)
    guard = Guard(peak_gaussians=len(pts), monitor=monitor, checks=bool(cfg.train.guard.enabled),
                  sync_free=resolve_sync_free(cfg.train.guard, device, fused_adam),
                  compiled=resolve_compiled_check(cfg.train.guard, device), cfg=cfg.train.guard)
    fused = fused_loss(cfg.optim.fused_loss, device)
    # the run's state (stdr.train.state): what a checkpoint holds, what the guard and the evaluations see
    state = RunState(model=model, run_dir=run_dir, guard=guard,
                     strategy_state=strategy.initialize_state(len(pts), extent, white_background=white, device=device),
                     sampler=CameraSampler(len(scene.splits.get("train", [])), cfg.seed),
                     train_threads=torch.get_num_threads(), train_loss="compiled" if fused else "torch",
                     make_optimizers=lambda: make_optimizers(cfg, state.model, fused_adam))
    state.optimizers = make_optimizers(cfg, model, fused_adam)
    groups = net_groups(model)
    state.net_opt = torch.optim.Adam([{k: v for k, v in g.items() if k == "params" or k == "name"} for g in groups],
                                     lr=cfg.baseline.lr_init, eps=1e-15, fused=fused_adam)
    return RunParts(device=device, fused_adam=fused_adam, monitor=monitor, scene=scene, strategy=strategy,
                    cull_train=cull_train, fused_loss=fused, image_loss=image_loss_compiled if fused else image_loss,
                    state=state, net_groups=groups)
