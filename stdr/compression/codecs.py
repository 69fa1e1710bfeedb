"""Codecs for a model's tensors in the compact file (stdr.compression.file): stateless functions
with shape contracts, each an `encode` to a dict of tensors (loadable with weights_only=True) and a
`decode` back to a float32 tensor of the original shape.

| codec | stores | decode error |
|---|---|---|
| `raw` | the tensor as it is, any dtype (an integer tensor such as STDR's 8-bit mask, float64 time knots) | exact |
| `f32` | float32 | exact for float32 |
| `f16` | float16 | \\|x\\| 2^-11 relative in float16's normal range (\\|x\\| >= 6.1e-5), 2^-25 absolute below it; values beyond +-65504 are refused |
| `q8` | uint8 per element, with a float32 (lo, hi) per column of the last dimension (one column for a vector) | at most (hi - lo) / 510 per element, half a quantization step |
| `q16` | as `q8` with 65 536 levels (int16) | at most (hi - lo) / 131 070 per element (positions: ~1e-5 of the scene's extent), plus float32's rounding |
| `cols` | the K given columns of each row [N, K] (values in float32, their indices in int16/int32) and a fill | exact on those columns; every other column reads `fill` |
| `q4` | 4 bits per element (two a byte), a float32 (lo, hi) per column as `q8` | at most (hi - lo) / 30 per element |
| `vq:C` | each row [N, ...] replaced by the nearest of C codewords (k-means on the rows, float16 codebook [C, D]); an int16 index a row | each row reads its codeword: the k-means error, plus float16's rounding of the codeword; exact for a tensor of at most C distinct rows |
| `lowrank:R` | a 2-D [N, K] as its column means plus a rank-R product A [N, R] (float16) B [R, K] (float32) | the truncated SVD's error (the best rank R in the Frobenius norm), plus A's float16 rounding; exact (to that rounding) for a matrix of rank <= R after centring |

`cols` is for a per-Gaussian table that rendering reads only at some columns of each row (SP-GS's
association logits: a row's K nearest superpoints, fixed once training ends).
"""
from __future__ import annotations

import torch
from torch import Tensor

CODECS = ("raw", "f32", "f16", "q8", "q16", "cols", "q4", "vq", "lowrank")
#: codecs that take a size after a colon ("vq:1024", "lowrank:8")
SIZED = {"vq": "C codewords", "lowrank": "rank R"}
#: the uniform quantizers' top level (levels 0..L, a range per column)
LEVELS = {"q8": 255.0, "q16": 65535.0, "q4": 15.0}
KMEANS_ITERS = 20
F16_MAX = 65504.0


def _columns(shape) -> int:
    """q8's and q16's columns: the last dimension of a tensor of two or more, else one column."""
    return int(shape[-1]) if len(shape) >= 2 else 1


def parse(codec: str) -> tuple[str, int | None]:
    """"vq:1024" -> ("vq", 1024); "q8" -> ("q8", None). An unknown name or a missing / stray size is
    a ValueError naming the codecs."""
    name, _, arg = str(codec).partition(":")
    if name not in CODECS:
        raise ValueError(f"unknown codec {codec!r}: one of {CODECS} (sized: vq:C, lowrank:R)")
    if name in SIZED:
        if not arg.isdigit() or int(arg) < 1:
            raise ValueError(f"codec {codec!r}: write {name}:<{SIZED[name]}>, a positive integer (e.g. {name}:8)")
        return name, int(arg)
    if arg:
        raise ValueError(f"codec {codec!r}: {name} takes no size")
    return name, None


def nearest(rows: Tensor, centres: Tensor, chunk: int = 8192) -> Tensor:
    """Index [N] of the centre [k, D] nearest each row [N, D] (Euclidean)."""
    return torch.cat([torch.cdist(rows[i:i + chunk], centres).argmin(1) for i in range(0, rows.shape[0], chunk)])


def kmeans(rows: Tensor, k: int, iters: int = KMEANS_ITERS, seed: int = 0, chunk: int = 8192) -> tuple[Tensor, Tensor]:
    """Lloyd's k-means of rows [N, D] (float32) into k <= N centres [k, D], started from k distinct
    rows drawn by `seed`; a centre left without rows keeps its place. Returns (centres, labels [N])."""
    n = rows.shape[0]
    g = torch.Generator().manual_seed(seed)
    uniq = torch.unique(rows, dim=0)
    k = min(k, uniq.shape[0])
    centres = uniq[torch.randperm(uniq.shape[0], generator=g)[:k]].clone()
    labels = torch.zeros(n, dtype=torch.long)
    for it in range(iters + 1):
        labels = nearest(rows, centres, chunk)
        if it == iters:
            break
        sums = torch.zeros_like(centres).index_add_(0, labels, rows)
        counts = torch.bincount(labels, minlength=k).unsqueeze(1).to(rows.dtype)
        centres = torch.where(counts > 0, sums / counts.clamp(min=1), centres)
    return centres, labels


