"""PLY export/import in the standard 3DGS layout, readable by common 3DGS viewers.

Properties: x, y, z, nx, ny, nz, f_dc_0..2, f_rest_0..(3*(K-1)-1), opacity, scale_0..2, rot_0..3.
f_rest is stored channel-major (all R coefficients, then G, then B), as 3DGS does.
Other per-Gaussian attributes (e.g. STDR's mask) are written as extra properties
`<key>_<j>` and read back when present.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from .files import atomic_path
from plyfile import PlyData, PlyElement
from torch import nn

from ..gaussians import GAUSSIAN_KEYS


def save_ply(params, path: str | Path, comments=()) -> None:
    """params in the 3DGS layout at `path` (atomic); `comments`: header comment lines (where the
    model came from: stdr's checkpoint step and SHA-256, the time of an export)."""
    p = {k: v.detach().cpu().float().numpy() for k, v in params.items()}
    N = p["means"].shape[0]
    f_dc = p["sh0"].reshape(N, 3)
    f_rest = p["shN"].transpose(0, 2, 1).reshape(N, -1)  # [N, 3, K-1] -> channel-major
    cols = [("x", p["means"][:, 0]), ("y", p["means"][:, 1]), ("z", p["means"][:, 2]),
            ("nx", np.zeros(N)), ("ny", np.zeros(N)), ("nz", np.zeros(N))]
    cols += [(f"f_dc_{i}", f_dc[:, i]) for i in range(3)]
    cols += [(f"f_rest_{i}", f_rest[:, i]) for i in range(f_rest.shape[1])]
    cols += [("opacity", p["opacities"])]
    cols += [(f"scale_{i}", p["scales"][:, i]) for i in range(3)]
    cols += [(f"rot_{i}", p["quats"][:, i]) for i in range(4)]
    for k, v in p.items():  # extra per-Gaussian attributes
        if k not in GAUSSIAN_KEYS:
            flat = v.reshape(N, -1)
            cols += [(f"{k}_{j}", flat[:, j]) for j in range(flat.shape[1])]
    arr = np.empty(N, dtype=[(name, "f4") for name, _ in cols])
    for name, v in cols:
        arr[name] = v
    with atomic_path(path, "ply") as tmp:  # the previous PLY stays until the new one is complete
        PlyData([PlyElement.describe(arr, "vertex")], comments=list(comments)).write(str(tmp))


def load_ply(path: str | Path, extra_keys: dict[str, tuple] | None = None) -> nn.ParameterDict:
    """Read a 3DGS PLY. `extra_keys` maps extra attribute names to their per-row shapes."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"PLY file not found: {path}")
    v = PlyData.read(str(path))["vertex"]
    names = {p.name for p in v.properties}
    need = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity"] + [f"scale_{i}" for i in range(3)] \
        + [f"rot_{i}" for i in range(4)]
    missing = [n for n in need if n not in names]
    if missing:
        raise ValueError(f"{path}: not a 3DGS PLY, missing properties {missing}")
    col = lambda n: np.asarray(v[n], dtype=np.float32)  # noqa: E731
    N = len(v)
    n_rest = len([n for n in names if n.startswith("f_rest_")])
    if n_rest % 3:
        raise ValueError(f"{path}: {n_rest} f_rest properties is not a multiple of 3")
    rest = np.stack([col(f"f_rest_{i}") for i in range(n_rest)], 1) if n_rest else np.zeros((N, 0), np.float32)
    t = lambda a: nn.Parameter(torch.from_numpy(np.ascontiguousarray(a)))  # noqa: E731
    params = nn.ParameterDict({
        "means": t(np.stack([col("x"), col("y"), col("z")], 1)),
        "scales": t(np.stack([col(f"scale_{i}") for i in range(3)], 1)),
        "quats": t(np.stack([col(f"rot_{i}") for i in range(4)], 1)),
        "opacities": t(col("opacity")),
        "sh0": t(np.stack([col(f"f_dc_{i}") for i in range(3)], 1)[:, None, :]),
        "shN": t(rest.reshape(N, 3, n_rest // 3).transpose(0, 2, 1)),
    })
    for k, shape in (extra_keys or {}).items():
        width = int(np.prod(shape))
        cols = [f"{k}_{j}" for j in range(width)]
        if not all(c in names for c in cols):
            raise ValueError(f"{path}: extra attribute {k!r} ({width} columns) not found")
        params[k] = t(np.stack([col(c) for c in cols], 1).reshape((N,) + tuple(shape)))
    return params
