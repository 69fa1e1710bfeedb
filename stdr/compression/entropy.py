"""Entropy coding of the compact file's streams with Zstandard (the `zstandard` package), lossless.

After the codecs (stdr.compression.codecs) have turned every tensor into its streams (8-bit codes,
codebook indices, float16 values, grids), `pack_tree` replaces each stream by its Zstandard frame
when that is smaller, and `unpack_tree` restores the exact tensors. Two reversible filters run
before the coder, each kept only where it makes the frame smaller:
* delta: an integer stream of two or more dimensions is stored as the differences between
  consecutive rows of its first dimension (modulo its width). A quantized grid plane is smooth, so
  its differences are small numbers the coder packs tightly.
* shuffle: a stream of 2- or 4-byte elements is byte-shuffled (all first bytes, then all second
  bytes, ...), which groups a float array's slowly varying sign-and-exponent bytes apart from its
  noisy low mantissa bytes.

    packed = pack_tree(tree, level=19)     # {..., tensor} -> {..., {ENTROPY: True, "zstd": uint8 [M], ...}}
    tree2 = unpack_tree(packed)            # every tensor bit-identical to tree's

A packed stream is {ENTROPY: True, "zstd": uint8 [M] (the frame), "dtype": str, "shape": int64 [D],
"shuffle": int (the element size it was shuffled by, 1: none), "delta": bool}; `codecs.nbytes` counts its frame
(and its shape).
"""
from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import Tensor

#: a packed stream's dict carries it (no codec's or state dict's key is named so)
ENTROPY = "__zstd__"
LEVEL = 19  # Zstandard's highest standard level: encoding runs once, decoding is as fast at any level
_DTYPES = {str(d): d for d in (torch.uint8, torch.int8, torch.int16, torch.int32, torch.int64, torch.float16,
                               torch.float32, torch.float64, torch.bool)}


def _zstd():
    import zstandard  # imported where a file uses it: training and the GPU path never need it
    return zstandard


def _frame(a: np.ndarray, delta: bool, level: int) -> tuple[bytes, int]:
    """The Zstandard frame of array `a` after its filters, and the shuffle's element size (1: none)."""
    if delta:
        a = a.copy()
        a[1:] = a[1:] - a[:-1]  # wraps modulo the integer width: exact to undo
    size = a.dtype.itemsize
    raw = np.ascontiguousarray(a).view(np.uint8).reshape(-1)
    data = raw.reshape(-1, size).T.tobytes() if size in (2, 4) else raw.tobytes()
    return _zstd().ZstdCompressor(level=level).compress(data), (size if size in (2, 4) else 1)


def pack(t: Tensor, level: int = LEVEL) -> Any:
    """A stream as its Zstandard frame (dict above), or the tensor itself when no frame is smaller
    (a tiny or incompressible stream)."""
    if str(t.dtype) not in _DTYPES or t.numel() == 0:
        return t
    a = t.detach().cpu().contiguous().numpy()
    options = [False] + ([True] if a.ndim >= 2 and a.shape[0] > 1 and np.issubdtype(a.dtype, np.integer) else [])
    frames = [(_frame(a, d, level), d) for d in options]
    (frame, shuffle), delta = min(frames, key=lambda f: len(f[0][0]))
    if len(frame) + 8 * (t.dim() + 1) >= a.nbytes:
        return t
    return {ENTROPY: True, "zstd": torch.frombuffer(bytearray(frame), dtype=torch.uint8), "dtype": str(t.dtype),
            "shape": torch.tensor(list(t.shape), dtype=torch.int64), "shuffle": shuffle, "delta": delta}


def unpack(e: dict) -> Tensor:
    """The exact tensor of a packed stream."""
    dtype = _DTYPES[e["dtype"]]
    shape = [int(v) for v in e["shape"]]
    data = _zstd().ZstdDecompressor().decompress(e["zstd"].numpy().tobytes())
    size = int(e["shuffle"])
    raw = np.frombuffer(data, dtype=np.uint8)
    if size > 1:
        raw = raw.reshape(size, -1).T.reshape(-1)
    a = raw.copy().view(torch.empty(0, dtype=dtype).numpy().dtype).reshape(shape)
    if e.get("delta"):
        a = np.cumsum(a, axis=0, dtype=a.dtype)  # wraps as the differences did
    return torch.from_numpy(a)


def pack_tree(x: Any, level: int = LEVEL) -> Any:
    """Every tensor of a nested dict / list / tuple packed (pack)."""
    if isinstance(x, Tensor):
        return pack(x, level)
    if isinstance(x, dict):
        return {k: pack_tree(v, level) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return type(x)(pack_tree(v, level) for v in x)
    return x


def unpack_tree(x: Any) -> Any:
    """pack_tree undone: every packed stream back to its tensor."""
    if isinstance(x, dict):
        if x.get(ENTROPY):
            return unpack(x)
        return {k: unpack_tree(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return type(x)(unpack_tree(v) for v in x)
    return x