def _pack4(q: Tensor) -> Tensor:
    flat = q.reshape(-1).to(torch.uint8)
    if flat.numel() % 2:
        flat = torch.cat([flat, flat.new_zeros(1)])
    return flat[0::2] | (flat[1::2] << 4)


def _unpack4(packed: Tensor, numel: int) -> Tensor:
    out = torch.stack([packed & 15, packed >> 4], 1).reshape(-1)
    return out[:numel]


def levels_of(flat: Tensor, lo: Tensor, hi: Tensor, levels: float) -> Tensor:
    """The quantization levels (float, 0..levels) of flat [M, K] in the ranges lo, hi [K]: the
    nearest level, values outside the range clamped to its ends; a column with lo == hi reads 0."""
    step = (hi - lo) / levels
    return torch.where(step > 0, torch.round((flat - lo) / torch.where(step > 0, step, 1.0)), 0.0).clamp(0, levels)


def dequantized(x: Tensor, codec: str, lo: Tensor, hi: Tensor) -> Tensor:
    """What q8 / q16 / q4 in the range lo, hi [K] per column read back for x [..., K], computed on
    x's device: decode(encode_in_range(x, codec, lo, hi)) without leaving it."""
    levels = LEVELS[codec]
    flat = x.reshape(-1, _columns(x.shape))
    return (lo + levels_of(flat, lo, hi, levels) * ((hi - lo) / levels)).reshape(x.shape)


def encode_in_range(x: Tensor, codec: str, lo: Tensor, hi: Tensor) -> dict:
    """x [...] in q8 / q16 / q4 with the given range per column (lo, hi [K], K = the last dimension;
    one for a vector) instead of the tensor's own min and max: values outside read back as the
    range's ends. `encode` is this with the tensor's range; a quantization-aware fine-tune
    (stdr.compact.finetune) keeps the range fixed while the values move."""
    levels = LEVELS[codec]
    flat = x.detach().cpu().float().reshape(-1, _columns(x.shape))
    lo, hi = lo.detach().cpu().float(), hi.detach().cpu().float()
    q = levels_of(flat, lo, hi, levels)
    if codec == "q4":
        return {"codec": "q4", "data": _pack4(q), "shape": torch.tensor(list(x.shape), dtype=torch.int64),
                "lo": lo, "hi": hi}
    # q16 in int16 (offset by 32 768: torch's uint16 lacks arithmetic)
    data = q.to(torch.uint8) if codec == "q8" else (q.to(torch.int32) - 32768).to(torch.int16)
    return {"codec": codec, "data": data.reshape(x.shape), "lo": lo, "hi": hi}


