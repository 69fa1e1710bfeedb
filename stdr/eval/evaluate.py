"""Render a split, compute PSNR/SSIM/LPIPS, measure render FPS, write metrics.json.

Conventions, recorded in the output:
- PSNR and SSIM on the float render clamped to [0, 1] (no 8-bit round trip), full image
  including the background; SSIM as 3DGS (11x11 Gaussian, sigma 1.5, data range 1).
- LPIPS-VGG v0.1 with inputs mapped to [-1, 1] (official) unless eval.lpips_input="[0,1]".
- FPS: deformation + projection + rasterization per frame, after `fps_warmup` untimed frames,
  excluding image I/O and metrics (time.perf_counter; CUDA synchronized when on a GPU). The split
  is timed `fps_repeats` times (the quality pass is the first); `fps` is the median pass's frames
  per second and every pass is kept in `fps_passes`, so a reader sees the spread.
"""
from __future__ import annotations

import json
import os
import subprocess
import time
from pathlib import Path
from typing import Any, Optional

import numpy as np
import torch

from ..device import MEMORY_CONVENTION, synchronize
from ..model import model_bytes
from ..plugins import Reporting
from ..metrics import psnr, ssim
from ..render import use_compiled_projection
from .lpips import LPIPS, fetch_weights
from ..data.fetch import DataError
from ..densify.prune import seen_per_frame, significance
from ..errors import BadInput
from ..io.files import read_json, write_atomic, write_png
from .. import __version__, source_checkout


def make_lpips(eval_cfg) -> Optional[LPIPS]:
    """The LPIPS module, None when disabled or (with lpips=auto) when no weights can be had. Where
    eval.lpips_weights is unset and no search folder holds the weights, they are downloaded once
    into the user cache (eval.lpips_download; stdr.eval.lpips.fetch_weights)."""

    mode = str(eval_cfg.lpips).lower()
    if mode in ("false", "off", "0"):
        return None
    try:
        return LPIPS(eval_cfg.lpips_net, eval_cfg.lpips_weights, eval_cfg.lpips_input)
    except FileNotFoundError as e:
        missing = e
    why = ""
    if eval_cfg.lpips_weights is None and getattr(eval_cfg, "lpips_download", True):
        try:
            fetch_weights(eval_cfg.lpips_net)
            return LPIPS(eval_cfg.lpips_net, None, eval_cfg.lpips_input)
        except (DataError, OSError) as e:
            why = f" The download failed: {e}. `stdr-data download lpips` fetches them when online."
    if mode in ("true", "on", "1"):
        raise FileNotFoundError(f"{missing}{why}")
    print(f"[stdr] warning: LPIPS skipped (reported as null). {missing}{why}")
    return None




def timed_render(model, frame, step: int):
    """(render output, seconds): one frame's deformation + projection + rasterization, the FPS
    convention's unit (device synchronized before and after on a GPU)."""
    synchronize(model.device)
    t0 = time.perf_counter()
    out = model.render(frame.camera, frame.time, step)
    synchronize(model.device)
    return out, time.perf_counter() - t0


def warm_up(model, frames, step: int, n: int) -> None:
    """Untimed renders before timing (allocator, caches, JIT)."""
    for f in frames[:n]:
        model.render(f.camera, f.time, step)


def timed_pass(model, frames, step: int) -> dict[str, Any]:
    """One timed pass over `frames`: frames per second and the rows rendered per frame."""
    times, active = [], []
    for f in frames:
        times.append(timed_render(model, f, step)[1])
        active.append(model.last_active)
    return {"fps": float(len(times) / sum(times)), "active": active}


def fps_summary(passes: list[float]) -> dict[str, Any]:
    """`fps` (the median pass, robust to one disturbed pass) and every pass's value."""
    return {"fps": float(np.median(passes)), "fps_passes": [float(p) for p in passes]}


def size_summary(model, active: list[int]) -> dict[str, Any]:
    """Gaussians in the model and rendered per frame (after temporal culling; all rows when off)."""
    return {"num_gaussians": model.num_gaussians,
            "active_gaussians_mean": float(np.mean(active)), "active_gaussians_max": int(max(active)),
            "render_cull": model.cull_mode()}


