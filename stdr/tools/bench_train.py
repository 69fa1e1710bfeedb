"""Milliseconds per training step, split into sections, at fixed Gaussian counts and resolutions.

For each experiment (e.g. dnerf_deform, dnerf_deform_stdr) and each resolution (data.max_width):
1. Build the experiment's trainer (the real training step of stdr.train.Trainer, nothing copied).
2. For each count N, replace its Gaussians by N copies of a source set (a finished run's
   Gaussians with `--run`, else the trainer's initial points), jittered as `stdr-tool
   cost-probe` does, and set the step to the end of the schedule minus the steps to time, so
   every phase is on: the deformation network, STDR's frozen mask and separated field, the
   full SH degree. Densification is off (N stays fixed); its per-step statistics still run.
3. Time `--iters` steps after `--warmup-iters` untimed ones. Per step: the median wall time,
   and the mean of each section of the trainer's profiler: deformation forward (`deform`:
   conditioning and deformed rows), `render_fwd` (projection, SH and rasterizer), `loss`, the
   plug-ins' and the baseline's regularizers, `backward`, `optimizer`, `densify`. The backward
   is split where its gradient reaches the projection's means2d and conics (`loss+rasterizer`), then the
   deformed Gaussians (`projection+sh`); the rest is the deformation network's and the
   regularizers' backward (`deformation+reg`). On CUDA every section boundary synchronizes.

A fixed `torch.mm` workload (2048², fp32) is timed before and after, so results from machines
under other load can be compared as ratios (`ms / mm_ms`).

    stdr-tool bench-train --run RUN --gaussians 10000 20000 50000 --res 200 400 \\
        --experiments dnerf_deform dnerf_deform_stdr --out research/measurements/bench_train_cpu \\
        -- data.path=../shared/data/dnerf/standup budget=cpu
    stdr-tool bench-train --compare BEFORE.json AFTER.json --out research/measurements/train_speed_cpu/bench_train/bench_train_cpu_compare
"""
from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch

from ..store import compose_config
from ..device import synchronize
from ..eval.evaluate import code_version, commit_stamp, machine_name
from ..eval.table import fmt_value as fmt
from ..eval.table import markdown_table, write_outputs
from ..gaussians import GAUSSIAN_KEYS
from ..train.timing import Profiler
from .bench_bounds import bound_rows, machine_rates, mm_reference, tally_steps
from ..train.trainer import Trainer
from ..io.checkpoint import load_checkpoint
from ..syncs import DeviceSyncCounter, OpCounter, SyncCounter

SECTIONS = ("deform", "render_fwd", "loss", "stdr_reg", "deform_reg", "backward", "optimizer", "densify")
PARTS = ("loss+rasterizer", "projection+sh", "deformation+reg")



def run_gaussians(run: Path) -> dict:
    """A finished run's Gaussian parameters (CPU tensors) from its checkpoint (format 1 or 2)."""
    ck = load_checkpoint(Path(run) / "checkpoints" / "last.pt")
    return {k: v.cpu() for k, v in (ck["model"]["params"] if "model" in ck else ck["params"]).items()}


def replicate(params: dict, n: int, gen: torch.Generator) -> dict:
    """Resample the Gaussians of `params` to n: copies jittered by half their scale."""
    import math

    n0 = params["means"].shape[0]
    idx = torch.randint(0, n0, (n,), generator=gen) if n < n0 else torch.arange(n) % n0
    copies = max(1.0, n / n0)
    out = {k: params[k][idx].clone() for k in GAUSSIAN_KEYS}
    sigma = out["scales"].exp()
    out["means"] += 0.5 * sigma * torch.randn(n, 3, generator=gen)
    out["scales"] -= 0.5 * math.log(copies)
    return out

def source_params(run: Path | None, trainer: Trainer) -> dict:
    if run is None:
        return {k: trainer.state.model.params[k].detach().cpu() for k in GAUSSIAN_KEYS}
    return run_gaussians(run)


