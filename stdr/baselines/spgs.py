"""SP-GS (Wan et al. 2024): Gaussians grouped into superpoints that move rigidly.

- M superpoints (default 300), placed by farthest-point sampling over the canonical means when
  the deformation first runs (the end of the static warm-up).
- Each Gaussian keeps learned association logits over all M superpoints (`spgs_assoc`, [N, M], in
  the parameter dict so densification keeps rows aligned). Its soft assignment is the softmax of
  the logits of its K = 5 nearest superpoints; it moves with the hard argmax.
- Superpoint centres are the soft-assignment-weighted means of the canonical means, refreshed
  every training step (no gradient).
- An MLP of (PE(centre), PE(t)) gives each superpoint a translation and an so(3) rotation
  vector: x_t = exp(w) x + d (about the world origin, as published), q_t = q(w) * q.
- Property-reconstruction losses tie the hard and soft assignments (see `regularizers`).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import torch
from torch import Tensor, nn

from ..ops import rows_of, scatter_mean, take_rows
from ..knn import searcher
from ..context import StepContext
from .base import (BaselineConfig, Deformation, Deltas, apply_post_activation, flag_value, mlp_kwargs, set_flag,
                   stage_start)
from .deform import DeformMLP
from .registry import register_baseline
from ..geometry import farthest_point_sampling, quat_multiply, so3_exp, so3_exp_quat

ASSOC_KEY = "spgs_assoc"


@dataclass
class SpgsConfig:
    """SP-GS superpoints, `baseline.spgs.*` (docs/baselines.md)."""

    num_superpoints: int = 300
    knn_k: int = 5
    # the searches of every step (Gaussians to superpoints): "cdist" or "direct" (stdr.knn; as scgs)
    knn: str = "cdist"
    assoc_lr: float = 1e-3          # constant, as published (its schedule never applies)
    lambda_xyz: float = 1e-3        # property-reconstruction weights
    lambda_rot: float = 100.0
    lambda_off: float = 100.0


@dataclass
class SpgsBaselineConfig(BaselineConfig):
    """SP-GS (Wan et al. 2024), `baseline=spgs`: superpoints moving rigidly (SO(3) + translation);
    PE(t) with 6 frequencies and no time net, lr 1e-3. Sizes:
    stdr/configs/budget_baseline/spgs_<budget>.yaml."""

    name: str = "spgs"
    time_net: bool = False
    lr_init: float = 1.0e-3
    spgs: SpgsConfig = field(default_factory=SpgsConfig)


class SuperpointDeformation(Deformation):
    # STDR's separated field feeds its network; the superpoints' conditioning blends every Gaussian's
    capabilities = frozenset({"conditioning", "mixes_rows"})

    apply_rule = staticmethod(apply_post_activation)

    @classmethod
    def config_kwargs(cls, b, cond_dim=0, train_times=None, seed=0, schedule=None) -> dict:
        c = b.spgs
        return dict(mlp_kwargs(b, cond_dim), num_superpoints=c.num_superpoints, knn_k=c.knn_k,
                    start_step=stage_start(b, schedule), assoc_lr=c.assoc_lr,
                    weights={"xyz": c.lambda_xyz, "rot": c.lambda_rot, "off": c.lambda_off}, seed=seed,
                    knn=c.knn, knn_compiled=b.knn_compiled)

    def __init__(self, num_superpoints: int = 300, knn_k: int = 5, start_step: int = 3000, depth: int = 8,
                 width: int = 256, skips=(4,), xyz_freqs: int = 10, t_freqs: int = 6, cond_dim: int = 0,
                 head_init_std: Optional[float] = None, assoc_lr: float = 1e-3,
                 weights: Optional[dict] = None, seed: int = 0, knn: str = "cdist",
                 knn_compiled: Optional[bool] = None):
        super().__init__()
        self.search = searcher("baseline.spgs.knn", knn, knn_compiled)  # the per-step nearest-neighbour search
        self.m, self.k, self.start_step = num_superpoints, knn_k, start_step
        self.cond_dim, self.assoc_lr = cond_dim, assoc_lr
        self.weights = dict(weights or {"xyz": 1e-3, "rot": 100.0, "off": 100.0})
        self.seed = seed
        self.net = DeformMLP(depth, width, skips, xyz_freqs, t_freqs, time_net=False, cond_dim=cond_dim,
                             heads=False)
        self.head_t = nn.Linear(width, 3)
        self.head_w = nn.Linear(width, 3)
        if head_init_std is not None:
            for h in (self.head_t, self.head_w):
                nn.init.normal_(h.weight, std=head_init_std)
                nn.init.zeros_(h.bias)
        self.register_buffer("centers", torch.zeros(num_superpoints, 3))
        self.register_buffer("ready", torch.zeros((), dtype=torch.bool))
        self._last: dict = {}

    # -------------------------------------------------------------- per-Gaussian state
    def compile_network(self) -> None:
        """baseline.compile=true: the MLP trunk through torch.compile (DeformMLP.compile_network)."""
        self.net.compile_network()

    def init_gaussians(self, params) -> None:
        """The association logits [N, num_superpoints] (lr baseline.spgs.assoc_lr), where absent."""
        if ASSOC_KEY not in params:
            n = params["means"].shape[0]
            params[ASSOC_KEY] = nn.Parameter(torch.zeros(n, self.m, device=params["means"].device))

    def param_groups(self) -> list[dict]:
        return [*super().param_groups(), {"key": ASSOC_KEY, "lr": self.assoc_lr}]

    @classmethod
    def stages(cls, b):
        return [(int(b.warmup), "baseline.warmup", "SP-GS: superpoints placed by FPS over the canonical means")], []

    def initialize(self, params) -> None:
        """Superpoints by FPS over the canonical means; logits 0.1 + 0.9 one-hot(nearest)."""
        x = params["means"].detach()
        if x.shape[0] < self.m:
            raise ValueError(f"SP-GS needs at least {self.m} Gaussians for its superpoints, has {x.shape[0]}; "
                             "lower baseline.spgs.num_superpoints")
        idx = farthest_point_sampling(x, self.m, torch.Generator().manual_seed(self.seed))
        self.centers.copy_(x[idx])
        _, closest = self.search(x, self.centers, 1)
        with torch.no_grad():
            a = params[ASSOC_KEY]
            a.fill_(0.1)
            a.scatter_(1, closest, 1.0)
        set_flag(self, "ready", True)

    def compact_columns(self, params) -> dict[str, Tensor]:
        """The association logits a trained model's renders read: each Gaussian's K nearest
        superpoints (`assignment`: the canonical means and the centres no longer move), K of the
        baseline.spgs.num_superpoints columns. Before the superpoints are placed, every column."""
        if not flag_value(self, "ready"):
            return {}
        with torch.no_grad():
            _, idx = self.search(params["means"].detach(), self.centers, min(self.k, self.m))
        return {ASSOC_KEY: idx}

    def assignment(self, params) -> tuple[Tensor, Tensor, Tensor]:
        """(knn indices [N, K], soft weights [N, K], hard superpoint [N]) for the current centres."""
        x = params["means"].detach()
        with torch.no_grad():
            _, idx = self.search(x, self.centers, min(self.k, self.m))
        G = torch.softmax(params[ASSOC_KEY].gather(1, idx), -1)
        hard = idx.gather(1, G.detach().argmax(-1, keepdim=True))[:, 0]
        return idx, G, hard

    def before_step(self, ctx: StepContext) -> None:
        params, step = ctx.params, ctx.step
        if step < self.start_step:
            return
        if not flag_value(self, "ready"):
            self.initialize(params)
            return
        with torch.no_grad():  # centres: soft-assignment-weighted means of the canonical means
            idx, G, _ = self.assignment(params)
            x = params["means"].detach()
            new, w = scatter_mean(x[:, None, :].expand(-1, idx.shape[1], -1), idx, G, self.m)
            keep = w > 1e-8  # (where, not boolean indexing: no host sync)
            self.centers.copy_(torch.where(keep[:, None], new, self.centers))

    # -------------------------------------------------------------- deformation
    def superpoint_motion(self, t: float, cond_sp: Optional[Tensor] = None) -> tuple[Tensor, Tensor]:
        """(translations [M, 3], rotation vectors [M, 3]) at time t."""
        h = self.net.trunk(self.centers, t, cond_sp)
        return self.head_t(h), self.head_w(h)

    def forward(self, params, t: float, cond: Optional[Tensor] = None) -> Deltas:
        return self.forward_rows(params, t, cond, None)

    def forward_rows(self, params, t: float, cond: Optional[Tensor], rows: Optional[Tensor]) -> Deltas:
        """Deltas of the Gaussians `rows` [M] (all when None). The assignment runs on every row:
        the superpoints' conditioning and the property-reconstruction regularizer use all of
        them; only the per-Gaussian transform is restricted."""
        if not flag_value(self, "ready"):
            raise RuntimeError("SP-GS superpoints are not initialized (the training loop does this at "
                               "the end of the static warm-up)")
        idx, G, hard = self.assignment(params)
        cond_sp = None
        if self.cond_dim:
            if cond is None:
                raise ValueError("this deformation was built with cond_dim > 0 and needs cond")
            cond_sp, _ = scatter_mean(cond[:, None, :].expand(-1, idx.shape[1], -1), idx, G.detach(), self.m)
        d, w = self.superpoint_motion(t, cond_sp)
        self._last = {"idx": idx, "G": G, "hard": hard, "d": d, "w": w}
        hard = rows_of(hard, rows)
        x = rows_of(params["means"], rows)
        R = take_rows(so3_exp(w), hard)  # [N, 3, 3]
        x_t = (R @ x[..., None])[..., 0] + take_rows(d, hard)
        q = rows_of(params["quats"], rows)
        qn = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        q_t = quat_multiply(take_rows(so3_exp_quat(w), hard), qn)
        # expressed as post-activation deltas so that every baseline shares the apply rule
        return Deltas(means=x_t - x, quats=q_t - qn)

    def regularizers(self, ctx: StepContext) -> dict[str, Tensor]:
        """Property reconstruction (SP-GS): a Gaussian's position, and its superpoint's rotation
        and translation, should equal their soft-assignment blends over its K superpoints."""
        if not self._last:
            return {}
        idx, G, hard, d, w = (self._last[k] for k in ("idx", "G", "hard", "d", "w"))
        x = ctx.params["means"].detach()
        blend = lambda v: (G[..., None] * take_rows(v, idx)).sum(1)  # noqa: E731
        terms = {"xyz": (x - blend(self.centers)).square().sum(-1).mean(),
                 "rot": (take_rows(w, hard) - blend(w)).square().sum(-1).mean(),
                 "off": (take_rows(d, hard) - blend(d)).square().sum(-1).mean()}
        self._last = {}
        return {f"spgs_re_{k}": self.weights[k] * v for k, v in terms.items() if self.weights.get(k, 0) > 0}


register_baseline("spgs", SuperpointDeformation, SpgsBaselineConfig, in_grids=True)