@torch.no_grad()
def measure_fps(model, frames, step: Optional[int] = None, fps_warmup: int = 3,
                fps_repeats: int = 1) -> dict[str, Any]:
    """Render FPS alone, by the same convention as `evaluate_model`, with the active-row counts
    of the render settings it ran under (for re-timing a trained run on an idle machine, or
    under another `render.cull`: `stdr-eval RUN remeasure=fps`)."""
    _check_repeats(fps_repeats)
    model.eval()
    step = model.step if step is None else step
    warm_up(model, frames, step, fps_warmup)
    passes = [timed_pass(model, frames, step) for _ in range(fps_repeats)]
    return {**fps_summary([p["fps"] for p in passes]), **size_summary(model, passes[0]["active"])}


def _check_repeats(fps_repeats: int) -> None:
    if int(fps_repeats) < 1:
        raise ValueError(f"eval.fps_repeats={fps_repeats}: the split is timed at least once; use 1 or more")


@torch.no_grad()
def evaluate_model(model, frames, step: Optional[int] = None, lpips_fn=None, save_dir: Optional[Path] = None,
                   fps_warmup: int = 3, fps_repeats: int = 1, seen: bool = False) -> dict[str, Any]:
    """Render each frame with `model` (a stdr.model.DynamicGaussians, in eval mode) at the
    iteration `step` (default: the model's), and measure PSNR/SSIM/LPIPS and the render FPS
    (the quality pass and `fps_repeats` - 1 timing-only passes; see the module docstring).
    seen: also `seen_per_frame`, the mean share of the model that contributes to a frame
    (a score pass per frame after the timed passes; stdr.densify.prune.seen_per_frame)."""
    _check_repeats(fps_repeats)
    model.eval()
    step = model.step if step is None else step
    ps, ss, ls, times = [], [], [], []
    if save_dir is not None:
        save_dir.mkdir(parents=True, exist_ok=True)
    warm_up(model, frames, step, fps_warmup)
    active = []
    for i, f in enumerate(frames):
        out, sec = timed_render(model, f, step)
        times.append(sec)
        active.append(model.last_active)
        img = out.image.clamp(0, 1)
        ps.append(float(psnr(img, f.image)))
        ss.append(float(ssim(img, f.image)))
        if lpips_fn is not None:
            ls.append(float(lpips_fn(img, f.image)))
        if save_dir is not None:
            both = torch.cat([img, f.image], 1).cpu().numpy()
            write_png(save_dir / f"{i:03d}.png", (both[..., ::-1] * 255 + 0.5).astype(np.uint8))
    passes = [float(len(times) / sum(times))]
    passes += [timed_pass(model, frames, step)["fps"] for _ in range(int(fps_repeats) - 1)]
    seen_frac = None
    if seen:
        seen_frac = seen_per_frame(significance(model, frames, step)[0])
    return {
        "seen_per_frame": seen_frac,
        "psnr": float(np.mean(ps)), "ssim": float(np.mean(ss)),
        "lpips": float(np.mean(ls)) if ls else None,
        **fps_summary(passes), **size_summary(model, active),
        "num_frames": len(frames),
        "per_frame_psnr": ps,
        "per_frame_time": [float(f.time) for f in frames],  # normalized times, in per_frame_psnr's order
        "width": frames[0].camera.width, "height": frames[0].camera.height,
    }


# widest SIMD level first: float32 reductions (MKL, the compiled rasterizer) round differently per level
_ISA_LEVELS = ("avx512f", "avx2", "avx", "sse4_2", "neon", "asimd")


