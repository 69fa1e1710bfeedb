"""SC-GS (Huang et al. 2024): sparse control nodes that drive the Gaussians by skinning.

Stages (by training step):
1. [0, start_step): static warm-up (the training loop renders the canonical Gaussians).
2. [start_step, node_stage_end): node stage. The Gaussians stand in for the nodes: they are
   rendered isotropic and moved directly by the node MLP, which learns the motion field.
3. At node_stage_end the M nodes are resampled by farthest-point sampling over the Gaussians'
   trajectories (positions at `trajectory_samples` times, flattened), and skinning starts.
4. [node_stage_end, ...): each Gaussian blends its K = 3 nearest nodes (in [xyz, hyper-coords]
   space), w_k = exp(-d_k^2 / (2 r_k^2)) * sigmoid(node weight k), normalized. In local frames:
   x_t = sum_k w_k (R_k (x - p_k) + p_k + T_k); raw quaternion + sum_k w_k dq_k; exp(log s) +
   sum_k w_k ds_k. For `main_warmup` steps the node deltas are detached (as published).
   ARAP over node neighbourhoods regularizes, with the published decaying weight.

Differences from the published code (docs/baselines.md): the node stage trains the run's own
Gaussians instead of a separate node model, which then continue as the skinned Gaussians.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import List, Optional, Sequence

import torch
from torch import Tensor, nn

from ..ops import RowView, rows_of, scatter_mean, sigmoid, take_rows
from ..knn import searcher
from ..syncs import host_only
from .base import BaselineConfig, Deformation, Deltas, flag_value, mlp_kwargs, set_flag, stage_start
from .deform import DeformMLP
from .registry import register_baseline
from ..geometry import farthest_point_sampling, quat_to_rotmat
from ..gaussians import Gaussians
from ..context import StepContext

FEATURE_KEY = "scgs_feature"


@dataclass
class ScgsConfig:
    """SC-GS control nodes, `baseline.scgs.*` (docs/baselines.md)."""

    num_nodes: int = 512
    hyper_dim: int = 8
    knn_k: int = 3
    # the searches of every step (Gaussians to their nodes, nodes to nodes): "cdist" (torch.cdist +
    # topk) or "direct" (exact coordinate differences, the compiled kernel on the CPU: stdr.knn)
    knn: str = "cdist"
    node_stage_end: int = 10000     # nodes resampled by FPS over trajectories, skinning starts
    main_warmup: int = 3000         # node deltas detached for this many steps after the switch
    trajectory_samples: int = 16
    local_frame: bool = True
    feature_lr: float = 2.5e-3      # per-Gaussian hyper-coordinates
    arap_k: int = 10
    arap_dt: float = 0.05
    arap_steps: List[int] = field(default_factory=lambda: [0, 5000, 10000, 20000, 20001])  # after node_stage_end
    arap_weights: List[float] = field(default_factory=lambda: [1e-4, 1e-4, 1e-5, 1e-5, 0.0])


@dataclass
class ScgsBaselineConfig(BaselineConfig):
    """SC-GS (Huang et al. 2024), `baseline=scgs`: control nodes + linear blend skinning; the node
    MLP is Deformable 3DGS's with its heads started near zero (published dscale 1e-8). Sizes and
    stages: stdr/configs/budget_baseline/scgs_<budget>.yaml."""

    name: str = "scgs"
    head_init_std: Optional[float] = 1.0e-5
    scgs: ScgsConfig = field(default_factory=ScgsConfig)


def skinning_weights(d2: Tensor, radius: Tensor, node_weight: Tensor) -> Tensor:
    """w [N, K] from squared distances d2 [N, K] and the neighbours' radii and weight logits
    [N, K]: exp(-d2 / (2 r^2)) * sigmoid(weight), plus 1e-7, normalized to sum 1."""
    w = torch.exp(-d2 / (2.0 * radius.square())) * sigmoid(node_weight) + 1e-7
    return w / w.sum(-1, keepdim=True)


def blend_translation(x: Tensor, p: Tensor, R: Tensor, T: Tensor, w: Tensor, local_frame: bool = True) -> Tensor:
    """New positions [N, 3] of points x [N, 3] under their K nodes' motions: positions p [N, K, 3],
    rotations R [N, K, 3, 3], translations T [N, K, 3], weights w [N, K]."""
    if not local_frame:
        return x + (w[..., None] * T).sum(1)
    local = (R @ (x[:, None, :] - p)[..., None])[..., 0] + p + T  # [N, K, 3]
    return (w[..., None] * local).sum(1)


def arap_energy(p1: Tensor, p2: Tensor, nbr: Tensor) -> Tensor:
    """As-rigid-as-possible energy between node positions at two times, p1, p2 [M, 3], over
    neighbourhoods nbr [M, J]: mean_k,j |e2_kj - R_k e1_kj|^2 with each R_k the best rotation
    (Kabsch, by SVD)."""
    e1 = take_rows(p1, nbr) - p1[:, None]  # [M, J, 3]
    e2 = take_rows(p2, nbr) - p2[:, None]
    H = e1.transpose(1, 2) @ e2  # [M, 3, 3]
    U, _, Vh = torch.linalg.svd(H.detach())
    d = torch.sign(torch.linalg.det(Vh.transpose(1, 2) @ U.transpose(1, 2)))
    D = torch.diag_embed(torch.stack([torch.ones_like(d), torch.ones_like(d), d], -1))
    R = Vh.transpose(1, 2) @ D @ U.transpose(1, 2)  # maps e1 onto e2
    return (e2 - (R[:, None] @ e1[..., None])[..., 0]).square().sum(-1).mean()


def log_interp_schedule(step: int, steps: Sequence[int], values: Sequence[float]) -> float:
    """Piecewise log-linear interpolation of `values` at `steps` (linear where a value is 0)."""
    if step <= steps[0]:
        return float(values[0])
    for (s0, v0), (s1, v1) in zip(zip(steps, values), zip(steps[1:], values[1:])):
        if step <= s1:
            a = (step - s0) / max(s1 - s0, 1)
            if v0 > 0 and v1 > 0:
                return float(math.exp((1 - a) * math.log(v0) + a * math.log(v1)))
            return float((1 - a) * v0 + a * v1)
    return float(values[-1])


class ControlNodeDeformation(Deformation):
    # STDR's separated field feeds its network; the node conditioning blends every Gaussian's
    capabilities = frozenset({"conditioning", "mixes_rows"})

    def __init__(self, num_nodes: int = 512, hyper_dim: int = 8, knn_k: int = 3, start_step: int = 2000,
                 node_stage_end: int = 10000, main_warmup: int = 3000, trajectory_samples: int = 16,
                 local_frame: bool = True, depth: int = 8, width: int = 256, skips=(4,), xyz_freqs: int = 10,
                 t_freqs: int = 6, time_net: bool = True, time_out: int = 30, cond_dim: int = 0,
                 head_init_std: Optional[float] = 1e-5, feature_lr: float = 2.5e-3, arap_k: int = 10,
                 arap_dt: float = 0.05, arap_steps: Sequence[int] = (0, 5000, 10000, 20000, 20001),
                 arap_weights: Sequence[float] = (1e-4, 1e-4, 1e-5, 1e-5, 0.0), seed: int = 0,
                 knn: str = "cdist", knn_compiled: Optional[bool] = None):
        super().__init__()
        self.search = searcher("baseline.scgs.knn", knn, knn_compiled)  # the per-step nearest-neighbour search
        if node_stage_end < start_step:
            raise ValueError(f"baseline.scgs.node_stage_end ({node_stage_end}) must be >= the warm-up ({start_step})")
        self.m, self.hyper_dim, self.k = num_nodes, hyper_dim, knn_k
        self.start_step, self.node_stage_end, self.main_warmup = start_step, node_stage_end, main_warmup
        self.trajectory_samples, self.local_frame = trajectory_samples, local_frame
        self.cond_dim, self.feature_lr, self.seed = cond_dim, feature_lr, seed
        self.arap_k, self.arap_dt = arap_k, arap_dt
        self.arap_steps, self.arap_weights = list(arap_steps), list(arap_weights)
        self.net = DeformMLP(depth, width, skips, xyz_freqs, t_freqs, time_net, time_out, cond_dim, heads=False)
        self.head_xyz, self.head_rot, self.head_scale = nn.Linear(width, 3), nn.Linear(width, 4), nn.Linear(width, 3)
        if head_init_std is not None:  # published: dxyz 1e-5, dscale 1e-8, drot 1e-5, zero bias
            for h, s in ((self.head_xyz, head_init_std), (self.head_rot, head_init_std),
                         (self.head_scale, head_init_std * 1e-3)):
                nn.init.normal_(h.weight, std=s)
                nn.init.zeros_(h.bias)
        self.nodes = nn.Parameter(torch.zeros(num_nodes, 3 + hyper_dim))   # xyz + hyper-coordinates
        self.node_log_radius = nn.Parameter(torch.zeros(num_nodes))
        self.node_weight = nn.Parameter(torch.zeros(num_nodes))             # sigmoid -> 0.5
        self.register_buffer("stage", torch.zeros((), dtype=torch.long))    # 0 static, 1 nodes, 2 skinning
        self.gen = torch.Generator().manual_seed(seed)

    @classmethod
    def config_kwargs(cls, b, cond_dim=0, train_times=None, seed=0, schedule=None) -> dict:
        c = b.scgs
        return dict(mlp_kwargs(b, cond_dim), time_net=b.time_net, time_out=b.time_out, num_nodes=c.num_nodes,
                    hyper_dim=c.hyper_dim, knn_k=c.knn_k, start_step=stage_start(b, schedule),
                    node_stage_end=c.node_stage_end, main_warmup=c.main_warmup,
                    trajectory_samples=c.trajectory_samples, local_frame=c.local_frame, feature_lr=c.feature_lr,
                    arap_k=c.arap_k, arap_dt=c.arap_dt, arap_steps=list(c.arap_steps),
                    arap_weights=list(c.arap_weights), seed=seed, knn=c.knn, knn_compiled=b.knn_compiled)

    @classmethod
    def stages(cls, b):
        """The node stage from the warm-up, and the node->skinning switch: nodes resampled at
        node_stage_end, node deltas detached for main_warmup steps after it (a switch window)."""
        c = b.scgs
        end, detached = int(c.node_stage_end), int(c.node_stage_end) + int(c.main_warmup)
        events = [(int(b.warmup), "baseline.warmup", "SC-GS node stage: each Gaussian moves as a control node"),
                  (end, "baseline.scgs.node_stage_end",
                   "SC-GS: nodes resampled by FPS, linear blend skinning starts, node deltas detached"),
                  (detached, "baseline.scgs.main_warmup", "SC-GS: node deltas attached")]
        return events, [("SC-GS node->skinning switch (baseline.scgs.node_stage_end + main_warmup)", end, detached)]

    # -------------------------------------------------------------- per-Gaussian state
    def compile_network(self) -> None:
        """baseline.compile=true: the MLP trunk through torch.compile (DeformMLP.compile_network)."""
        self.net.compile_network()

    def init_gaussians(self, params) -> None:
        """The hyper-coordinates [N, hyper_dim] (lr baseline.scgs.feature_lr), where absent."""
        if FEATURE_KEY not in params:
            n = params["means"].shape[0]
            params[FEATURE_KEY] = nn.Parameter(torch.full((n, self.hyper_dim), -1e-2, device=params["means"].device))

    def param_groups(self) -> list[dict]:
        return [*super().param_groups(), {"key": FEATURE_KEY, "lr": self.feature_lr}]

    # -------------------------------------------------------------- node MLP
    def node_deltas(self, xyz: Tensor, t: float, cond: Optional[Tensor] = None) -> tuple[Tensor, Tensor, Tensor]:
        h = self.net.trunk(xyz, t, cond)
        return self.head_xyz(h), self.head_rot(h), self.head_scale(h)

    def _cond_or_zeros(self, cond: Optional[Tensor], n: int, like: Tensor) -> Optional[Tensor]:
        if not self.cond_dim:
            return None
        return like.new_zeros(n, self.cond_dim) if cond is None else cond

    @torch.no_grad()
    def resample_nodes(self, params, cond: Optional[Tensor] = None) -> None:
        """Nodes := FPS over the Gaussians' trajectories; radius := mean distance to 3 nearest nodes.

        The trajectories are those the node stage renders: the node MLP on each Gaussian with its
        conditioning cond [N, cond_dim] (zeros when None)."""
        x = params["means"].detach()
        if x.shape[0] < self.m:
            raise ValueError(f"SC-GS needs at least {self.m} Gaussians to place its nodes, has {x.shape[0]}; "
                             "lower baseline.scgs.num_nodes")
        c = self._cond_or_zeros(None if cond is None else cond.detach(), x.shape[0], x)
        traj = []
        for t in torch.linspace(0.0, 1.0, self.trajectory_samples, device="cpu").tolist():
            dx, _, _ = self.node_deltas(x, t, c)
            traj.append(x + dx)
        idx = farthest_point_sampling(torch.cat(traj, -1), self.m, self.gen)
        p = x[idx]
        d2, _ = self.search(p, p, min(3, self.m - 1), exclude_self=True)
        self.nodes.zero_()
        self.nodes[:, :3] = p
        self.node_log_radius.copy_(torch.log(d2.mean(1).sqrt().clamp_min(1e-6)))
        self.node_weight.zero_()

    def before_step(self, ctx: StepContext) -> None:
        params, step, cond = ctx.params, ctx.step, ctx.cond
        if step < self.start_step:
            set_flag(self, "stage", 0)
        elif step < self.node_stage_end:
            set_flag(self, "stage", 1)
        elif flag_value(self, "stage") != 2:
            self.resample_nodes(params, cond)
            set_flag(self, "stage", 2)
        self._detach = flag_value(self, "stage") == 2 and step < self.node_stage_end + self.main_warmup
        self._last_search = None  # a step's searches start afresh

    # -------------------------------------------------------------- skinning
    def neighbours(self, params, reuse: bool = False) -> tuple[Tensor, Tensor]:
        """(node indices [N, K], squared distances [N, K] with gradients to the hyper-coordinates
        and node radii) of each Gaussian in [xyz, hyper] space, node xyz detached.

        The last search is kept with the tensors it read and their versions. With `reuse`, a
        search on the same, unchanged tensors takes its indices from there: the ARAP term's node
        conditioning, after the render of the same step, so +STDR searches once a step. Any
        in-place update (the optimizer) or new tensor (densification) searches again, and the
        distances are always recomputed (they carry the gradients)."""
        sources = (params["means"], params[FEATURE_KEY], self.nodes)
        key = [(t, t._version) for t in sources]
        x = torch.cat([params["means"].detach(), params[FEATURE_KEY]], -1)
        nodes = torch.cat([self.nodes[:, :3].detach(), self.nodes[:, 3:]], -1)
        last = getattr(self, "_last_search", None)
        if reuse and last is not None and all(a is b and va == vb for (a, va), (b, vb) in zip(key, last[0])):
            idx = last[1]
        else:
            with torch.no_grad():
                _, idx = self.search(x.detach(), nodes.detach(), min(self.k, self.m))
            self._last_search = (key, idx)
        d2 = (x[:, None, :] - take_rows(nodes, idx)).square().sum(-1)
        return idx, d2

    def skinning(self, params, reuse: bool = False) -> tuple[Tensor, Tensor]:
        """(node indices [N, K], skinning weights [N, K]) of every Gaussian (`reuse`: neighbours)."""
        idx, d2 = self.neighbours(params, reuse)
        return idx, skinning_weights(d2, take_rows(self.node_log_radius.exp(), idx), take_rows(self.node_weight, idx))

    def node_conditioning(self, cond: Optional[Tensor], idx: Tensor, w: Tensor) -> Optional[Tensor]:
        """Per-node conditioning [M, cond_dim]: the skinning-weighted mean of its Gaussians' cond."""
        if not self.cond_dim:
            return None
        cond_n, _ = scatter_mean(cond[:, None, :].expand(-1, idx.shape[1], -1), idx, w.detach(), self.m)
        return cond_n

    def forward(self, params, t: float, cond: Optional[Tensor] = None) -> Deltas:
        return self.forward_rows(params, t, cond, None)

    def forward_rows(self, params, t: float, cond: Optional[Tensor], rows: Optional[Tensor]) -> Deltas:
        """Deltas of the Gaussians `rows` [M] (all when None). The node conditioning blends every
        Gaussian's cond, so with a conditioning all rows are skinned and only the blend is
        restricted; without one, only the kept rows are skinned."""
        if self.cond_dim and cond is None:
            raise ValueError("this deformation was built with cond_dim > 0 and needs cond")
        if flag_value(self, "stage") == 1:  # node stage: the Gaussians are the nodes, moved directly
            dx, _, _ = self.node_deltas(rows_of(params["means"], rows).detach(), t, rows_of(cond, rows))
            return Deltas(means=dx)
        skinned = params if rows is None or self.cond_dim else RowView(params, rows)
        idx, w = self.skinning(skinned)
        cond_n = self.node_conditioning(cond, idx, w)
        if rows is not None and skinned is params:
            idx, w = take_rows(idx, rows), take_rows(w, rows)
        p = self.nodes[:, :3]
        if getattr(self, "_detach", False):
            with torch.no_grad():
                T, dq, ds = self.node_deltas(p.detach(), t, cond_n)
        else:
            T, dq, ds = self.node_deltas(p.detach(), t, cond_n)
        R = quat_to_rotmat(torch.cat([1.0 + dq[:, :1], dq[:, 1:]], -1))  # identity + dq (no host tensor: a copy) [M, 3, 3]
        x = rows_of(params["means"], rows)
        x_t = blend_translation(x, take_rows(p, idx), take_rows(R, idx), take_rows(T, idx), w, self.local_frame)
        wq = (w[..., None] * take_rows(dq, idx)).sum(1)
        wsc = (w[..., None] * take_rows(ds, idx)).sum(1)
        return Deltas(means=x_t - x, quats=wq, scales=wsc)

    def apply_rule(self, params, d: Deltas):
        """Node stage: isotropic, unrotated Gaussians moved by dxyz. Skinning: dxyz added to the
        means, the blended dq added to the *raw* quaternion, ds after activation (SC-GS)."""
        sh = torch.cat([params["sh0"], params["shN"]], 1)
        op = sigmoid(params["opacities"])
        if flag_value(self, "stage") == 1:
            s = torch.exp(params["scales"].mean(-1, keepdim=True)).expand(-1, 3)
            q = torch.zeros_like(params["quats"])
            q[:, 0] = 1.0
            return Gaussians(means=params["means"] + d.means, quats=q, scales=s, opacities=op, sh=sh)
        q = params["quats"] + (0 if d.quats is None else d.quats)
        s = torch.exp(params["scales"]) + (0 if d.scales is None else d.scales)
        return Gaussians(means=params["means"] + d.means, quats=q, scales=s, opacities=op, sh=sh)

    def regularizers(self, ctx: StepContext) -> dict[str, Tensor]:
        """ARAP between the nodes at two nearby times, under the node conditioning the render uses
        (zeros when ctx.cond is None)."""
        params, step, cond = ctx.params, ctx.step, ctx.cond
        if flag_value(self, "stage") != 2 or getattr(self, "_detach", False):
            return {}
        lam = log_interp_schedule(step - self.node_stage_end, self.arap_steps, self.arap_weights)
        if lam <= 0:
            return {}
        # the pair of times comes from (seed, step), so a resumed run draws the same ones
        g = torch.Generator().manual_seed(self.seed * 1_000_003 + step)
        with host_only():  # a CPU generator's draw: host work, no device to wait for
            t1 = float(torch.rand((), generator=g, device="cpu")) * (1.0 - self.arap_dt)
        t2 = t1 + self.arap_dt
        p = self.nodes[:, :3].detach()
        _, nbr = self.search(p, p, min(self.arap_k, self.m - 1), exclude_self=True)
        cond_n = self._cond_or_zeros(None if cond is None or not self.cond_dim  # the render's search, reused
                                     else self.node_conditioning(cond, *self.skinning(params, reuse=True)), self.m, p)
        p1 = p + self.node_deltas(p, t1, cond_n)[0]
        p2 = p + self.node_deltas(p, t2, cond_n)[0]
        return {"scgs_arap": lam * arap_energy(p1, p2, nbr)}


register_baseline("scgs", ControlNodeDeformation, ScgsBaselineConfig, in_grids=True)
