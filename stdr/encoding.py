"""Input encodings shared by deformation networks and plug-ins."""
from __future__ import annotations

import torch
from torch import Tensor

_FREQS: dict = {}  # (n_freqs, dtype, device) -> the bands, made once (two operators fewer a call)


def _bands(n_freqs: int, dtype, device) -> Tensor:
    key = (n_freqs, dtype, device)
    if key not in _FREQS:
        _FREQS[key] = 2.0 ** torch.arange(n_freqs, dtype=dtype, device=device)
    return _FREQS[key]


def positional_encoding(x: Tensor, n_freqs: int) -> Tensor:
    """NeRF encoding with the input included: [.., D] -> [.., D (1 + 2 n_freqs)].

    Frequency bands 2^0 .. 2^(n_freqs-1), sin then cos per band.
    """
    if n_freqs == 0:
        return x
    freqs = _bands(n_freqs, x.dtype, x.device)
    xf = x[..., None, :] * freqs[:, None]  # [.., L, D]
    return torch.cat([x, torch.stack([xf.sin(), xf.cos()], -2).flatten(-3)], -1)


def positional_encoding_dim(d: int, n_freqs: int) -> int:
    """Width of `positional_encoding` of a D-vector."""
    return d * (1 + 2 * n_freqs)