def machine_name(cpuinfo: str | None = None) -> str:
    """The CPU as results depend on it: model name, x86 family/model/stepping and the widest SIMD
    level (Linux /proc/cpuinfo, else platform), and the logical CPU count. Two machines sold
    under one model name ("AMD EPYC") give different float32 results when their family or ISA
    differ, so the label tells them apart. The GPU is `conventions.device_name`."""
    import platform
    if cpuinfo is None:
        try:
            cpuinfo = Path("/proc/cpuinfo").read_text()
        except OSError:
            cpuinfo = ""
    first = cpuinfo.strip().split("\n\n", 1)[0]  # the first processor's block of `key: value` lines
    f = {k.strip(): v.strip() for k, _, v in (line.partition(":") for line in first.splitlines())}
    parts = [f.get("model name") or platform.processor() or platform.machine()]
    if "cpu family" in f:
        parts.append(f"family {f['cpu family']} model {f.get('model', '?')} stepping {f.get('stepping', '?')}")
    flags = set((f.get("flags") or f.get("Features") or "").split())
    isa = next((x for x in _ISA_LEVELS if x in flags), None)
    if isa:
        parts.append(isa.upper().replace("_", "."))
    return f"{', '.join(parts)}, {os.cpu_count()} logical CPUs"


def metric_conventions(eval_cfg, lpips_fn, backend: str, device: torch.device) -> dict[str, Any]:
    """How the numbers were measured, including the device and rasterizer backend the run used."""
    return {
        "psnr": "float render clamped to [0,1], data range 1, full image",
        "ssim": "3DGS: 11x11 Gaussian window sigma 1.5, zero padding, data range 1",
        "lpips": None if lpips_fn is None else f"LPIPS-{lpips_fn.net} v0.1, inputs {lpips_fn.input_range}",
        "fps": "deformation + projection + rasterization, perf_counter, after warm-up, no I/O; "
               "median of fps_passes (the split timed eval.fps_repeats times)",
        "device": str(device),
        "device_name": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
        "machine": machine_name(),
        "torch_threads": torch.get_num_threads(),
        "mkl_cbwr": os.environ.get("MKL_CBWR"),  # MKL's reproducibility mode (set on import: AUTO,STRICT)
        "mkl_dynamic": os.environ.get("MKL_DYNAMIC"),  # MKL's dynamic threads (stdr-train: FALSE)
        "render_backend": backend,
        "memory": MEMORY_CONVENTION["cuda" if device.type == "cuda" else "cpu"],  # guard.peak_memory_mb
    }


def history_record(tag: str, iteration: int, split: str, train_seconds: float, res: dict[str, Any]) -> dict[str, Any]:
    """One evaluation as a point of the run's learning curve (the trainer's `history`, kept in
    checkpoints and history.json): tag (static_warmup | periodic | final), iteration, split,
    training seconds so far (evaluation excluded), frames rendered and the metrics."""
    return {"tag": tag, "iteration": iteration, "split": split, "train_seconds": train_seconds,
            "frames": res["num_frames"], **{k: res[k] for k in ("psnr", "ssim", "lpips", "num_gaussians")}}


def evaluate_state(state, frames, split: str, tag: str = "final", step: Optional[int] = None, log=None,
                   lpips_fn=None, save_dir: Optional[Path] = None, fps_warmup: int = 3, fps_repeats: int = 1,
                   seen: bool = False) -> dict[str, Any]:
    """Evaluate a run's model (`state.model`, a stdr.train.state.RunState) on `frames` of `split`
    (evaluate_model) and make the evaluation a point of its learning curve (`state.history`, with
    the training seconds so far); into an open `log` (RunLog), eval_<split>/* scalars."""
    res = evaluate_model(state.model, frames, step=state.step if step is None else step, lpips_fn=lpips_fn,
                         save_dir=save_dir, fps_warmup=fps_warmup, fps_repeats=fps_repeats, seen=seen)
    rec = history_record(tag, state.step, split, state.train_seconds, res)
    if tag == "final":  # the final evaluation names the checkpoint it evaluated
        rec["checkpoint"] = getattr(state, "checkpoint_id", None)
    state.history.append(rec)
    if log is not None:
        for k in ("psnr", "ssim", "lpips", "num_gaussians", "train_seconds"):
            if rec[k] is not None:
                log.scalar_if_open(f"eval_{split}/{k}", rec[k], state.step)
    return res


