"""Reference rasterizer in pure PyTorch: the oracle for the compiled backends.

Semantics (identical in every backend):
- Gaussians are composited front to back in order of camera depth; ties keep index order.
- At pixel centre p, alpha_i = min(0.99, o_i exp(-0.5 d^T Q_i d)) with d = p - mu_i and Q_i the
  conic, but only inside the 3-sigma ellipse (d^T Q_i d <= 9); alpha_i < 1/255 counts as 0.
  Because the footprint is defined per pixel, the image does not depend on how Gaussians are
  binned into tiles.
- T_i = prod_{j<i} (1 - alpha_j). Compositing stops before the first Gaussian that would bring
  T below 1e-4 (that Gaussian is not composited), as in 3DGS.
- C = sum_i alpha_i T_i f_i + T_final * background.

Implementation: Gaussians are binned into tiles (a Gaussian-tile pair per tile its 3-sigma
square touches), pairs are sorted by (tile, depth), and each tile's depth-ordered list is
processed in chunks of `chunk` Gaussians at a time across all tiles at once, carrying the
transmittance between chunks. Tiles are ordered by pair count, so the tiles still alive at chunk
j are a prefix and every step is a slice, not a masked scatter.
"""
from __future__ import annotations

import torch
from torch import Tensor

from .projection import SIGMA_EXTENT

ALPHA_MAX = 0.99
ALPHA_MIN = 1.0 / 255.0
T_MIN = 1e-4


