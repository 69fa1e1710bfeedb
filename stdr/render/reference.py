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
transmittance between chunks. A tile leaves the batch when its list is exhausted or all its
pixels have stopped (T < 1e-4), as a CUDA block would exit early.
"""
from __future__ import annotations

import math

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
                        tile_size: int = 8, chunk: int = 32) -> tuple[Tensor, Tensor]:
    """Composite Gaussians front to back.

    means2d [N, 2], conics [N, 3], opacities [N], features [N, F], depths [N], radii [N].
    Returns (feature image [H, W, F] without background, transmittance [H, W]).
    """
    return _composite(means2d, conics, opacities, features, depths, radii, width, height, tile_size, chunk)


def contribution_reference(means2d: Tensor, conics: Tensor, opacities: Tensor, depths: Tensor,
                           radii: Tensor, width: int, height: int, tile_size: int = 8,
                           chunk: int = 32) -> Tensor:
    """Each Gaussian's blending weight alpha_i T_i summed over the pixels of the image [N] (0 for
    Gaussians not rendered): the torch twin of the compiled backends' score pass
    (`stdr.render.contribution`). Same compositing as `rasterize_reference`.

    means2d [N, 2], conics [N, 3], opacities [N], depths [N], radii [N]."""
    score = torch.zeros(means2d.shape[0], dtype=means2d.dtype, device=means2d.device)
    _composite(means2d.detach(), conics.detach(), opacities.detach(), means2d.new_ones(means2d.shape[0], 1),
               depths.detach(), radii, width, height, tile_size, chunk, score=score)
    return score


def _composite(means2d: Tensor, conics: Tensor, opacities: Tensor, features: Tensor, depths: Tensor,
               radii: Tensor, width: int, height: int, tile_size: int, chunk: int,
               score: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """rasterize_reference's compositing; with `score` [N], also adds each Gaussian's blending
    weights (summed over the pixels) to score."""
    dev, dt = means2d.device, means2d.dtype
    F = features.shape[1]
    ntx, nty = -(-width // tile_size), -(-height // tile_size)
    n_tiles, Pt = ntx * nty, tile_size * tile_size
    gid, tid = bin_gaussians(means2d, radii, depths, width, height, tile_size)

    counts = torch.bincount(tid, minlength=n_tiles)
    starts = torch.cumsum(counts, 0) - counts
    n_chunks = -(-int(counts.max()) // chunk) if tid.numel() else 0
    tiles = torch.arange(n_tiles, device=dev)

    # Per-pixel exponent as one batched matmul. In tile-local coordinates (u, v) = pixel centre
    # minus tile centre, the exponent log(o) - 0.5 (d^T Q d) with d = (u, v) - m is a quadratic
    # polynomial: coef [.., 6] . (u^2, uv, v^2, u, v, 1). The expansion's rounding error is
    # about eps * a * |m|^2; the 0.3 px^2 low-pass bounds a <= 1/0.3 and a Gaussian binned to a
    # tile has |m| <= tile_size/sqrt(2) + 3 sigma, so at 8x8 tiles in float32 the exponent is off
    # by < 2e-5 (relative alpha error < 2e-5). Tests pin it to a direct per-pixel loop in float64.
    basis, centre, inside = _tile_basis(tiles, ntx, tile_size, width, height, dt, score is not None)
    log_op = torch.log(opacities.clamp_min(1e-30))
    # per-Gaussian cut-off on the exponent: inside the 3-sigma ellipse and alpha >= 1/255
    cut = torch.maximum(log_op - 0.5 * SIGMA_EXTENT ** 2, torch.full_like(log_op, math.log(ALPHA_MIN)))

    ar = torch.arange(chunk, device=dev)
    ids = torch.nonzero(counts > 0).squeeze(1)  # tiles still compositing
    T = torch.ones(ids.numel(), Pt, dtype=dt, device=dev)
    acc = torch.zeros(ids.numel(), Pt, F, dtype=dt, device=dev)
    done = torch.zeros(ids.numel(), Pt, dtype=torch.bool, device=dev)
    out_ids, out_T, out_acc = [torch.nonzero(counts == 0).squeeze(1)], [], []
    out_T.append(torch.ones(out_ids[0].numel(), Pt, dtype=dt, device=dev))
    out_acc.append(torch.zeros(out_ids[0].numel(), Pt, F, dtype=dt, device=dev))
    for j in range(n_chunks):
        # a tile is final when its list is exhausted or every pixel has stopped (T < 1e-4)
        alive = (counts[ids] > j * chunk) & ~done.all(1)
        if not bool(alive.all()):
            out_ids.append(ids[~alive])
            out_T.append(T[~alive])
            out_acc.append(acc[~alive])
            ids, T, acc, done = ids[alive], T[alive], acc[alive], done[alive]
            if ids.numel() == 0:
                break
        pos = starts[ids, None] + j * chunk + ar  # [n, C]
        valid = pos < (starts[ids] + counts[ids])[:, None]
        g = gid[torch.where(valid, pos, torch.zeros_like(pos))]  # [n, C]
        m = means2d[g] - centre[ids, None, :]  # [n, C, 2] mean relative to the tile centre
        a, b, c = conics[g].unbind(-1)
        mx, my = m.unbind(-1)
        coef = torch.stack([-0.5 * a, -b, -0.5 * c, a * mx + b * my, b * mx + c * my,
                            log_op[g] - 0.5 * (a * mx * mx + 2 * b * mx * my + c * my * my)], -1)
        power = torch.matmul(coef, basis)  # [n, C, Pt]
        thr = torch.where(valid, cut[g], torch.full_like(cut[g], math.inf))
        use = power >= thr[:, :, None]
        alpha = torch.where(use, torch.exp(power).clamp_max(ALPHA_MAX), torch.zeros_like(power))
        cp = torch.cumprod(1.0 - alpha, dim=1)  # [n, C, Pt]
        T_incl = T[:, None, :] * cp
        T_excl = torch.cat([T[:, None, :], T_incl[:, :-1]], 1)
        keep = (T_incl >= T_MIN) & ~done[:, None, :]
        w = torch.where(keep, alpha * T_excl, torch.zeros_like(alpha))
        if score is not None:  # padding entries (not valid) have alpha 0, so w 0; pixels past the
            # image's right and bottom edges (in partial tiles) are composited but cropped: not counted
            px_in = inside[ids]  # [n, Pt]
            score.index_add_(0, g.reshape(-1), (w * px_in[:, None, :]).sum(-1).reshape(-1))
        acc = acc + torch.bmm(w.transpose(1, 2), features[g])
        T = torch.where(keep, T_incl, T[:, None, :]).amin(1)
        done = done | (T_incl[:, -1] < T_MIN)
    out_ids.append(ids)
    out_T.append(T)
    out_acc.append(acc)
    return _tiles_to_image(torch.cat(out_ids), torch.cat(out_T, 0), torch.cat(out_acc, 0), ntx, nty, tile_size,
                           width, height)


def _tile_basis(tiles: Tensor, ntx: int, tile_size: int, width: int, height: int, dt,
                with_inside: bool) -> tuple[Tensor, Tensor, Tensor | None]:
    """The per-pixel polynomial basis (u^2, uv, v^2, u, v, 1) [6, Pt] of a tile's pixel centres
    relative to the tile centre, each tile's centre [n_tiles, 2], and which of its pixels lie
    inside the image [n_tiles, Pt] (partial tiles at the right and bottom edges; only the score
    pass reads it, None without `with_inside`)."""
    dev = tiles.device
    half = tile_size / 2.0
    lc = torch.arange(tile_size, device=dev, dtype=dt) + 0.5 - half
    v_, u_ = torch.meshgrid(lc, lc, indexing="ij")
    u_, v_ = u_.reshape(-1), v_.reshape(-1)
    basis = torch.stack([u_ * u_, u_ * v_, v_ * v_, u_, v_, torch.ones_like(u_)])  # [6, Pt]
    ty, tx = tiles // ntx, tiles % ntx
    centre = torch.stack([tx, ty], -1).to(dt) * tile_size + half  # [n_tiles, 2]
    if not with_inside:
        return basis, centre, None
    px = tx[:, None] * tile_size + (u_ + half - 0.5).long()[None]  # [n_tiles, Pt] pixel columns
    py = ty[:, None] * tile_size + (v_ + half - 0.5).long()[None]
    return basis, centre, ((px < width) & (py < height)).to(dt)


def _tiles_to_image(order: Tensor, T: Tensor, acc: Tensor, ntx: int, nty: int, tile_size: int, width: int,
                    height: int) -> tuple[Tensor, Tensor]:
    """Per-tile results ([n_tiles, Pt] transmittance, [n_tiles, Pt, F] colour) listed in the order
    of tile ids `order`, as the cropped image ([H, W, F], [H, W])."""
    inv = torch.empty_like(order)
    inv[order] = torch.arange(order.numel(), device=order.device)
    T_all, acc_all = T[inv], acc[inv]  # tile-index order
    F = acc.shape[-1]
    T_img = T_all.reshape(nty, ntx, tile_size, tile_size).permute(0, 2, 1, 3)
    acc_img = acc_all.reshape(nty, ntx, tile_size, tile_size, F).permute(0, 2, 1, 3, 4)
    T_img = T_img.reshape(nty * tile_size, ntx * tile_size)[:height, :width]
    acc_img = acc_img.reshape(nty * tile_size, ntx * tile_size, F)[:height, :width]
    return acc_img, T_img