def bench_one(tr: Trainer, source: dict, n: int, iters: int, warmup_iters: int, seed: int = 0,
              rates: dict | None = None) -> dict:
    """Time `iters` training steps of `tr` with n Gaussians replicated from `source`."""
    tr.replace_gaussians(replicate(source, n, torch.Generator().manual_seed(seed)))
    total = warmup_iters + iters
    tr.step = max(tr.cfg.optim.iterations - total, tr.state.model.warmup)
    dev = tr.device
    times, active = [], []
    for i in range(total):
        if i == warmup_iters:
            tr.profile = Profiler(split_backward=True, device=dev, after="deformation+reg")
        synchronize(dev)
        t0 = time.perf_counter()
        info = tr.train_step()
        synchronize(dev)
        if i >= warmup_iters:
            times.append(time.perf_counter() - t0)
            active.append(info["active"])
    prof = tr.profile
    # machine-independent proxies, counted on steps after the timed ones (the counters slow a step)
    # (and, on a GPU, the synchronizing calls the CUDA runtime reports, without the profiler's own)
    ops, syncs, n_count = 0, 0, 3
    dev_syncs = 0 if dev.type == "cuda" else None
    tr.step = min(tr.step, tr.cfg.optim.iterations - 2 * n_count)
    tr.profile = Profiler()  # the training one: no syncs
    for _ in range(n_count):
        with SyncCounter() as sc, OpCounter() as oc:
            tr.train_step()
        ops, syncs = ops + oc.ops, syncs + sc.total
        if dev_syncs is not None:
            with DeviceSyncCounter() as dc:
                tr.train_step()
            dev_syncs += dc.total
    work = None
    if rates is not None:  # FLOPs and bytes per section, on one more step (bench_bounds)
        tr.step = min(tr.step, tr.cfg.optim.iterations - 1)
        work = tally_steps(tr, rates, after="deformation+reg")
    return {"work": work, "ops_per_step": ops / n_count, "syncs_per_step": syncs / n_count,
            "device_syncs_per_step": None if dev_syncs is None else dev_syncs / n_count,
            "gaussians": tr.state.model.num_gaussians, "active_mean": statistics.mean(active),
            "ms": statistics.median(times) * 1e3, "ms_mean": statistics.mean(times) * 1e3,
            "sections_ms": {k: v * 1e3 / iters for k, v in prof.seconds.items()},
            "backward_parts_ms": {k: v * 1e3 / iters for k, v in prof.backward_parts.items()},
            "step": tr.step, "iters": iters}


def run(experiments: list[str], resolutions: list[int], counts: list[int], overrides: list[str],
        source_run: Path | None, iters: int, warmup_iters: int, bounds: bool = True) -> dict:
    rows = []
    fixed = ["densify.refine_start=1000000000", "train.progress=false", "eval.lpips=false",
             "train.eval_every=0", "train.eval_at_warmup_end=false"]
    mm_before, rates = None, None
    for exp in experiments:
        for res in resolutions:
            cfg = compose_config([f"experiment={exp}", *overrides, f"data.max_width={res}", *fixed])
            with tempfile.TemporaryDirectory() as tmp:
                tr = Trainer(cfg, tmp, splits=("train",))
                if mm_before is None:
                    mm_before = mm_reference(tr.device)
                    rates = machine_rates(tr.device) if bounds else None
                cam = tr.scene.frames("train")[0].camera
                if cam.width < res:
                    print(f"[bench-train] {exp}: the scene's images are {cam.width}x{cam.height}, below "
                          f"data.max_width={res} (images are never upscaled)", file=sys.stderr)
                src = source_params(source_run, tr)
                for n in counts:
                    r = bench_one(tr, src, n, iters, warmup_iters, rates=rates)
                    r.update({"experiment": exp, "stdr": bool(cfg.stdr.enabled), "width": cam.width,
                              "height": cam.height, "backend": tr.backend, "device": str(tr.device)})
                    rows.append(r)
                    print(f"{exp:>22} {cam.width}x{cam.height} N={r['gaussians']:>7,}: {r['ms']:7.1f} ms/step  "
                          + " ".join(f"{k}={v:.1f}" for k, v in r["sections_ms"].items()), flush=True)
    dev = torch.device(rows[0]["device"]) if rows else torch.device("cpu")
    mm_after = mm_reference(dev)
    return {"rows": rows, "mm_ms_before": mm_before, "mm_ms_after": mm_after,
            "mm_gflops": 2 * 2048 ** 3 / (min(mm_before or mm_after, mm_after) * 1e-3) / 1e9,
            "threads": torch.get_num_threads(), "machine": machine_name(), "platform": platform.platform(),
            "torch": torch.__version__, "code": code_version(), "overrides": overrides,
            "rates": rates, "source_run": None if source_run is None else str(source_run), "iters": iters,
            "warmup_iters": warmup_iters}


