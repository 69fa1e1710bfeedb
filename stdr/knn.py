"""Exact k-nearest neighbours in torch (chunked cdist + topk); no pytorch3d / simple-knn."""
from __future__ import annotations

import torch
from torch import Tensor


#: query points per block of the distance matrix: a block is KNN_CHUNK x len(points) floats
KNN_CHUNK = 1024


def knn(query: Tensor, points: Tensor, k: int, exclude_self: bool = False,
        chunk: int = KNN_CHUNK) -> tuple[Tensor, Tensor]:
    """Squared distances [Q, k] and indices [Q, k] of the k nearest `points` [P, D] to `query` [Q, D].

    With exclude_self, query i is assumed to be points i and is not its own neighbour.
    """
    kk = k + 1 if exclude_self else k
    if points.shape[0] < kk:
        raise ValueError(f"knn: need at least {kk} points, got {points.shape[0]}")
    d_out, i_out = [], []
    for s in range(0, query.shape[0], chunk):
        q = query[s:s + chunk]
        d2 = torch.cdist(q, points).square_()
        if exclude_self:
            d2.diagonal(offset=s).fill_(float("inf"))  # (r, r + s): each query itself
        d, i = torch.topk(d2, k, dim=1, largest=False)
        d_out.append(d)
        i_out.append(i)
    return torch.cat(d_out), torch.cat(i_out)
