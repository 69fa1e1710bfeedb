"""A short fine-tune of the compact file's codebooks (the `vq:C` codec, stdr.compact.codecs) with the
training loss, after the file's codecs are applied.

k-means places each codeword at the mean of its rows, which minimizes the error in the tensor, not
in the image. `finetune_codebooks` renders training frames with the model read back from the file
and moves only the codewords: each step sets the tensor to codebook[index], renders, and gives each
codeword the sum of its rows' gradients (the exact gradient of the loss through the lookup), then
an Adam step. Every other tensor stays as the file holds it. The codebooks are stored back in float16.
A table that the render uses as a constant (STDR's `derived` conditioning is read detached: the
field's output of a frozen mask) gets no gradient; its codebook stays as k-means placed it, and
the result lists it under `fixed`.
"""
from __future__ import annotations

from typing import Any

import torch

from ..metrics import image_loss
from .file import MARK

#: defaults, fixed before any measurement (docs/measurements/compact_bytes/protocol.md, amendment 1)
STEPS = 500
LR = 5e-4
LAMBDA_DSSIM = 0.2


def vq_entries(payload: dict[str, Any]) -> dict[str, dict]:
    """The per-Gaussian tensors a compact payload holds with the `vq` codec: {key: its encoded dict}."""
    return {k: e for k, e in payload["model"]["params"].items() if isinstance(e, dict) and e.get(MARK)
            and e.get("codec") == "vq"}


def finetune_codebooks(payload: dict[str, Any], model, frames, steps: int = STEPS, lr: float = LR,
                       lambda_dssim: float = LAMBDA_DSSIM, seed: int = 0) -> dict[str, Any]:
    """Fine-tune, in place, the codebooks of `payload` (from stdr.compact.file.encode_model) on
    `frames` (training frames), rendering with `model` (the payload's model read back, in eval mode).
    Returns {steps, loss_first, loss_last (means over the first and last 10 % of the steps), keys
    (the codebooks fine-tuned), fixed (those no gradient reaches, left as they were)}."""
    entries = vq_entries(payload)
    if not entries or steps <= 0:
        return {"steps": 0, "keys": sorted(entries), "fixed": []}
    if not frames:
        raise ValueError("finetune_codebooks: no frames to fine-tune on")
    model.eval()
    for p in model.params.values():
        p.requires_grad_(False)
    for module in [model.deform, *(m for pl in model.plugins for m in pl.modules())]:
        for p in module.parameters():
            p.requires_grad_(False)
    books, idx, shapes = {}, {}, {}
    for k, e in entries.items():
        books[k] = e["codebook"].float().to(model.params[k].device).requires_grad_(True)
        idx[k] = e["data"].long().to(model.params[k].device)
        shapes[k] = model.params[k].shape
        model.params[k].requires_grad_(True)
    opt = torch.optim.Adam(list(books.values()), lr=lr)
    g = torch.Generator().manual_seed(seed)
    order = torch.randint(0, len(frames), (steps,), generator=g).tolist()
    losses, fixed = [], set()
    for i in order:
        f = frames[i]
        with torch.no_grad():
            for k in books:
                model.params[k].copy_(books[k][idx[k]].reshape(shapes[k]))
                model.params[k].grad = None
        out = model.render(f.camera, f.time)
        loss = image_loss(out.image, f.image, lambda_dssim)[0]
        loss.backward()
        opt.zero_grad(set_to_none=True)
        for k, b in books.items():
            if model.params[k].grad is None:  # the render reads this table as a constant
                fixed.add(k)
                continue
            grad = model.params[k].grad.reshape(shapes[k][0], -1)
            b.grad = torch.zeros_like(b).index_add_(0, idx[k], grad)
        opt.step()
        losses.append(float(loss.detach()))
    with torch.no_grad():
        for k, b in books.items():
            if k in fixed:  # exactly the codebook the file had
                model.params[k].grad = None
                continue
            entries[k]["codebook"] = b.detach().cpu().half()
            model.params[k].copy_(entries[k]["codebook"].float().to(b.device)[idx[k]].reshape(shapes[k]))
            model.params[k].grad = None
    tenth = max(1, steps // 10)
    return {"steps": steps, "loss_first": sum(losses[:tenth]) / tenth, "loss_last": sum(losses[-tenth:]) / tenth,
            "keys": sorted(set(books) - fixed), "fixed": sorted(fixed)}
