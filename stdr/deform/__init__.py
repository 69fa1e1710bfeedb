"""Deformation modules: one per baseline, all behind the interface in `base`."""
from __future__ import annotations

from typing import Optional

import numpy as np

from .base import Deformation, Deltas, apply_post_activation, apply_pre_activation
from .control_nodes import ControlNodeDeformation
from .deform3dgs import DeformMLP
from .hexplane import HexPlaneDeformation
from .superpoints import SuperpointDeformation

REGISTRY = {"deform": DeformMLP, "scgs": ControlNodeDeformation, "spgs": SuperpointDeformation,
            "4dgs": HexPlaneDeformation}


def build_deformation(name: str, **kwargs) -> Deformation:
    if name not in REGISTRY:
        raise ValueError(f"baseline.name={name!r} is not one of {sorted(REGISTRY)}")
    return REGISTRY[name](**kwargs)


def hexplane_time_res(b, train_times: Optional[np.ndarray]) -> int:
    """baseline.hexplane.time_res, or half the number of distinct training times when 0 (the
    published per-scene values are exactly that: bouncingballs 150 frames -> 75, ...)."""
    if b.hexplane.time_res > 0:
        return int(b.hexplane.time_res)
    if train_times is None or len(train_times) == 0:
        raise ValueError("baseline.hexplane.time_res=0 takes half the number of training times, but none were "
                         "given: build the model from a scene with a train split or from a checkpoint that "
                         "holds them (stdr.model.load_model), or set baseline.hexplane.time_res")
    return max(2, len(train_times) // 2)


def deformation_kwargs(b, cond_dim: int = 0, train_times: Optional[np.ndarray] = None, seed: int = 0,
                       schedule=None) -> dict:
    """Constructor arguments of baseline `b.name` from the baseline config; the step at which the
    module's stages start is the schedule's end of the static warm-up (b.warmup without one)."""
    start = int(b.warmup) if schedule is None else schedule.static_warmup_end
    mlp = dict(depth=b.depth, width=b.width, skips=list(b.skips), xyz_freqs=b.xyz_freqs, t_freqs=b.t_freqs,
               cond_dim=cond_dim, head_init_std=b.head_init_std)
    if b.name == "deform":
        return dict(mlp, time_net=b.time_net, time_out=b.time_out)
    if b.name == "scgs":
        c = b.scgs
        return dict(mlp, time_net=b.time_net, time_out=b.time_out, num_nodes=c.num_nodes, hyper_dim=c.hyper_dim,
                    knn_k=c.knn_k, start_step=start, node_stage_end=c.node_stage_end, main_warmup=c.main_warmup,
                    trajectory_samples=c.trajectory_samples, local_frame=c.local_frame, feature_lr=c.feature_lr,
                    arap_k=c.arap_k, arap_dt=c.arap_dt, arap_steps=list(c.arap_steps),
                    arap_weights=list(c.arap_weights), seed=seed)
    if b.name == "spgs":
        c = b.spgs
        return dict(mlp, num_superpoints=c.num_superpoints, knn_k=c.knn_k, start_step=start,
                    assoc_lr=c.assoc_lr, weights={"xyz": c.lambda_xyz, "rot": c.lambda_rot, "off": c.lambda_off},
                    seed=seed)
    if b.name == "4dgs":
        c = b.hexplane
        return dict(base_res=c.base_res, multires=list(c.multires), channels=c.channels,
                    time_res=hexplane_time_res(b, train_times), depth=b.depth, width=b.width, cond_dim=cond_dim,
                    head_init_std=b.head_init_std, grid_lr_mult=c.grid_lr_mult,
                    weights={"plane_tv": c.plane_tv, "time_smooth": c.time_smooth, "l1_time": c.l1_time})
    raise ValueError(f"baseline.name={b.name!r} is not one of {sorted(REGISTRY)}")


__all__ = ["Deformation", "Deltas", "DeformMLP", "ControlNodeDeformation", "SuperpointDeformation",
           "HexPlaneDeformation", "REGISTRY", "build_deformation", "deformation_kwargs",
           "apply_post_activation", "apply_pre_activation"]
