"""Deformable 3DGS (Yang et al. 2024): an MLP of (PE(xyz), PE(t)) giving dxyz, dq, ds."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from ..encoding import positional_encoding, positional_encoding_dim
from .base import BaselineConfig, Deformation, Deltas, apply_post_activation, mlp_kwargs
from .registry import register_baseline


@dataclass
class DeformConfig(BaselineConfig):
    """Deformable 3DGS (Yang et al. 2024), `baseline=deform`: the common keys at their published
    values (8x256 MLP, skip after layer 4, PE 10/6, a time net for synthetic data; real data uses
    t_freqs 10 without it). Budget sizes: stdr/configs/budget_baseline/deform_<budget>.yaml."""

    name: str = "deform"


class DeformMLP(Deformation):
    """depth x width ReLU MLP with a skip (input re-concatenated) after layer `skip`.

    Input: PE(xyz, xyz_freqs) and either time_net(PE(t, t_freqs)) (synthetic data: a
    Linear(., width)-ReLU-Linear(width, time_out) net) or raw PE(t) (real data), plus an
    optional conditioning vector per Gaussian. Canonical xyz is detached: no gradient reaches
    the Gaussians' positions through the network. Heads: dxyz (3), dq (4), ds (3).

    head_init_std: None keeps PyTorch's default init (the published code); its heads then start
    with random deltas of ~0.3 scene units. A small value (1e-5) starts the deformation at
    identity, which short schedules need.
    """

    capabilities = frozenset({"conditioning"})  # STDR's separated field feeds its network
    apply_rule = staticmethod(apply_post_activation)

    @classmethod
    def config_kwargs(cls, b, cond_dim=0, train_times=None, seed=0, schedule=None) -> dict:
        return dict(mlp_kwargs(b, cond_dim), time_net=b.time_net, time_out=b.time_out)

    def __init__(self, depth: int = 8, width: int = 256, skips: Sequence[int] = (4,),
                 xyz_freqs: int = 10, t_freqs: int = 6, time_net: bool = True, time_out: int = 30,
                 cond_dim: int = 0, head_init_std: float | None = None, heads: bool = True):
        super().__init__()
        self.xyz_freqs, self.t_freqs, self.cond_dim = xyz_freqs, t_freqs, cond_dim
        self.skips = tuple(skips)
        xyz_dim = positional_encoding_dim(3, xyz_freqs)
        t_dim = positional_encoding_dim(1, t_freqs)
        self.time_net = nn.Sequential(nn.Linear(t_dim, width), nn.ReLU(), nn.Linear(width, time_out)) \
            if time_net else None
        in_dim = xyz_dim + (time_out if time_net else t_dim) + cond_dim
        layers = []
        for i in range(depth):
            d_in = in_dim if i == 0 else width + (in_dim if (i - 1) in self.skips else 0)
            layers.append(nn.Linear(d_in, width))
        self.layers = nn.ModuleList(layers)
        self.width = width
        if cond_dim:  # cond inputs start at zero weight: adding them later does not change the output
            with torch.no_grad():
                for i, layer in enumerate(self.layers):
                    if i == 0 or (i - 1) in self.skips:
                        layer.weight[:, -cond_dim:] = 0.0
        if not heads:  # a trunk for modules with their own heads (SP-GS, SC-GS)
            return
        self.head_xyz = nn.Linear(width, 3)
        self.head_rot = nn.Linear(width, 4)
        self.head_scale = nn.Linear(width, 3)
        if head_init_std is not None:  # near-identity start (as SC-GS); None = PyTorch default init
            for head in (self.head_xyz, self.head_rot, self.head_scale):
                nn.init.normal_(head.weight, std=head_init_std)
                nn.init.zeros_(head.bias)

    def forward(self, params, t: float, cond: Optional[Tensor] = None) -> Deltas:
        h = self.trunk(params["means"].detach(), t, cond)
        # the three heads as one [N, 10] product (three skinny ones cost more than one)
        heads = (self.head_xyz, self.head_rot, self.head_scale)
        out = F.linear(h, torch.cat([m.weight for m in heads]), torch.cat([m.bias for m in heads]))
        return Deltas(means=out[:, :3], quats=out[:, 3:7], scales=out[:, 7:])

    def trunk(self, xyz: Tensor, t: float, cond: Optional[Tensor] = None) -> Tensor:
        """Hidden features [N, width] at points xyz [N, 3] and time t (the baselines that query
        the network at control nodes or superpoints call this directly).

        The layers that read the input (the first, and the one after each skip) see it as three
        column blocks of their weight, [PE(xyz) | time embedding | cond], and each block is
        multiplied separately: the time embedding is one row for all Gaussians, so its product
        is a [1, width] bias instead of an [N, time_out] block of every row, and no [N, in_dim]
        input is concatenated. The same function as one Linear on the concatenated input (the
        weights are unchanged; only float rounding differs), and with xyz detached autograd
        computes no gradient for the PE block (about a fifth of the backward's products)."""
        if self.cond_dim and cond is None:
            raise ValueError("this deformation network was built with cond_dim > 0 and needs cond")
        t_in = torch.full((1, 1), float(t), dtype=xyz.dtype, device=xyz.device)  # a tensor: compiled code
        return (self._compiled or self._trunk)(xyz, t_in, cond)                # is not specialized on t

    #: the trunk through torch.compile (baseline.compile; `compile_network`), or None: eager
    _compiled = None

    def compile_network(self) -> None:
        """Run the trunk through torch.compile (inductor; shapes dynamic, so densification does not
        recompile it). baseline.compile=true; off by default (docs/performance.md)."""
        self._compiled = torch.compile(self._trunk, dynamic=True)

    def _trunk(self, xyz: Tensor, t_in: Tensor, cond: Optional[Tensor]) -> Tensor:
        """`trunk` with the time as a [1, 1] tensor (what torch.compile compiles)."""
        t_emb = positional_encoding(t_in, self.t_freqs)  # [1, T]
        if self.time_net is not None:
            t_emb = self.time_net(t_emb)
        pe = positional_encoding(xyz, self.xyz_freqs)  # [N, P]
        P, T = pe.shape[1], t_emb.shape[1]

        def read_input(layer: nn.Linear, h: Optional[Tensor]) -> Tensor:
            w = layer.weight  # [width, (width +) P + T + cond_dim]
            k = 0 if h is None else h.shape[1]
            row = F.linear(t_emb, w[:, k + P:k + P + T], layer.bias)  # [1, width]
            out = F.linear(pe, w[:, k:k + P]) + row
            if h is not None:
                out = out + F.linear(h, w[:, :k])
            if self.cond_dim:
                out = out + F.linear(cond, w[:, k + P + T:])
            return out

        h: Optional[Tensor] = None
        for i, layer in enumerate(self.layers):
            reads_input = i == 0 or (i - 1) in self.skips
            z = read_input(layer, None if i == 0 else h) if reads_input else layer(h)
            h = torch.relu_(z)  # z is a fresh sum: nothing else reads it
        return h


# bf16 on a CPU with bf16 matrix instructions passed its checks: its step 1.66x faster, mean val
# delta PSNR +0.050 / +0.073 dB (plain / +STDR) at budget=cpu over 8 pairs and -0.069 / +0.271 at
# cpu_long over 2 (research/measurements/precision_val; docs/performance.md, "bf16 by default")
register_baseline("deform", DeformMLP, DeformConfig, in_grids=True, bf16_default=True)
