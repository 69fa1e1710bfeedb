"""Exact k-nearest neighbours of points (any dimension), in two forms.

* `knn`: torch.cdist's distances and torch.topk (no pytorch3d / simple-knn): used where a search
  runs once (initial scales, STDR's mask neighbourhoods) and, with `baseline.<name>.knn=cdist`, in
  SC-GS's and SP-GS's searches of every step. cdist's distances come from a matrix product, so
  near-ties can order differently on another BLAS or CPU.
* `knn_direct`: the squared coordinate differences summed in double, ties to the lower index
  (stdr/csrc/knn_math.h); the compiled kernel (CPU) and its torch twin `knn_direct_torch` give
  the same bits, so which one runs (`baseline.knn_compiled`) changes no result.
  `baseline.<name>.knn=direct` takes it.
"""
from __future__ import annotations

import functools
from typing import Callable, Optional

import torch
from torch import Tensor

from . import extension
from .errors import ConfigError

#: query points per block of the distance matrix: a block is KNN_CHUNK x len(points) floats
KNN_CHUNK = 1024
#: the largest k of the compiled search (stdr/csrc/knn_math.h KNN_MAX_K)
KNN_MAX_K = 16
#: the searches a baseline can use for its per-step neighbours (`baseline.<name>.knn`)
KNN_FORMS = ("cdist", "direct")


def _check(query: Tensor, points: Tensor, k: int, exclude_self: bool) -> None:
    kk = k + 1 if exclude_self else k
    if points.shape[0] < kk:
        raise ValueError(f"knn: need at least {kk} points, got {points.shape[0]}")


def knn(query: Tensor, points: Tensor, k: int, exclude_self: bool = False,
        chunk: int = KNN_CHUNK) -> tuple[Tensor, Tensor]:
    """Squared distances [Q, k] and indices [Q, k] of the k nearest `points` [P, D] to `query` [Q, D].

    With exclude_self, query i is assumed to be points i and is not its own neighbour.
    """
    _check(query, points, k, exclude_self)
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


def knn_direct_torch(query: Tensor, points: Tensor, k: int, exclude_self: bool = False,
                     chunk: int = KNN_CHUNK) -> tuple[Tensor, Tensor]:
    """The torch twin of the compiled search: float32 squared distances [Q, k] and int64 indices
    [Q, k] of the k nearest `points` [P, D] to `query` [Q, D], nearest first, ties to the lower
    index, a NaN last; a distance adds the float32 differences' squares in float64, coordinate
    by coordinate in order (stdr/csrc/knn_math.h)."""
    _check(query, points, k, exclude_self)
    d_out, i_out = [], []
    for s in range(0, query.shape[0], chunk):
        q = query[s:s + chunk]
        d2 = torch.zeros(q.shape[0], points.shape[0], dtype=torch.float64, device=q.device)
        for c in range(q.shape[1]):
            d2 += (q[:, None, c] - points[None, :, c]).double().square_()
        d, i = torch.sort(d2, dim=1, stable=True)
        d, i = d[:, :k + exclude_self], i[:, :k + exclude_self]
        if exclude_self:  # each row without its own point (or without its last, where that is further)
            keep = i != torch.arange(s, s + q.shape[0], device=q.device)[:, None]
            keep[:, -1] &= ~keep.all(1)
            d, i = d[keep].view(-1, k), i[keep].view(-1, k)
        d_out.append(d.float())
        i_out.append(i)
    return torch.cat(d_out), torch.cat(i_out)


def knn_direct(query: Tensor, points: Tensor, k: int, exclude_self: bool = False,
               compiled: Optional[bool] = None) -> tuple[Tensor, Tensor]:
    """`knn_direct_torch`'s result, from the compiled kernel or the twin by `compiled`
    (`baseline.knn_compiled`: null = the kernel where it has been verified, stdr.verified.VERIFIED,
    and the extension builds; false = the twin; true insists): the same bits either way. No
    gradient flows (the searches run on detached positions)."""
    kind = query.device.type
    fits = (kind == "cpu" and query.dtype == points.dtype == torch.float32 and query.shape[-1] == points.shape[-1]
            and 1 <= k <= KNN_MAX_K and (not exclude_self or query.shape[0] == points.shape[0]))
    if extension.use_compiled("baseline.knn_compiled", compiled, kind, fits,
                              f"the compiled search takes float32 points on the CPU and k <= {KNN_MAX_K}, "
                              f"here {query.dtype} on {kind}, k={k}"):
        _check(query, points, k, exclude_self)
        return extension.load_extension(kind).knn_direct(query.detach(), points.detach(), k, exclude_self)
    return knn_direct_torch(query.detach(), points.detach(), k, exclude_self)


def check_knn_form(key: str, form: str) -> str:
    """A `knn` key's value, or a ConfigError naming the key and the choices."""
    if form not in KNN_FORMS:
        raise ConfigError(f"{key}={form!r}: use one of {', '.join(KNN_FORMS)}")
    return form


def nearest(form: str, query: Tensor, points: Tensor, k: int, exclude_self: bool = False,
            compiled: Optional[bool] = None) -> tuple[Tensor, Tensor]:
    """A baseline's search by its `knn` key: "cdist" (`knn`) or "direct" (`knn_direct`, its
    kernel chosen by `compiled`: `baseline.knn_compiled`)."""
    if form == "direct":
        return knn_direct(query, points, k, exclude_self, compiled)
    if form == "cdist":
        return knn(query, points, k, exclude_self)
    check_knn_form("knn", form)  # raises: no other form
    raise AssertionError(form)


def searcher(key: str, form: str, compiled: Optional[bool] = None) -> Callable[..., tuple[Tensor, Tensor]]:
    """`nearest` with a baseline's `knn` key (its name `key`, checked here) and
    `baseline.knn_compiled` bound: search(query, points, k, exclude_self=False)."""
    check_knn_form(key, form)
    return functools.partial(nearest, form, compiled=compiled)