def training_facts(state) -> dict[str, Any]:
    """What a split's metrics.json entry says about the training, from the run's state:
    * train_cpu_seconds, and train_cpu_utilization = that / (train_seconds x the training's thread
      count): near 1, the run had the cores to itself; e.g. 0.5, another job took half the machine.
      None: unknown (a checkpoint from before it was recorded);
    * train_loss: the form of the training loss that ran (optim.fused_loss), `compiled` or `torch`
      (None: not recorded);
    * precision: the deformation network's arithmetic, `fp32` or `bf16` (baseline.precision as the
      run resolved `auto`);
    * prune: the contribution-pruning events (stdr.densify.prune), when there were any;
    * config_changes: the keys a resume changed (train.resume=override; stdr.train.resume), when any."""
    cpu, secs, threads = state.train_cpu_seconds, float(state.train_seconds or 0.0), state.train_threads
    out = {"train_cpu_seconds": cpu,
           "train_cpu_utilization": cpu / (secs * threads) if cpu is not None and threads and secs > 0 else None,
           "train_loss": state.train_loss,
           # the deformation network's arithmetic (baseline.precision as the run resolved it)
           "precision": getattr(getattr(state.model, "deform", None), "precision", None)}
    if state.prune_log:
        out["prune"] = list(state.prune_log)
    if getattr(state, "config_changes", None):  # resumed with changed keys: what changed at which step
        out["config_changes"] = list(state.config_changes)
    return out


def metrics_entry(res: dict[str, Any], split: str, state, max_gaussians: Optional[int]) -> dict[str, Any]:
    """The metrics.json entry of a run's final evaluation `res` of `split` (evaluate_model's
    result) from its state, live (stdr-train) or loaded (stdr-eval): the one builder. Adds the
    training seconds and iterations, the learning curve of `state.history` (which ends with this
    evaluation's record), its best and last points, the guard's summary (none for a run from
    before the guard) and the training facts (training_facts)."""
    curve = learning_curve(state.history, split)
    res.update({"train_seconds": state.train_seconds, "iterations": state.step, "curve": curve,
                **best_and_last(curve)})
    if state.guard is not None:
        res["guard"] = state.guard.summary(max_gaussians)
    res.update(training_facts(state))
    # the checkpoint these numbers are of (stdr.io.checkpoint.checkpoint_identity): readers compare
    # it with the run's last checkpoint, so a result never outlives the model it measured unnoticed
    res["checkpoint"] = getattr(state, "checkpoint_id", None)
    return res


def evaluate_run(state, scene, split: str, eval_cfg, max_gaussians: Optional[int] = None, log=None) -> dict[str, Any]:
    """The final evaluation of a run (a RunState, live or loaded) on `split` of `scene`: renders it,
    builds the metrics entry (metrics_entry), merges it into run_dir/metrics.json and writes the
    learning curve to run_dir/history.json. `max_gaussians`: densify.max_gaussians (0/None: no
    cap), for the guard's report."""
    lp = make_lpips(eval_cfg)
    if lp is not None:
        lp = lp.to(state.model.device)
    run_dir = Path(state.run_dir)
    save_dir = run_dir / "renders" / split if eval_cfg.save_images else None
    res = evaluate_state(state, scene.frames(split), split, tag="final", log=log, lpips_fn=lp, save_dir=save_dir,
                         fps_warmup=eval_cfg.fps_warmup, fps_repeats=eval_cfg.fps_repeats, seen=True)
    metrics_entry(res, split, state, int(max_gaussians or 0) or None)
    write_metrics(run_dir, split, res, state.model, eval_cfg, lp, scene.meta)
    write_atomic(run_dir / "history.json", json.dumps(state.history, indent=1), site="history")
    return res


CURVE_KEYS = ("step", "train_seconds", "psnr", "ssim", "lpips", "num_gaussians", "frames", "tag")


def learning_curve(history: list[dict[str, Any]], split: str) -> list[dict[str, Any]]:
    """The run's accuracy against training: its evaluations of `split` in step order (the static
    warm-up's, the periodic ones of train.eval_every, and the final one last), each
    {step, train_seconds (evaluation excluded), psnr, ssim, lpips (None unless computed),
    num_gaussians, frames (how many were rendered), tag}. A point from before a resume that
    lies past the final step (a run continued with fewer iterations) is left out."""
    final = [h for h in history if h["split"] == split and h["tag"] == "final"]
    last = final[-1]["iteration"] if final else None
    pts = [h for h in history if h["split"] == split and h["tag"] in ("static_warmup", "periodic")
           and (last is None or h["iteration"] < last)]
    pts = list({h["iteration"]: h for h in pts}.values())  # a resumed run may repeat a step: keep the latest
    pts.sort(key=lambda h: h["iteration"])
    out = [{"step": h["iteration"], **{k: h.get(k) for k in CURVE_KEYS if k != "step"}} for h in pts + final[-1:]]
    return out


