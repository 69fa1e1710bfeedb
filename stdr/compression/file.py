"""The compact model file: a trained model in fewer bytes, for viewers and for shipping.

One file per model (`model.stdrc`, written by `stdr-tool pack RUN` and at the end of
`stdr-tool compact RUN`), read by `stdr.model.load_model` and so by `stdr-export`, `stdr-render`
and `stdr-eval`'s model loading. It is a checkpoint file (atomic, SHA-256 checked,
weights_only) whose payload is

    {"format": "stdr-compact", "version": 1, "spec": {...},
     "model": the model's entry (stdr.model.DynamicGaussians.state_dict) with every tensor
              replaced by its codec's dict (stdr.compression.codecs)}

`spec` says which codec holds what: per-Gaussian parameter keys, and `state` for the deformation
module's and the plug-ins' tensors (networks, HexPlane grids, STDR's field), `state:<part>` for
those whose dotted key contains <part> (`state:grids`: 4DGS's HexPlane planes; a plane of three or
more dimensions is quantized with a range per channel, its first dimension); `sh_degree` (optional)
keeps the SH rest to that degree's bands, the higher ones reading back as zeros (the model renders
as one of that degree). A baseline may name,
per parameter, the columns its renders read (`compact_columns`, stdr.compression.hooks: SP-GS's association
logits at each Gaussian's K nearest superpoints); those are stored with the `cols` codec. A
plug-in may name tables it reads only through an activation to [0, 1] and accepts in 8 bits
(`compact_form`'s units: STDR's mask); a codec the spec names for such a key encodes the activated
values and the file reads them back as uint8 q (for q / 255), the form `stdr.mask_bits=8` stores.
The spec value `derived` for such a table stores instead what a finished model computes from it
(`compact_form`'s derived tables: STDR's mask as the separated field's output [N, 17], with the field's
weights left out; only for a model whose mask no longer multiplies opacity), under the plug-in's
key for it, in the codec the spec names for that key (`stdr_cond: q8`; default `*`).
Sized codecs are written "vq:1024", "lowrank:8" (stdr.compression.codecs). A file with a higher version
than this code reads is refused with an error that says so.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Optional

import torch
from torch import Tensor

from ..errors import UserError
from ..io.checkpoint import CKPT, checkpoint_identity
from ..io.files import read_json
from . import codecs, entropy
from .hooks import columns_of, form_of

FORMAT = "stdr-compact"
VERSION = 2  # 2: streams may be entropy coded (spec `entropy`); version 1 files read as before
SUFFIX = ".stdrc"
DERIVED = "derived"  # the spec value: store what the finished model computes from this table
MARK = "__codec__"  # an encoded tensor's dict carries it (a state dict's own keys never do)

#: the default codecs: positions exact, the other attributes in half precision, the SH rest (45 of
#: 59 floats a Gaussian at degree 3) in 8 bits per coefficient with a per-coefficient range, an
#: integer mask as it is, every other per-Gaussian tensor in half precision; networks and grids float32
#: (integer and float64 tensors are always stored as they are: flags, an 8-bit mask, time knots);
#: every stream then entropy coded (lossless; chosen by research/measurements/compact_entropy's rule)
DEFAULT_SPEC = {"means": "f32", "scales": "f16", "quats": "f16", "opacities": "f16", "sh0": "f16", "shN": "q8",
                "*": "f16", "state": "f32", "entropy": "zstd"}
#: the spec's `entropy` values: none, or Zstandard over every stream (stdr.compression.entropy), at its
#: default level or `zstd:<level>` (1 to 22)
ENTROPY_CODERS = ("none", "zstd")


def _enc(x: Tensor, codec: str, cols: Optional[Tensor] = None) -> dict:
    if not x.is_floating_point() or x.dtype == torch.float64:
        codec = "raw"  # an integer tensor (an 8-bit mask, a flag) or a float64 one (time knots) as it is
    return {MARK: True, **codecs.encode(x, codec, cols)}


def _state_codec(path: str, spec: dict) -> str:
    """The codec of the state tensor at `path` (dotted): the first `state:<part>` entry of the spec
    whose part occurs in the path, else `state`."""
    return next((c for k, c in spec.items() if k.startswith("state:") and k[6:] in path), spec["state"])


def _walk_encode(x: Any, spec: dict, path: str = "") -> Any:
    if isinstance(x, Tensor):
        codec = _state_codec(path, spec)
        if x.dim() >= 3 and codecs.parse(codec)[0] in ("q8", "q4", "q16") and x.is_floating_point():
            # a grid plane [C, H, W]: a range per channel (the first dimension), not per last-axis column
            return {**_enc(x.movedim(0, -1), codec), "channels_first": True}
        return _enc(x, codec)
    if isinstance(x, dict):
        return {k: _walk_encode(v, spec, f"{path}.{k}" if path else str(k)) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return type(x)(_walk_encode(v, spec, f"{path}.{i}") for i, v in enumerate(x))
    return x


def _walk_decode(x: Any) -> Any:
    if isinstance(x, dict):
        if x.get(MARK):
            t = codecs.decode({k: v for k, v in x.items() if k not in (MARK, "pad_rows", "unit8", "channels_first")})
            if x.get("channels_first"):
                return t.movedim(-1, 0).contiguous()
            if x.get("unit8"):  # a plug-in's [0, 1] table, read back in its 8-bit form
                return torch.round(t.clamp(0.0, 1.0) * 255.0).to(torch.uint8)
            if "pad_rows" in x:  # the SH rest kept to a lower degree: the higher bands read as zeros
                t = torch.cat([t, t.new_zeros(t.shape[0], int(x["pad_rows"]) - t.shape[1], *t.shape[2:])], 1)
            return t
        return {k: _walk_decode(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return type(x)(_walk_decode(v) for v in x)
    return x


def check_spec(spec: Optional[dict]) -> dict:
    """The spec over DEFAULT_SPEC, each codec parsed; a ValueError names the key and what to write."""
    spec = {**DEFAULT_SPEC, **(spec or {})}
    if spec.get("sh_degree") is not None and not 0 <= int(spec["sh_degree"]) <= 3:
        raise ValueError(f"compact spec sh_degree={spec['sh_degree']}: use 0 to 3 (or leave it out)")
    entropy_level(spec)
    named = {k[len("state:"):] for k in spec if k.startswith("state:")}
    for part in str(spec.get("finetune_state") or "").split(","):
        if part.strip() and part.strip() not in named:
            raise ValueError(f"compact spec finetune_state={spec['finetune_state']!r} (pack.finetune_state): "
                             f"{part.strip()!r} is no state:<part> of the spec ({', '.join(sorted(named)) or 'none'}); "
                             "name a part the spec gives a codec, e.g. state:grids=q4 with finetune_state=grids")
    for k, c in spec.items():
        if k in ("sh_degree", "finetune", "finetune_state", "entropy") or c == DERIVED:
            continue
        try:
            codecs.parse(c)
        except ValueError as err:
            raise ValueError(f"compact spec {k}={c!r}: {err}") from None
    return spec


def entropy_level(spec: dict) -> Optional[int]:
    """The Zstandard level of the spec's `entropy` (None: no entropy coding); a ValueError names
    the key and what to write."""
    name, _, arg = str(spec.get("entropy", "none")).partition(":")
    if name not in ENTROPY_CODERS or (arg and (name == "none" or not arg.isdigit() or not 1 <= int(arg) <= 22)):
        raise ValueError(f"compact spec entropy={spec.get('entropy')!r}: use none, zstd or zstd:<level 1-22>")
    return None if name == "none" else int(arg or entropy.LEVEL)


def encode_model(model, spec: Optional[dict] = None, pack: bool = True) -> dict[str, Any]:
    """The compact file's payload of a `DynamicGaussians` (its state_dict, encoded by `spec`,
    DEFAULT_SPEC's entries where `spec` names none), its streams entropy coded when the spec's
    `entropy` says so (pack=False leaves that to the caller: `pack_streams`, after a fine-tune)."""
    spec = check_spec(spec)
    entry = model.state_dict()
    cols = columns_of(model.deform, model.params)
    asked = {k for k, c in spec.items() if c == DERIVED}
    units, derived, plugins = {}, {}, dict(entry["plugins"])
    for p in model.plugins:
        # its state without what a render does not read (STDR: its training caches, and the
        # field's weights when the file stores the field's output)
        form = form_of(p, model.params, plugins[p.name], model.step, asked & set(model.params))
        units.update(form.units)
        derived.update({k: v for k, v in form.derived.items() if k in asked})
        plugins[p.name] = form.state
    # a table this model does not have is not stored at all (a spec serves every method: the
    # preset's `stdr_mask: derived` on a run without STDR); one it has must be derived as asked
    missing = (asked & set(entry["params"])) - set(derived)
    if missing:
        raise ValueError(f"compact spec {', '.join(f'{k}={DERIVED}' for k in sorted(missing))}: "
                         "no plug-in of this model derives that table; name a codec instead")
    params = {}
    degree = spec.get("sh_degree")
    for k, v in entry["params"].items():
        if k in derived:
            key, values = derived[k]
            params[key] = _enc(values, spec.get(key, spec["*"]))
        elif k in cols:
            params[k] = _enc(v, "cols", cols[k])
        elif k in units and k in spec and spec[k] == "q8":  # the 8-bit form itself, exact uint8
            params[k] = _enc(torch.round(units[k] * 255.0).to(torch.uint8), "raw")
        elif k in units and k in spec and spec[k] not in ("raw", "f32", "f16"):
            params[k] = {**_enc(units[k], spec[k]), "unit8": True}
        elif k == "shN" and degree is not None and (int(degree) + 1) ** 2 - 1 < v.shape[1]:
            keep = (int(degree) + 1) ** 2 - 1
            params[k] = {**_enc(v[:, :keep], spec.get(k, spec["*"])), "pad_rows": v.shape[1]}
        else:
            params[k] = _enc(v, spec.get(k, spec["*"]))
    # what each was stored as (an integer tensor: raw; a sized codec with its size)
    used = {k: (spec.get(k, spec["*"]) if e["codec"] == codecs.parse(spec.get(k, spec["*"]))[0] else e["codec"])
            for k, e in params.items()}
    used.update({k: DERIVED for k in derived})
    model_entry = {**entry, "params": params, "deform": _walk_encode(entry["deform"], spec),
                   "plugins": _walk_encode(plugins, spec)}
    payload = {"format": FORMAT, "version": VERSION, "model": model_entry,
               "spec": {**used, "state": spec["state"], **{k: c for k, c in spec.items() if k.startswith("state:")},
                        **({"sh_degree": int(degree)} if degree is not None else {}), "entropy": spec["entropy"]}}
    return pack_streams(payload) if pack else payload


def pack_streams(payload: dict[str, Any]) -> dict[str, Any]:
    """The payload with every stream of its model entry entropy coded as its spec says (no-op for
    `entropy: none`)."""
    level = entropy_level(payload["spec"])
    return payload if level is None else {**payload, "model": entropy.pack_tree(payload["model"], level)}


def is_compact(payload: Any) -> bool:
    return isinstance(payload, dict) and payload.get("format") == FORMAT


def decode_model(payload: dict[str, Any], where: str = "compact file") -> dict[str, Any]:
    """The model entry (as `DynamicGaussians.state_dict` gives it) of a compact file's payload."""
    v = payload.get("version")
    if not isinstance(v, int) or v < 1:
        raise ValueError(f"{where}: not a readable {FORMAT} file (version {v!r})")
    if v > VERSION:
        raise ValueError(f"{where}: a {FORMAT} file of version {v}, written by a newer stdr; this stdr reads "
                         f"versions up to {VERSION}: upgrade stdr (pip install -U stdr) to load it")
    return _walk_decode(entropy.unpack_tree(payload["model"]))


