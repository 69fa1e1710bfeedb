"""STDR's separated deformation field.

Input: p_i = softmax_t(m_i) [N, K] (optionally with PE(x_i)). Two shared fully connected layers,
then two branches, each Linear-BatchNorm-ReLU-Dropout-Linear:
  - temporal branch ending in tanh: a temporal-identity feature z_i [N, temporal_dim];
  - motion branch ending in sigmoid: the probability d_i [N, 1] that the Gaussian is dynamic.
The conditioning handed to the deformation network is cat(z_i, d_i) [N, temporal_dim + 1].
BatchNorm normalizes over the Gaussians of one step; eval mode (running statistics, no
dropout) is used for every render outside a training step.

`precision` (stdr.field_precision): "fp32", or "bf16": the matrix products in bfloat16 (autocast,
fp32 accumulation), batch norm, activations and outputs in fp32, and in training each branch's
BatchNorm-ReLU-Dropout as one function (stdr.ops.norm_relu_dropout: a hand-written backward, a
third of the dropout's random draws). The same function; other rounding and other dropout draws.
"""
from __future__ import annotations

import torch
from torch import Tensor, nn

from ...ops import BatchNorm1d, Sigmoid, norm_relu_dropout

#: the field's arithmetic (stdr.field_precision, "auto" resolved)
FIELD_PRECISIONS = ("fp32", "bf16")


class SeparatedField(nn.Module):
    def __init__(self, in_dim: int, width: int = 64, temporal_dim: int = 16, dropout: float = 0.1,
                 precision: str = "fp32"):
        super().__init__()
        if precision not in FIELD_PRECISIONS:
            raise ValueError(f"stdr.field_precision={precision!r}: use one of {('auto', *FIELD_PRECISIONS)}")
        self.in_dim, self.temporal_dim, self.precision = in_dim, temporal_dim, precision
        self.shared = nn.Sequential(nn.Linear(in_dim, width), nn.ReLU(), nn.Linear(width, width), nn.ReLU())

        def branch(out_dim: int, act: nn.Module) -> nn.Sequential:
            return nn.Sequential(nn.Linear(width, width), BatchNorm1d(width), nn.ReLU(),
                                 nn.Dropout(dropout), nn.Linear(width, out_dim), act)
        self.temporal = branch(temporal_dim, nn.Tanh())
        self.motion = branch(1, Sigmoid())

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """x [N, in_dim] -> (z [N, temporal_dim] in (-1, 1), d [N, 1] in (0, 1)), in fp32."""
        if x.shape[0] == 1 and self.training:  # BatchNorm needs two rows to normalize in training
            x = x.expand(2, -1)
            z, d = self.forward(x)
            return z[:1], d[:1]
        if self.precision == "bf16":
            return self._forward_bf16(x)
        h = self.shared(x)
        return self.temporal(h), self.motion(h)

    def _forward_bf16(self, x: Tensor) -> tuple[Tensor, Tensor]:
        with torch.autocast(device_type=x.device.type, dtype=torch.bfloat16):
            h = self.shared(x)

        def branch(seq: nn.Sequential) -> Tensor:
            lin1, bn, _relu, drop, lin2, act = seq
            with torch.autocast(device_type=x.device.type, dtype=torch.bfloat16):
                a = lin1(h)
            a = norm_relu_dropout(a.float(), bn, drop.p)
            with torch.autocast(device_type=x.device.type, dtype=torch.bfloat16):
                o = lin2(a)
            return act(o.float())
        return branch(self.temporal), branch(self.motion)