def bin_gaussians(means2d: Tensor, radii: Tensor, depths: Tensor, width: int, height: int,
                  tile_size: int):
    """Gaussian-tile pairs sorted by (tile, depth).

    means2d [N, 2], radii [N] (0 = culled), depths [N].
    Returns (gauss_ids [P], tile_ids [P]) with P pairs, both int64.
    """
    dev = means2d.device
    ntx, nty = -(-width // tile_size), -(-height // tile_size)
    vis = torch.nonzero(radii > 0).squeeze(1)
    order = vis[torch.argsort(depths.detach()[vis], stable=True)]  # [V] visible, front to back
    m = means2d.detach()[order]
    r = radii[order].to(m.dtype)
    tx0 = torch.floor((m[:, 0] - r) / tile_size).clamp(0, ntx).long()
    tx1 = (torch.floor((m[:, 0] + r) / tile_size) + 1).clamp(0, ntx).long()
    ty0 = torch.floor((m[:, 1] - r) / tile_size).clamp(0, nty).long()
    ty1 = (torch.floor((m[:, 1] + r) / tile_size) + 1).clamp(0, nty).long()
    nx, ny = tx1 - tx0, ty1 - ty0
    cnt = nx * ny
    P = int(cnt.sum())
    g = torch.repeat_interleave(torch.arange(order.numel(), device=dev), cnt)  # depth rank
    local = torch.arange(P, device=dev) - torch.repeat_interleave(torch.cumsum(cnt, 0) - cnt, cnt)
    tile = (ty0[g] + local // nx[g]) * ntx + tx0[g] + local % nx[g]
    tile_sorted, perm = torch.sort(tile, stable=True)  # g is increasing: depth order kept
    return order[g[perm]], tile_sorted


def rasterize_reference(means2d: Tensor, conics: Tensor, opacities: Tensor, features: Tensor,
                        depths: Tensor, radii: Tensor, width: int, height: int,
                        tile_size: int = 16, chunk: int = 32) -> tuple[Tensor, Tensor]:
    """Composite Gaussians front to back.

    means2d [N, 2], conics [N, 3], opacities [N], features [N, F], depths [N], radii [N].
    Returns (feature image [H, W, F] without background, transmittance [H, W]).
    """
    dev, dt = means2d.device, means2d.dtype
    F = features.shape[1]
    ntx, nty = -(-width // tile_size), -(-height // tile_size)
    n_tiles, Pt = ntx * nty, tile_size * tile_size
    gid, tid = bin_gaussians(means2d, radii, depths, width, height, tile_size)

    counts = torch.bincount(tid, minlength=n_tiles)
    starts = torch.cumsum(counts, 0) - counts
    tiles = torch.argsort(counts, descending=True, stable=True)
    counts_s, starts_s = counts[tiles], starts[tiles]
    n_alive = [int(x) for x in torch.stack(
        [(counts_s > j * chunk).sum() for j in range(-(-int(counts.max()) // chunk))]
    )] if tid.numel() else []

    # pixel centres of every tile, in the sorted tile order: [n_tiles, Pt, 2]
    iy, ix = torch.meshgrid(torch.arange(tile_size, device=dev), torch.arange(tile_size, device=dev),
                            indexing="ij")
    ty, tx = tiles // ntx, tiles % ntx
    px = (tx[:, None] * tile_size + ix.reshape(1, -1)).to(dt) + 0.5
    py = (ty[:, None] * tile_size + iy.reshape(1, -1)).to(dt) + 0.5

    ar = torch.arange(chunk, device=dev)
    T = torch.ones(n_tiles, Pt, dtype=dt, device=dev)
    acc = torch.zeros(n_tiles, Pt, F, dtype=dt, device=dev)
    done = torch.zeros(n_tiles, Pt, dtype=torch.bool, device=dev)
    out_T, out_acc = [], []
    cur = n_tiles
    for j, n in enumerate(n_alive):
        if n < cur:  # tiles with no more pairs are final
            out_T.append(T[n:cur]); out_acc.append(acc[n:cur])
            T, acc, done = T[:n], acc[:n], done[:n]
            cur = n
        pos = starts_s[:n, None] + j * chunk + ar  # [n, C]
        valid = pos < (starts_s[:n] + counts_s[:n])[:, None]
        g = gid[torch.where(valid, pos, torch.zeros_like(pos))]  # [n, C]
        dx = px[:n, None, :] - means2d[g, 0][:, :, None]  # [n, C, Pt]
        dy = py[:n, None, :] - means2d[g, 1][:, :, None]
        cg = conics[g]
        maha = cg[:, :, 0, None] * dx * dx + 2.0 * cg[:, :, 1, None] * dx * dy + cg[:, :, 2, None] * dy * dy
        alpha = torch.clamp_max(opacities[g][:, :, None] * torch.exp(-0.5 * maha), ALPHA_MAX)
        use = valid[:, :, None] & (maha <= SIGMA_EXTENT ** 2) & (alpha >= ALPHA_MIN)
        alpha = torch.where(use, alpha, torch.zeros_like(alpha))
        cp = torch.cumprod(1.0 - alpha, dim=1)  # [n, C, Pt]
        T_incl = T[:, None, :] * cp
        T_excl = torch.cat([T[:, None, :], T_incl[:, :-1]], 1)
        keep = (T_incl >= T_MIN) & ~done[:, None, :]
        w = torch.where(keep, alpha * T_excl, torch.zeros_like(alpha))
        acc = acc + torch.bmm(w.transpose(1, 2), features[g])
        T = torch.where(keep, T_incl, T[:, None, :]).amin(1)
        done = done | (T_incl[:, -1] < T_MIN)
    out_T.append(T); out_acc.append(acc)
    T_all = torch.cat(out_T[::-1], 0)  # sorted tile order
    acc_all = torch.cat(out_acc[::-1], 0)
    inv = torch.empty_like(tiles)
    inv[tiles] = torch.arange(n_tiles, device=dev)
    T_img = T_all[inv].reshape(nty, ntx, tile_size, tile_size).permute(0, 2, 1, 3)
    acc_img = acc_all[inv].reshape(nty, ntx, tile_size, tile_size, F).permute(0, 2, 1, 3, 4)
    T_img = T_img.reshape(nty * tile_size, ntx * tile_size)[:height, :width]
    acc_img = acc_img.reshape(nty * tile_size, ntx * tile_size, F)[:height, :width]
    return acc_img, T_img
