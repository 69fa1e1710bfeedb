"""A short fine-tune of the compact file's lossy codes with the training loss, after the file's
codecs are applied: the codebooks (the `vq:C` codec) and, quantization-aware, the deformation
state the spec names in `finetune_state` (4DGS's HexPlane planes in q4).

k-means places each codeword at the mean of its rows, and a uniform quantizer rounds each value to
its nearest level; both minimize the error in the tensor, not in the image. `finetune` renders
training frames with the model read back from the file and, each step:

* a codebook: the tensor is set to codebook[index]; each codeword gets the sum of its rows'
  gradients (the exact gradient of the loss through the lookup);
* a quantized state tensor (q4 / q8 / q16): a float copy of the full model's values is kept, the
  model reads its quantized value in the file's range (`codecs.dequantized`, on the model's
  device; the range fixed at the file's), and the gradient passes straight through the rounding
  to the float copy where it lies inside the range (the straight-through estimator);

then one Adam step on them all. Every other tensor stays as the file holds it. At the end the
codebooks are stored back in float16 and the state tensors re-encoded in their range, so the file
holds exactly what the last step rendered with. A table that the render uses as a constant (STDR's
`derived` conditioning is read detached) gets no gradient: its codebook stays as k-means placed
it, and the result lists it under `fixed`.
"""
from __future__ import annotations

from typing import Any, Iterable

import torch

from ..metrics import image_loss
from ..compression import codecs
from ..compression.file import MARK

#: defaults, fixed before any measurement (research/measurements/compact_bytes/protocol.md, amendment 1)
STEPS = 500
LR = 5e-4
LAMBDA_DSSIM = 0.2


def vq_entries(payload: dict[str, Any]) -> dict[str, dict]:
    """The per-Gaussian tensors a compact payload holds with the `vq` codec: {key: its encoded dict}."""
    return {k: e for k, e in payload["model"]["params"].items() if isinstance(e, dict) and e.get(MARK)
            and e.get("codec") == "vq"}


def state_entries(payload: dict[str, Any], parts: Iterable[str]) -> dict[str, dict]:
    """The deformation state tensors a compact payload holds in a uniform quantizer (q4, q8, q16)
    whose dotted key contains one of `parts` ("grids": 4DGS's HexPlane planes): {key: its encoded dict}."""
    parts = tuple(parts)
    return {k: e for k, e in payload["model"]["deform"].items() if isinstance(e, dict) and e.get(MARK)
            and e.get("codec") in codecs.LEVELS and any(p in k for p in parts)}


class _State:
    """A quantized state tensor's fine-tune: its payload entry, the float copy it trains, and the
    entry's range per column on the copy's device (moved there once)."""

    def __init__(self, entry: dict, latent: torch.Tensor):
        self.entry, self.latent = entry, latent
        self.lo, self.hi = entry["lo"].to(latent.device), entry["hi"].to(latent.device)

    def _cols(self, t: torch.Tensor) -> torch.Tensor:  # a plane [C, H, W] as the codec sees it: [H, W, C]
        return t.movedim(0, -1) if self.entry.get("channels_first") else t

    def _back(self, t: torch.Tensor) -> torch.Tensor:
        return t.movedim(-1, 0) if self.entry.get("channels_first") else t

    def quantized(self) -> torch.Tensor:
        """What the file stores for the float copy (codecs.dequantized, on its device)."""
        return self._back(codecs.dequantized(self._cols(self.latent.detach()), self.entry["codec"], self.lo, self.hi))

    def inside(self) -> torch.Tensor:
        """Where the float copy lies inside its columns' ranges (the straight-through estimator's mask)."""
        x = self._cols(self.latent.detach())
        return self._back((x >= self.lo) & (x <= self.hi))

    def store(self) -> torch.Tensor:
        """The entry's data re-encoded from the float copy in its range; returns what the file reads
        back (dequantized is decode(encode_in_range) exactly)."""
        self.entry["data"] = codecs.encode_in_range(self._cols(self.latent.detach()), self.entry["codec"],
                                                    self.entry["lo"], self.entry["hi"])["data"]
        return self.quantized()


def finetune(payload: dict[str, Any], model, frames, steps: int = STEPS, lr: float = LR,
             lambda_dssim: float = LAMBDA_DSSIM, seed: int = 0, full=None, state_parts: Iterable[str] = ()) -> dict[str, Any]:
    """Fine-tune, in place, the codebooks of `payload` (from stdr.compression.file.encode_model) and its
    quantized deformation state under `state_parts`, on `frames` (training frames), rendering with
    `model` (the payload's model read back, in eval mode). A state tensor starts from `full`'s (the
    model the payload was encoded from) float values. Returns {steps, loss_first, loss_last (means
    over the first and last 10 % of the steps), keys (the codebooks fine-tuned), fixed (those no
    gradient reaches, left as they were), state (the state tensors fine-tuned)}."""
    entries = vq_entries(payload)
    trainable = {k for k, _ in model.deform.named_parameters()}  # a buffer under a named part is not trained
    states = {k: e for k, e in state_entries(payload, state_parts).items() if k in trainable}
    if (not entries and not states) or steps <= 0:
        return {"steps": 0, "keys": sorted(entries), "fixed": [], "state": sorted(states)}
    if not frames:
        raise ValueError("finetune: no frames to fine-tune on")
    if states and full is None:
        raise ValueError("finetune: state_parts needs the full model (full=) for the state's float values")
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
    tuned, targets = {}, {}
    for k, e in states.items():
        targets[k] = model.deform.get_parameter(k)
        z = full.deform.get_parameter(k).detach().float().clone().to(targets[k].device).requires_grad_(True)
        tuned[k] = _State(e, z)
        targets[k].requires_grad_(True)
    opt = torch.optim.Adam([*books.values(), *(t.latent for t in tuned.values())], lr=lr)
    g = torch.Generator().manual_seed(seed)
    order = torch.randint(0, len(frames), (steps,), generator=g).tolist()
    losses, fixed = [], set()
    for i in order:
        f = frames[i]
        with torch.no_grad():
            for k in books:
                model.params[k].copy_(books[k][idx[k]].reshape(shapes[k]))
                model.params[k].grad = None
            for k, t in tuned.items():
                targets[k].copy_(t.quantized())
                targets[k].grad = None
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
        for k, t in tuned.items():
            if targets[k].grad is not None:
                t.latent.grad = targets[k].grad * t.inside()
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
        for k, t in tuned.items():
            targets[k].copy_(t.store())
            targets[k].grad = None
    tenth = max(1, steps // 10)
    return {"steps": steps, "loss_first": sum(losses[:tenth]) / tenth, "loss_last": sum(losses[-tenth:]) / tenth,
            "keys": sorted(set(books) - fixed), "fixed": sorted(fixed), "state": sorted(tuned)}