def best_and_last(curve: list[dict[str, Any]]) -> dict[str, Any]:
    """metrics.json -> best (the curve's point of highest PSNR) and last (its final point), each
    {step, psnr, ssim, lpips, tag}: a run that collapsed and recovered, or ended below its best,
    shows both. Non-finite PSNRs are never the best."""
    keys = ("step", "psnr", "ssim", "lpips", "tag")
    pts = [p for p in curve if p.get("psnr") is not None and np.isfinite(p["psnr"])]
    best = max(pts, key=lambda p: p["psnr"]) if pts else None
    return {"best": None if best is None else {k: best.get(k) for k in keys},
            "last": {k: curve[-1].get(k) for k in keys} if curve else None}


def code_version(exclude: tuple[str, ...] = (), root=None) -> dict[str, Any]:
    """Which code wrote a number: the stdr package version, and, in a git checkout, its commit
    and whether tracked files had uncommitted changes (None outside a checkout). `exclude`:
    folders of the checkout whose changes do not count (a study's own tables, rewritten as it runs).
    `root`: the checkout (default: the one this package runs from)."""
    root = source_checkout() if root is None else root
    out: dict[str, Any] = {"version": __version__, "commit": None, "dirty": None}
    if root is None:  # an installed copy: no commit to name (a checkout that holds the venv is not it)
        return out
    try:
        head = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True,
                              timeout=10)
        if head.returncode != 0:
            return out
        status = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no", "--", ".",
                                 *(f":(exclude){e}" for e in exclude)], capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.TimeoutExpired):
        return out
    out["commit"] = head.stdout.strip()
    out["dirty"] = bool(status.stdout.strip()) if status.returncode == 0 else None
    return out


def commit_stamp(code: Optional[dict[str, Any]]) -> str:
    """The one printed form of a code_version() record: the short commit ('3407bc9'), '+dirty' when
    tracked files differed from it, or 'version V (no commit)' outside a checkout."""
    code = code or {}
    if not code.get("commit"):
        return f"version {code.get('version', '?')} (no commit)"
    return str(code["commit"])[:7] + ("+dirty" if code.get("dirty") else "")


def write_metrics(run_dir: Path, split: str, res: dict[str, Any], model, eval_cfg, lpips_fn,
                  data_meta: dict[str, Any]) -> None:
    """Add the conventions, the data's description and each plug-in's statistics (under its
    name: memory, timings, statistics of its state) to `res`, and merge it into
    run_dir/metrics.json under `split` (atomically)."""
    conv = metric_conventions(eval_cfg, lpips_fn, model.backend, model.device)
    compiled = use_compiled_projection(model.backend, model.cfg.render.get("compiled_projection"))
    conv["render_projection"] = "compiled" if compiled else "torch"  # projection + SH: extension or torch twin
    res.update({"conventions": conv,
                "data": data_meta,  # how the scene was read (split, scale, intrinsics, ...)
                "code": code_version()})  # the checkout that wrote this entry
    res["model_mb"] = model_bytes(model) / 2 ** 20
    for p in model.plugins:  # (every plug-in's name is in it: {} for one without the Reporting role)
        res[p.name] = p.stats(model.params) if isinstance(p, Reporting) else {}
    path = run_dir / "metrics.json"
    try:
        metrics = read_json(path, "metrics") if path.is_file() else {}
    except BadInput:  # damaged: this evaluation writes it anew (its other splits were unreadable anyway)
        metrics = {}
    if not isinstance(metrics, dict):
        metrics = {}
    metrics[split] = res
    save_metrics(path, metrics)


def save_metrics(path: Path, metrics: dict[str, Any]) -> None:
    """Write a run's metrics.json atomically (a reader never sees half a file)."""
    write_atomic(path, json.dumps(metrics, indent=1))
