"""The compact file of a model or of a trained run: the one place the trainer (`pack.enabled`,
`compact=on`), `stdr-tool pack` and `stdr-tool compact` write it from.

* `check_pack_config(cfg)`: the run's `pack` section (codecs, and what the enabled plug-ins
  accept), checked before training so that a bad codec never costs a run;
* `write_compact(model, path, spec, frames)`: encode (stdr.compression.file), fine-tune the
  codebooks when the spec asks (stdr.compact.finetune), write atomically;
* `pack(run_dir, ...)`: a trained run's file, and its renders against the full model's
  (RUN/model.stdrc, RUN/pack.json).
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Optional

from ..store import load_config
from ..data.load import load_run_scene
from ..errors import ConfigError
from ..eval.evaluate import evaluate_model
from ..io.checkpoint import CKPT, checkpoint_identity, save_checkpoint
from ..io.files import write_atomic
from ..io.files import run_lock
from ..model import load_model, model_bytes, model_from_checkpoint
from ..plugins import enabled_plugins, plugin_node
from ..compression import codecs
from ..compression.file import SUFFIX, check_spec, encode_model, pack_streams
from ..compression.hooks import check_plugin_spec
from .finetune import finetune, state_entries, vq_entries


def check_pack_config(cfg) -> Optional[dict]:
    """The compact spec of a run config with `pack.enabled`, checked (its codecs, and each enabled
    plug-in's view of them), or None when the run writes no compact file. A bad spec is a
    ConfigError (one line from stdr-train) naming `pack.codecs`."""
    if not cfg.pack.enabled:
        return None
    try:
        spec = check_spec(spec_of_config(cfg.pack))
        for p in enabled_plugins(cfg):
            check_plugin_spec(p.plugin, plugin_node(cfg, p.name), spec)
    except ValueError as e:
        raise ConfigError(f"pack.codecs: {e}") from None
    return spec


def write_compact(model, path: str | Path, spec: Optional[dict] = None, frames=None) -> dict[str, Any]:
    """Write the compact file of `model` to `path` (atomic, checksummed). Returns {bytes (of its
    tensors), full_bytes (the model's own tensors), spec}. With spec `finetune: STEPS`, the
    codebooks of its `vq:C` codecs and the quantized state its `finetune_state` names (e.g.
    "grids") are first fine-tuned for STEPS steps on `frames` (training frames;
    stdr.compact.finetune), and the result has `finetune` (its losses). With spec `entropy: zstd`
    every stream is entropy coded last (stdr.compression.entropy)."""
    payload = encode_model(model, spec, pack=False)
    steps = int((spec or {}).get("finetune") or 0)
    parts = finetune_parts(spec)
    extra = {}
    if steps:
        if not vq_entries(payload) and not state_entries(payload, parts):
            raise ValueError("compact spec finetune: no tensor is stored with a vq:C codec and no state tensor named by "
                             "finetune_state in q4/q8/q16, so there is nothing to fine-tune")
        if not frames:
            raise ValueError("compact spec finetune: pass the training frames (stdr-tool pack loads them from the run's data)")
        small = model_from_checkpoint(payload, next(model.params.values()).device, model.cfg)
        extra["finetune"] = finetune(payload, small, frames, steps, full=model, state_parts=parts)
        payload["spec"]["finetune"] = steps
        if extra["finetune"]["state"]:  # recorded where it tuned something: a model without the state writes the same file
            payload["spec"]["finetune_state"] = ",".join(parts)
    payload = pack_streams(payload)
    save_checkpoint(path, payload, site="compact")
    return {"bytes": codecs.nbytes(payload["model"]), "full_bytes": model_bytes(model), "spec": payload["spec"], **extra}


def finetune_parts(spec: Optional[dict]) -> tuple[str, ...]:
    """The spec's `finetune_state` ("grids", or parts separated by commas) as a tuple of parts."""
    return tuple(p.strip() for p in str((spec or {}).get("finetune_state") or "").split(",") if p.strip())


def pack(run_dir: Path, out: Optional[Path] = None, spec: Optional[dict] = None, split: Optional[str] = "val",
         data_base: Optional[str] = None) -> dict:
    """The compact file of run_dir's model, and (split not None) its renders against the full model's.
    Under the run's lock (stdr.io.files): it writes model.stdrc and pack.json into the run."""
    run_dir = Path(run_dir)
    src = run_dir / CKPT
    if not (run_dir / "config.yaml").is_file() or not src.is_file():
        raise FileNotFoundError(f"{run_dir}: not a trained run (config.yaml and {CKPT} are needed)")
    with run_lock(run_dir, "stdr-tool pack"):
        return _pack_locked(run_dir, src, out, spec, split, data_base)


def _pack_locked(run_dir: Path, src: Path, out: Optional[Path], spec: Optional[dict], split: Optional[str],
                 data_base: Optional[str]) -> dict:
    out = Path(out) if out is not None else run_dir / f"model{SUFFIX}"
    cfg = load_config(run_dir / "config.yaml")
    cfg.device = "cpu"
    full = load_model(src, "cpu", cfg)
    frames = None
    if (spec or {}).get("finetune"):  # the codebooks' fine-tune renders the training frames
        frames = load_run_scene(run_dir, cfg, ("train",), base=data_base, seed=cfg.seed).frames("train")
    rec = {"file": str(out), **write_compact(full, out, spec, frames),
           "checkpoint": checkpoint_identity(src)}  # the model it packs (readers compare it with the run's)
    rec["ratio"] = rec["bytes"] / rec["full_bytes"]
    if split:
        scene = load_run_scene(run_dir, cfg, (split,), base=data_base, seed=cfg.seed)
        small = load_model(out, "cpu", cfg)
        a = evaluate_model(full, scene.frames(split), fps_warmup=0)
        b = evaluate_model(small, scene.frames(split), fps_warmup=0)
        rec.update({"split": split, "full": {k: a[k] for k in ("psnr", "ssim")},
                    "compact": {k: b[k] for k in ("psnr", "ssim")}, "delta_psnr": b["psnr"] - a["psnr"]})
    write_atomic(run_dir / "pack.json", json.dumps(rec, indent=1) + "\n", site="pack")
    return rec


def spec_of_config(pcfg) -> dict:
    """The compact spec of a run's `pack` config section (stdr.config.PackConfig)."""
    spec = {str(k): str(v) for k, v in (pcfg.codecs or {}).items()}
    if pcfg.get("finetune"):
        spec["finetune"] = int(pcfg.finetune)
    if pcfg.get("finetune_state"):
        spec["finetune_state"] = str(pcfg.finetune_state)
    if pcfg.get("sh_degree") is not None:
        spec["sh_degree"] = int(pcfg.sh_degree)
    return spec


def summary(rec: dict) -> str:
    line = (f"[stdr] {rec['file']}: {rec['bytes'] / 2**20:.2f} MiB of tensors, {rec['ratio']:.1%} of the model's "
            f"{rec['full_bytes'] / 2**20:.2f} MiB")
    if "delta_psnr" in rec:
        line += (f"; {rec['split']} PSNR {rec['compact']['psnr']:.2f} dB vs {rec['full']['psnr']:.2f} "
                 f"({rec['delta_psnr']:+.3f})")
    return line