def encode(x: Tensor, codec: str, cols: Tensor | None = None) -> dict:
    """x [...] -> the codec's dict (`raw`: any dtype; the others: float). `cols` [N, K] int: the
    columns `cols` keeps of x [N, M]. Sized codecs: "vq:C" (x [N, ...]: rows), "lowrank:R" (x [N, K])."""
    codec, size = parse(codec)
    x = x.detach().cpu()
    if codec == "raw":
        return {"codec": "raw", "data": x.clone()}
    if codec == "f32":
        if not x.is_floating_point():
            raise ValueError(f"codec 'f32' encodes float tensors, got {x.dtype}; use 'raw'")
        return {"codec": "f32", "data": x.float().clone()}
    if not x.is_floating_point():
        raise ValueError(f"codec {codec!r} encodes float tensors, got {x.dtype}")
    if not torch.isfinite(x).all():
        raise ValueError(f"codec {codec!r}: the tensor has non-finite values")
    if codec == "f16":
        if x.numel() and float(x.abs().max()) > F16_MAX:
            raise ValueError(f"codec 'f16': values up to {float(x.abs().max()):.4g} exceed float16's range "
                             f"({F16_MAX}); use 'f32' or 'q8' for this tensor")
        return {"codec": "f16", "data": x.half()}
    if codec in LEVELS:
        flat = x.float().reshape(-1, _columns(x.shape))
        lo = flat.min(0).values if flat.shape[0] else torch.zeros(flat.shape[1])
        hi = flat.max(0).values if flat.shape[0] else torch.zeros(flat.shape[1])
        return encode_in_range(x, codec, lo, hi)
    if codec == "vq":
        if x.dim() < 1 or x.shape[0] == 0:
            raise ValueError("codec 'vq' needs rows: x [N, ...] with N >= 1")
        if size > 32767:
            raise ValueError(f"codec 'vq:{size}': at most 32767 codewords (an int16 index a row)")
        rows = x.float().reshape(x.shape[0], -1)
        centres, _ = kmeans(rows, size)
        if float(centres.abs().max()) > F16_MAX:
            raise ValueError("codec 'vq': codewords exceed float16's range; use q8 for this tensor")
        book = centres.half()
        labels = nearest(rows, book.float())  # against the stored (float16) codewords
        return {"codec": "vq", "data": labels.to(torch.int16), "codebook": book,
                "shape": torch.tensor(list(x.shape), dtype=torch.int64)}
    if codec == "lowrank":
        if x.dim() != 2:
            raise ValueError(f"codec 'lowrank:{size}' needs a 2-D tensor [N, K], got shape {tuple(x.shape)}")
        xf = x.double()
        mean = xf.mean(0)
        u, sv, vh = torch.linalg.svd(xf - mean, full_matrices=False)
        r = min(size, sv.numel())
        a = (u[:, :r] * sv[:r]).float()
        if a.numel() and float(a.abs().max()) > F16_MAX:
            raise ValueError(f"codec 'lowrank:{size}': factors exceed float16's range; use q8 for this tensor")
        return {"codec": "lowrank", "data": a.half(), "basis": vh[:r].float(), "mean": mean.float()}
    if codec == "cols":
        if cols is None or x.dim() != 2 or cols.dim() != 2 or cols.shape[0] != x.shape[0]:
            raise ValueError("codec 'cols' needs x [N, M] and cols [N, K]")
        m = x.shape[1]
        if cols.numel() and (int(cols.min()) < 0 or int(cols.max()) >= m):
            raise ValueError(f"codec 'cols': column indices outside [0, {m})")
        vals = x.float().gather(1, cols.long())
        fill = (float(vals.min()) if vals.numel() else 0.0) - 30.0  # a logit that softmax reads as 0
        idx = cols.to(torch.int16 if m <= 32767 else torch.int32)
        return {"codec": "cols", "data": vals, "cols": idx, "width": torch.tensor(m), "fill": torch.tensor(fill)}
    raise ValueError(f"unknown codec {codec!r}: one of {CODECS}")


def decode(e: dict) -> Tensor:
    """The codec's dict -> the tensor (float32; `raw`: as it was stored)."""
    codec = e.get("codec")
    if codec == "raw":
        return e["data"].clone()
    if codec == "f32":
        return e["data"].float()
    if codec == "f16":
        return e["data"].float()
    if codec == "q4":
        shape = [int(v) for v in e["shape"]]
        numel = 1
        for v in shape:
            numel *= v
        q = _unpack4(e["data"], numel).float().reshape(-1, _columns(shape))
        return (e["lo"] + q * ((e["hi"] - e["lo"]) / 15.0)).reshape(shape)
    if codec == "vq":
        return e["codebook"].float()[e["data"].long()].reshape([int(v) for v in e["shape"]])
    if codec == "lowrank":
        return e["data"].float() @ e["basis"] + e["mean"]
    if codec in ("q8", "q16"):
        step = (e["hi"] - e["lo"]) / (255.0 if codec == "q8" else 65535.0)
        q = e["data"]
        qf = q.float() if codec == "q8" else q.to(torch.int32).add(32768).float()
        return (e["lo"] + qf.reshape(-1, _columns(q.shape)) * step).reshape(q.shape)
    if codec == "cols":
        vals, idx = e["data"], e["cols"].long()
        out = torch.full((vals.shape[0], int(e["width"])), float(e["fill"]))
        return out.scatter_(1, idx, vals.float())
    raise ValueError(f"unknown codec {codec!r} in the compact file: one of {CODECS} (a file from a newer stdr?)")


def nbytes(e) -> int:
    """Bytes of an encoded dict's tensors (or of a tensor / nested dict)."""
    if isinstance(e, Tensor):
        return e.numel() * e.element_size()
    if isinstance(e, dict):
        return sum(nbytes(v) for v in e.values())
    if isinstance(e, (list, tuple)):
        return sum(nbytes(v) for v in e)
    return 0
