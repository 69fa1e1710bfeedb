"""Compact a trained run: prune its least significant Gaussians by contribution, fine-tune, save.

    stdr-tool compact RUN_DIR [--share S] [--steps 300] [--time-weight W] [--mask-bits 8|32] [--out DIR] [--split val]

Without --share / --time-weight / --mask-bits, the compact preset's values are used
(stdr/configs/compact/on.yaml, `compact=on` of stdr-train): one event removing the share that the
preset's events remove together, its time weight, its mask form for an STDR run, and its compact
file codecs (`pack`; STDR's derived mask only where the run allows it, else its 8-bit mask).

The run's checkpoint is copied to the new run folder (default RUN_DIR_compact) and training goes
on from it for --steps more iterations with `prune.share=SHARE prune.at=[<its step>]`: the
contribution pruning of a run trained with those keys (stdr/densify/prune.py), then a short
fine-tune at the learning rates the schedules give past the old end. The phase boundaries the
run already crossed are pinned to their values (a boundary that scales with optim.iterations
would move otherwise); the new folder is a complete run (config.yaml, checkpoint, metrics.json
with both the prune event and the final evaluation, and the compact model file model.stdrc with
its pack.json, in the preset's codecs: stdr-tool pack), and the original stays untouched.
"""
from __future__ import annotations

import argparse
import copy
import shutil
from pathlib import Path
from typing import Optional
from ..config import CONFIG_DIR
from ..store import resolve_schedule, load_config
from ..compact.pack import spec_of_config, pack
from ..compression.hooks import check_plugin_spec, fallback_of
from ..plugins import enabled_plugins, plugin_node
from ..train.run import run_training as run
from ..io.checkpoint import load_checkpoint, CKPT


def preset_values() -> dict:
    """The compact preset's keys (stdr/configs/compact/on.yaml) as this tool applies them to a
    trained run in one event: `share` = the fraction the preset's `prune.at` events remove
    together (1 - (1 - s)^events), `time_weight`, `mask_bits` (0: the preset keeps the mask's
    form), `pack` (the compact file's spec, stdr.compact.pack.spec_of_config of its `pack` node; {}
    when the preset writes no file)."""
    from omegaconf import OmegaConf

    node = OmegaConf.load(Path(CONFIG_DIR) / "compact" / "on.yaml")
    s, events = float(node.prune.share), len(node.prune.at)
    pk = OmegaConf.select(node, "pack", default=None)
    return {"share": 1.0 - (1.0 - s) ** events, "time_weight": float(node.prune.time_weight),
            "mask_bits": _as_change(int(OmegaConf.select(node, "stdr.mask_bits", default=32))),
            "pack": spec_of_config(pk) if pk is not None and pk.get("enabled") else {}}


def spec_for_run(cfg, spec: dict) -> tuple[dict, Optional[str]]:
    """`spec` as a trained run can take it: a plug-in's derived form that the run's keys do not
    allow (STDR's `stdr_mask: derived` on a run trained with stdr.mask_after_freeze=true) becomes
    that table's exact 8-bit form. Returns (spec, a note saying what changed, or None)."""
    out, notes = dict(spec), []
    for p in enabled_plugins(cfg):
        try:
            check_plugin_spec(p.plugin, plugin_node(cfg, p.name), out)
        except ValueError as err:
            moved = {k: c for k, c in fallback_of(p.plugin).items() if out.get(k) == "derived"}
            if not moved:
                raise
            out.update(moved)
            notes.append(f"{', '.join(f'{k}={c}' for k, c in moved.items())} in place of the preset's derived form: {err}")
    return out, "; ".join(notes) or None


def _as_change(bits: int) -> int:
    """A mask form as `compact` takes it: 8 (store in 8 bits) or 0 (keep; 32 is the float form)."""
    return 0 if bits == 32 else bits


def compact_config(cfg, step: int, share: float, steps: int, time_weight: float = 0.0, mask_bits: int = 0):
    """`cfg` (a run's loaded config) continued for `steps` iterations past `step` with one pruning
    event at `step`; every schedule boundary at or before `step` kept where it was. An error names
    the boundary when that cannot be done by pinning."""
    if steps < 1:
        raise ValueError(f"--steps {steps}: the fine-tune needs at least one step")
    old = resolve_schedule(cfg)
    new = copy.deepcopy(cfg)
    new.schedule = "${stdr_schedule:}"  # derived again from the new keys (the loaded one is the old run's)
    new.optim.iterations = int(step + steps)
    new.train.stop_at = new.train.deadline = new.train.start_by = None  # the old run's stops are not this one's
    new.train.resume = True
    new.prune.share = float(share)
    new.prune.at = [str(int(step))]
    new.prune.time_weight = float(time_weight)
    new.baseline.warmup = int(old.static_warmup_end)
    if mask_bits:
        if "stdr" not in [p.name for p in enabled_plugins(cfg)]:
            raise ValueError("--mask-bits: the run has no STDR mask (stdr.enabled=false)")
        new.stdr.mask_bits = int(mask_bits)
    for spec in enabled_plugins(cfg):  # plug-in phases resolved from the old run's length
        node = new[spec.name]
        for k, v in old.plugins.get(spec.name, {}).items():
            if k in node and isinstance(v, int) and not isinstance(v, bool):
                node[k] = v
    sched = resolve_schedule(new)

    def crossed(s):
        return sorted((e.step, e.key.replace(" (moved)", "")) for e in s.events
                      if e.step <= step and not e.key.startswith("prune"))
    if crossed(sched) != crossed(old):
        raise ValueError(f"compacting at step {step}: the run's schedule before it would change "
                         f"({crossed(old)} -> {crossed(sched)}); pin the moved keys in RUN_DIR/config.yaml")
    return new