def markdown(res: dict) -> str:
    mm = min(res["mm_ms_before"], res["mm_ms_after"])
    head = ["experiment", "res", "Gaussians", "active", "ms/step", "÷ mm", "ops/step", "syncs/step", "CUDA syncs/step", *SECTIONS,
            *(f"bwd: {p}" for p in PARTS)]
    body = []
    for r in res["rows"]:
        sec, parts = r["sections_ms"], r["backward_parts_ms"]
        body.append([r["experiment"], f"{r['width']}x{r['height']}", f"{r['gaussians']:,}", f"{r['active_mean']:,.0f}",
                     fmt(r["ms"], "{:.1f}"), fmt(r["ms"] / mm, "{:.1f}"), fmt(r.get("ops_per_step"), "{:.0f}"),
                     fmt(r.get("syncs_per_step"), "{:.1f}"),
                     fmt(r.get("device_syncs_per_step"), "{:.1f}"), *(fmt(sec.get(k), "{:.1f}") for k in SECTIONS), *(fmt(parts.get(p), "{:.1f}") for p in PARTS)])
    return "\n".join([
        "Training step time by section (stdr-tool bench-train): median ms per step, sections as the mean ms "
        "per step of the trainer's profiler; `bwd:` splits the backward where its gradient reaches the "
        "projection's means2d and conics and then the deformed Gaussians; ops/step: ATen operators dispatched "
        "(forward and backward), syncs/step: host syncs (stdr.syncs), over 3 further steps; CUDA syncs/step: "
        "those the CUDA runtime reports (torch.cuda.set_sync_debug_mode), on a GPU, over 3 more.", "",
        f"Machine: {res['machine']}, {res['threads']} threads, torch {res['torch']}; torch.mm 2048² fp32: "
        f"{res['mm_ms_before']:.1f} ms before, {res['mm_ms_after']:.1f} ms after ({res['mm_gflops']:.0f} GFLOP/s); "
        f"÷ mm = ms/step over the faster mm time. {res['iters']} timed steps after {res['warmup_iters']} untimed; "
        f"overrides: {' '.join(res['overrides']) or '–'}.", "",
        markdown_table(head, body), "", *bounds_markdown(res)])


def bounds_markdown(res: dict) -> list[str]:
    """The second table: each section's time against its bound (stdr.tools.bench_bounds), or nothing
    for a result taken without it."""
    rates = res.get("rates")
    body = [[r["experiment"], f"{r['width']}x{r['height']}", f"{r['gaussians']:,}", *line]
            for r in res["rows"] for line in bound_rows(r, SECTIONS, PARTS)]
    if not rates or not body:
        return []
    head = ["experiment", "res", "Gaussians", "section", "ms", "GFLOP", "MB moved", "bound ms", "× bound", "limited by"]
    return ["Each section against its bound (stdr.tools.bench_bounds): an operator's bound is the larger of "
            "its matrix products' FLOPs at the measured matrix-multiply rate of its precision and the bytes "
            "of its tensor arguments and results at the measured memory bandwidth; a section's bound is the "
            "sum over its operators, on one more step; `limited by`: which of the two makes most of the bound.", "",
            f"Measured here: torch.mm 2048² {rates['fp32'] / 1e9:.0f} GFLOP/s in fp32, {rates['bf16'] / 1e9:.0f} "
            f"GFLOP/s in bf16; copy_ of 256 MiB {rates['bandwidth'] / 1e9:.1f} GB/s (read + write).", "",
            markdown_table(head, body), ""]


