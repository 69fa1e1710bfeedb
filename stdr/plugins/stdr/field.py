"""STDR's separated deformation field.

Input: p_i = softmax_t(m_i) [N, K] (optionally with PE(x_i)). Two shared fully connected layers,
then two branches, each Linear-BatchNorm-ReLU-Dropout-Linear:
  - temporal branch ending in tanh: a temporal-identity feature z_i [N, temporal_dim];
  - motion branch ending in sigmoid: the probability d_i [N, 1] that the Gaussian is dynamic.
The conditioning handed to the deformation network is cat(z_i, d_i) [N, temporal_dim + 1].
BatchNorm normalizes over the Gaussians of one step; eval mode (running statistics, no
dropout) is used for every render outside a training step.
"""
from __future__ import annotations

from torch import Tensor, nn

from ...ops import BatchNorm1d, Sigmoid


class SeparatedField(nn.Module):
    def __init__(self, in_dim: int, width: int = 64, temporal_dim: int = 16, dropout: float = 0.1):
        super().__init__()
        self.in_dim, self.temporal_dim = in_dim, temporal_dim
        self.shared = nn.Sequential(nn.Linear(in_dim, width), nn.ReLU(), nn.Linear(width, width), nn.ReLU())

        def branch(out_dim: int, act: nn.Module) -> nn.Sequential:
            return nn.Sequential(nn.Linear(width, width), BatchNorm1d(width), nn.ReLU(),
                                 nn.Dropout(dropout), nn.Linear(width, out_dim), act)
        self.temporal = branch(temporal_dim, nn.Tanh())
        self.motion = branch(1, Sigmoid())

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """x [N, in_dim] -> (z [N, temporal_dim] in (-1, 1), d [N, 1] in (0, 1))."""
        if x.shape[0] == 1 and self.training:  # BatchNorm needs two rows to normalize in training
            x = x.expand(2, -1)
            z, d = self.forward(x)
            return z[:1], d[:1]
        h = self.shared(x)
        return self.temporal(h), self.motion(h)