def compact(run_dir: Path, share: float, steps: int = 300, time_weight: float = 0.0, out: Optional[Path] = None,
            split: Optional[str] = None, data_base: Optional[str] = None, mask_bits: int = 0,
            pack_spec: Optional[dict] = None) -> dict:
    """Prune run_dir's model by contribution, fine-tune `steps` iterations into `out`, evaluate, and
    write the compact file of the result with `pack_spec` (stdr.compression.file; None: its defaults)."""
    run_dir = Path(run_dir)
    out = Path(out) if out is not None else run_dir.with_name(run_dir.name + "_compact")
    src = run_dir / CKPT
    if not (run_dir / "config.yaml").is_file() or not src.is_file():
        raise FileNotFoundError(f"{run_dir}: not a trained run (config.yaml and {CKPT} are needed)")
    if out.exists():
        raise FileExistsError(f"{out} exists: choose another --out or remove it")
    cfg = load_config(run_dir / "config.yaml")
    step = int(load_checkpoint(src)["model"]["step"])
    new = compact_config(cfg, step, share, steps, time_weight, mask_bits)
    if split:
        new.data.eval_split = split
    new.name = f"{cfg.name}_compact"
    spec, note = spec_for_run(new, dict(pack_spec or {}))
    if note:
        print(f"[stdr] compact file: {note}")
    new.pack.enabled = False  # written once, below, with `spec` (not the old run's pack keys)
    (out / CKPT).parent.mkdir(parents=True)
    shutil.copy2(src, out / CKPT)
    res = run(new, out, data_base)
    rec = pack(out, spec=spec, split=new.data.eval_split, data_base=data_base)  # out/model.stdrc, out/pack.json
    print(f"[stdr] {rec['file']}: {rec['bytes'] / 2**20:.2f} MiB ({rec['ratio']:.1%} of the model's tensors)")
    return res


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(prog="stdr-tool compact", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", type=Path, help="a trained run folder")
    ap.add_argument("--share", type=float, default=None, help="fraction of the Gaussians removed, in (0, 1) "
                    "(default: what the compact preset's events remove together)")
    ap.add_argument("--steps", type=int, default=300, help="fine-tuning iterations after the pruning")
    ap.add_argument("--time-weight", type=float, default=None,
                    help="prune.time_weight (stdr/densify/prune.py; default: the compact preset's)")
    ap.add_argument("--out", type=Path, default=None, help="the new run folder (default RUN_compact)")
    ap.add_argument("--split", default=None, help="evaluation split (default: the run's data.eval_split)")
    ap.add_argument("--mask-bits", type=int, default=None, choices=(0, 8, 32),
                    help="STDR runs: 8 stores the frozen mask in 8 bits from the first fine-tuning step, 0 or 32 "
                    "keeps it (default: the compact preset's form for an STDR run, nothing for a plain one)")
    a = ap.parse_args(argv)
    pre = preset_values()
    share = pre["share"] if a.share is None else a.share
    if not 0.0 < share < 1.0:
        raise SystemExit(f"stdr-tool compact: --share {share}: use a fraction in (0, 1)")
    if a.mask_bits is not None:
        mask_bits = _as_change(a.mask_bits)
    else:  # the preset's mask form applies to an STDR run only
        mask_bits = pre["mask_bits"] if _has_stdr(a.run) else 0
    tw = pre["time_weight"] if a.time_weight is None else a.time_weight
    compact(a.run, share, a.steps, tw, a.out, a.split, mask_bits=mask_bits, pack_spec=pre["pack"])


def _has_stdr(run_dir: Path) -> bool:
    """Whether a run folder's config switches STDR on (the preset's mask form applies to it)."""
    cfg_path = Path(run_dir) / "config.yaml"
    if not cfg_path.is_file():
        raise SystemExit(f"stdr-tool compact: {run_dir}: not a trained run (no config.yaml)")
    return "stdr" in [p.name for p in enabled_plugins(load_config(cfg_path))]


if __name__ == "__main__":
    main()