def compare(before: dict, after: dict, labels=("before", "after")) -> tuple[str, dict]:
    """Two bench-train results side by side: for every (experiment, resolution, Gaussians) both
    have, the ms per step of each, the speed-up, and the sections and backward parts of each.
    Rows one side lacks are listed, never compared. Returns (Markdown, the rows as a dict)."""
    def key(r):
        return (r["experiment"], r["width"], r["height"], r["gaussians"])
    b = {key(r): r for r in before["rows"]}
    a = {key(r): r for r in after["rows"]}
    common = [k for k in b if k in a]
    missing = sorted({k for k in list(a) + list(b) if k not in common})
    head = ["experiment", "res", "Gaussians", f"ms/step {labels[0]}", f"ms/step {labels[1]}", "speed-up",
            *(f"{p} ({labels[0]} → {labels[1]})" for p in ("deform", "render_fwd", "loss", "optimizer")),
            *(f"bwd: {p} ({labels[0]} → {labels[1]})" for p in PARTS)]
    body, rows = [], []
    for k in common:
        rb, ra = b[k], a[k]
        body.append([k[0], f"{k[1]}x{k[2]}", f"{k[3]:,}", fmt(rb["ms"], "{:.1f}"), fmt(ra["ms"], "{:.1f}"),
                     fmt(rb["ms"] / ra["ms"], "{:.2f}x"),
                     *(f"{fmt(rb['sections_ms'].get(p), '{:.1f}')} → {fmt(ra['sections_ms'].get(p), '{:.1f}')}"
                       for p in ("deform", "render_fwd", "loss", "optimizer")),
                     *(f"{fmt(rb['backward_parts_ms'].get(p), '{:.1f}')} → {fmt(ra['backward_parts_ms'].get(p), '{:.1f}')}"
                       for p in PARTS)])
        rows.append({"experiment": k[0], "width": k[1], "height": k[2], "gaussians": k[3], "ms_before": rb["ms"],
                     "ms_after": ra["ms"], "speedup": rb["ms"] / ra["ms"]})
    code = lambda r: commit_stamp(r.get("code"))  # noqa: E731
    md = "\n".join([
        f"Training step, {labels[0]} and {labels[1]} (stdr-tool bench-train --compare): median ms per step; "
        "sections are the mean ms per step of the trainer's profiler.", "",
        f"{labels[0]}: code {code(before)}, torch.mm 2048² {min(before['mm_ms_before'], before['mm_ms_after']):.1f} ms; "
        f"{labels[1]}: code {code(after)}, torch.mm 2048² {min(after['mm_ms_before'], after['mm_ms_after']):.1f} ms "
        f"({before['machine']} / {after['machine']}; overrides {' '.join(after['overrides']) or '–'}).", "",
        markdown_table(head, body), ""]
        + ([f"Not compared (in one file only): {', '.join(f'{e} {w}x{h} {n:,}' for e, w, h, n in missing)}", ""]
           if missing else []))
    return md, {"rows": rows, "before": {"code": before.get("code"), "mm_ms": before["mm_ms_after"]},
                "after": {"code": after.get("code"), "mm_ms": after["mm_ms_after"]}, "labels": list(labels)}


def main(argv=None) -> None:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["--compare"]:
        cp = argparse.ArgumentParser(prog="stdr-tool bench-train --compare",
                                     description="two bench-train JSON files side by side")
        cp.add_argument("--compare", nargs=2, type=Path, metavar=("BEFORE.json", "AFTER.json"), required=True)
        cp.add_argument("--labels", nargs=2, default=["before", "after"])
        cp.add_argument("--out", type=Path, default=None, help="write OUT.json and OUT.md")
        c = cp.parse_args(argv)
        loaded = []
        for f in c.compare:
            try:
                loaded.append(json.loads(f.read_text()))
            except (OSError, ValueError) as e:
                raise SystemExit(f"--compare {f}: {e} (give the .json a bench-train --out wrote)")
            if "rows" not in loaded[-1]:
                raise SystemExit(f"--compare {f}: no 'rows' (not a bench-train result)")
        md, res = compare(*loaded, labels=tuple(c.labels))
        print(md, end="")
        write_outputs(c.out, md, res)
        return
    overrides = argv[argv.index("--") + 1:] if "--" in argv else []
    ap = argparse.ArgumentParser(prog="stdr-tool bench-train", description=__doc__.split("\n")[0],
                                 epilog="Hydra overrides for every experiment follow --")
    ap.add_argument("--experiments", nargs="+", required=True)
    ap.add_argument("--gaussians", type=int, nargs="+", default=[10000, 20000, 50000])
    ap.add_argument("--res", type=int, nargs="+", default=[200, 400], help="data.max_width values")
    ap.add_argument("--run", type=Path, default=None, help="a finished run whose Gaussians are replicated")
    ap.add_argument("--iters", type=int, default=10)
    ap.add_argument("--warmup-iters", type=int, default=3)
    ap.add_argument("--out", type=Path, default=None, help="write OUT.json and OUT.md")
    ap.add_argument("--no-bounds", action="store_true",
                    help="skip the machine's rates and the per-section bounds (one more step per row)")
    a = ap.parse_args(argv[:argv.index("--")] if "--" in argv else argv)
    if a.iters < 1 or a.warmup_iters < 0:
        raise SystemExit("--iters must be at least 1 and --warmup-iters at least 0")
    if a.run is not None and not (a.run / "checkpoints" / "last.pt").is_file():
        raise SystemExit(f"--run {a.run}: no checkpoints/last.pt there (give a finished run's folder)")
    res = run(a.experiments, a.res, a.gaussians, overrides, a.run, a.iters, a.warmup_iters, bounds=not a.no_bounds)
    md = markdown(res)
    print(md, end="")
    write_outputs(a.out, md, res)


if __name__ == "__main__":
    main()