def compact_source_note(path: str | Path) -> str:
    """A compact model file in a run folder (RUN/model.stdrc) packed from another checkpoint than
    the run's last (pack.json names its source): one line saying so; "" otherwise."""
    path = Path(path)
    ck = path.parent / CKPT
    if path.suffix != ".stdrc" or not (path.parent / "pack.json").is_file() or not ck.is_file():
        return ""
    src = model_source(path)
    now = checkpoint_identity(ck)
    if not isinstance(src, dict) or now is None or src.get("sha256") == now["sha256"]:
        return ""
    return (f"{path} was packed from the checkpoint at iteration {src.get('step')}; the run's {CKPT} is at iteration "
            f"{now['step']}: this file is not the run's model now (stdr-tool pack {path.parent} packs it again)")


def model_source(path: str | Path) -> Optional[dict[str, Any]]:
    """The checkpoint a model file came from ({"step", "sha256"}): a checkpoint's own identity, or
    for a compact file the one its run's pack.json recorded; None when unknown."""
    path = Path(path)
    if path.suffix != ".stdrc":
        return checkpoint_identity(path)
    try:
        rec = read_json(path.parent / "pack.json", "pack record") if (path.parent / "pack.json").is_file() else {}
    except UserError:
        return None
    src = rec.get("checkpoint") if isinstance(rec, dict) else None
    return src if isinstance(src, dict) else None
