"""Rasterizer benchmark: forward and forward+backward time per backend, size and resolution.

Scenes are random Gaussians in a cube in front of the camera, sized so that their 3-sigma
footprints cover the image `--coverage` times over (sum of ellipse areas / image area), with
opacities uniform in [0.05, 1] and anisotropic scales. Timings are medians over `--repeats`
after one warm-up call and cover rasterization alone (projected inputs -> image + gradients),
and, separately, the whole `render()` (projection, SH, rasterization).

Throughput is reported as pair evaluations per second of the forward: the (pixel, Gaussian)
alpha evaluations a tile rasterizer with exact ellipse/tile culling must do (for each 16x16
tile, its pixels times its list entries up to the last one any pixel composites), divided by
the forward time, and as a fraction of the machine's fp32 peak (`--peak-gflops`, 600 on these
2 AVX-512 cores) at `--flop-per-pair` (40) flop per evaluation. Each row runs in its own
process, so `peak_mb` is the growth of peak resident memory (CUDA: peak allocated) over the
scene's inputs during the rasterizer calls.

    stdr-tool bench-rasterizer --backends cpu reference --n 10000 100000 \
        --res 256 400 800 --json outputs/bench/rasterizer.json
"""
from __future__ import annotations

import argparse
import json
import math
import platform
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch


from stdr.cameras import Camera
from stdr.device import synchronize
from stdr.render import DEFAULT_TILE, rasterize, render, resolve_backend
from stdr.render.projection import project_gaussians
from stdr.extension import load_extension
from stdr.io.files import make_folder, write_atomic


def make_scene(n: int, res: int, coverage: float, seed: int = 0, device: str = "cpu"):
    g = torch.Generator().manual_seed(seed)
    dist, fov = 4.0, 0.6
    f = 0.5 * res / math.tan(0.5 * fov)
    # the cube [-h, h]^3 fills the view at the distance of its centre
    h = dist * math.tan(0.5 * fov)
    means = (torch.rand(n, 3, generator=g) * 2 - 1) * h
    # 3-sigma ellipse area per Gaussian ~ pi (3 s f / z)^2 -> solve for s
    s = math.sqrt(coverage * res * res / (n * math.pi * 9.0)) * dist / f
    aniso = torch.exp((torch.rand(n, 3, generator=g) * 2 - 1) * math.log(2.0))
    scales = s * aniso / aniso.prod(-1, keepdim=True) ** (1 / 3)
    quats = torch.randn(n, 4, generator=g)
    opac = torch.rand(n, generator=g) * 0.95 + 0.05
    sh = torch.randn(n, 1, 3, generator=g) * 0.5
    R = torch.eye(3)
    t = torch.tensor([0.0, 0.0, dist])
    cam = Camera(R=R, t=t, fx=f, fy=f, cx=res / 2, cy=res / 2, width=res, height=res)
    tensors = [x.to(device) for x in (means, quats, scales, opac, sh)]
    return tensors, cam  # render() moves the camera's tensors to the Gaussians' device


def timed(fn, repeats: int, device: str) -> float:
    fn()  # warm-up (and JIT build)
    synchronize(torch.device(device))
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        synchronize(torch.device(device))
        times.append(time.perf_counter() - t0)
    return statistics.median(times) * 1e3


def pair_work(p, width, height, tile: int = 16) -> tuple[int, int]:
    """(pair evaluations, Gaussian-tile pairs) of a tile rasterizer with exact ellipse culling.

    Evaluations = sum over tiles of (tile pixels) x (tile list entries up to the tile's last
    composited one): the alpha evaluations every pixel of the tile performs in the forward.
    """
    c = lambda x: x.detach().cpu().contiguous()  # noqa: E731
    _, _, last, ids, *_ = load_extension("cpu").forward(
        c(p.means2d), c(p.conics), c(p.opacities), c(p.depths[:, None]), c(p.depths),
        p.radii.int().cpu().contiguous(), width, height, tile)
    ntx, nty = -(-width // tile), -(-height // tile)
    padded = torch.zeros(nty * tile, ntx * tile, dtype=last.dtype)
    padded[:height, :width] = last
    per_tile = padded.reshape(nty, tile, ntx, tile).amax(dim=(1, 3))
    return int(per_tile.sum()) * tile * tile, int(ids.numel())


def measure_row(backend: str, n: int, res: int, coverage: float, repeats: int, tile: int,
                reference_device: str = "cpu") -> dict:
    # the compiled backends run on their own device; the pure-torch reference on either
    device = {"cuda": "cuda", "cpu": "cpu"}.get(backend, reference_device)
    backend = resolve_backend(backend, device)
    tile = tile or DEFAULT_TILE[backend]
    (means, quats, scales, opac, sh), cam = make_scene(n, res, coverage, device=device)
    p = project_gaussians(means, quats, scales, opac, cam)
    evals, n_pairs = pair_work(p, res, res, 16)
    params = [x.clone().requires_grad_(True) for x in (means, quats, scales, opac, sh)]
    m2 = p.means2d.detach().requires_grad_(True)
    con = p.conics.detach().requires_grad_(True)
    op = p.opacities.detach().requires_grad_(True)
    feats = torch.cat([torch.rand(n, 3, device=device), p.depths[:, None].detach()], 1).requires_grad_(True)
    depths, radii = p.depths.detach(), p.radii

    def fwd():
        with torch.no_grad():
            rasterize(m2, con, op, feats, depths, radii, res, res, tile, backend)

    def fwd_bwd():
        acc, T = rasterize(m2, con, op, feats, depths, radii, res, res, tile, backend)
        (acc.sum() + T.sum()).backward()

    def render_fb(compiled_projection=True):
        out = render(*params, cam, 0, backend=backend, tile_size=tile, compiled_projection=compiled_projection)
        (out.image.sum() + out.depth.sum()).backward()

    if device == "cuda":
        torch.cuda.synchronize()
        base = torch.cuda.memory_allocated()
        torch.cuda.reset_peak_memory_stats()
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t_f = timed(fwd, repeats, device)
    t_fb = timed(fwd_bwd, repeats, device)
    if device == "cuda":
        peak = (torch.cuda.max_memory_allocated() - base) / 2**20
    else:  # growth of the process's peak resident set over the scene's inputs
        peak = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss0) / 1024
    t_r = timed(render_fb, max(1, repeats // 2), device)
    # compiled backends: the same render() with the projection and SH in torch (render.compiled_projection=false)
    t_rt = None if backend == "reference" else timed(lambda: render_fb(False), max(1, repeats // 2), device)
    return dict(backend=backend, device=device, n=n, width=res, height=res, tile=tile, coverage=coverage,
                fwd_ms=t_f, fwd_bwd_ms=t_fb, render_fwd_bwd_ms=t_r, render_torch_projection_fwd_bwd_ms=t_rt,
                peak_mb=peak, pairs=n_pairs,
                pair_evals=evals, threads=torch.get_num_threads(), repeats=repeats)


def main(argv=None):
    ap = argparse.ArgumentParser(prog="stdr-tool bench-rasterizer", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--backends", nargs="+", default=["cpu", "reference"])
    ap.add_argument("--n", nargs="+", type=int, default=[10_000, 100_000, 1_000_000])
    ap.add_argument("--res", nargs="+", type=int, default=[256, 400, 800])
    ap.add_argument("--coverage", type=float, default=5.0)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--tile", type=int, default=0, help="tile size (0 = each backend's default)")
    ap.add_argument("--peak-gflops", type=float, default=600.0)
    ap.add_argument("--flop-per-pair", type=float, default=40.0)
    ap.add_argument("--max-ref-n", type=int, default=100_000,
                    help="skip the reference backend above this many Gaussians (time, memory)")
    ap.add_argument("--reference-device", default="cpu", choices=["cpu", "cuda"],
                    help="where the pure-torch reference runs (the compiled backends run on their own)")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--markdown", type=Path, default=None, help="also write the table as Markdown")
    ap.add_argument("--one", default=None, help=argparse.SUPPRESS)  # internal: one row as JSON
    args = ap.parse_args(argv)
    if args.one:
        print(json.dumps(measure_row(**json.loads(args.one))))
        return

    rows = []
    header = (f"{'backend':>9} {'N':>8} {'res':>5} {'fwd ms':>9} {'fwd+bwd ms':>11} "
              f"{'render f+b':>11} {'torch proj':>11} {'pairs/s':>9} {'%peak':>6} {'peak MB':>8}")
    print(header)
    for n in args.n:
        for res in args.res:
            for b in args.backends:
                if b == "reference" and n > args.max_ref_n:
                    print(f"{b:>9} {n:>8} {res:>5}   skipped (reference; --max-ref-n)")
                    continue
                # one process per row: a clean peak-memory reading, no allocator carry-over
                spec = dict(backend=b, n=n, res=res, coverage=args.coverage, repeats=args.repeats,
                            tile=args.tile, reference_device=args.reference_device)
                proc = subprocess.run([sys.executable, "-m", "stdr.tools.bench_rasterizer", "--one", json.dumps(spec)],
                                      capture_output=True, text=True)
                if proc.returncode != 0:
                    print(proc.stderr[-2000:], file=sys.stderr)
                    raise SystemExit(f"row {spec} failed")
                row = json.loads(proc.stdout.strip().splitlines()[-1])
                rate = row["pair_evals"] / (row["fwd_ms"] / 1e3)
                row.update(pair_evals_per_s=rate,
                           peak_fraction=rate * args.flop_per_pair / (args.peak_gflops * 1e9))
                rows.append(row)
                rt = row.get("render_torch_projection_fwd_bwd_ms")
                print(f"{label(row):>9} {n:>8} {res:>5} {row['fwd_ms']:>9.1f} "
                      f"{row['fwd_bwd_ms']:>11.1f} {row['render_fwd_bwd_ms']:>11.1f} "
                      f"{'-' if rt is None else f'{rt:.1f}':>11} "
                      f"{rate:>9.2e} {100 * row['peak_fraction']:>5.1f}% {row['peak_mb']:>8.0f}",
                      flush=True)
    # speed-ups against the reference where both ran
    ref = {(r["n"], r["width"]): r for r in rows if r["backend"] == "reference"}
    for r in rows:
        k = (r["n"], r["width"])
        if r["backend"] != "reference" and k in ref:
            r["speedup_fwd_bwd_vs_reference"] = ref[k]["fwd_bwd_ms"] / r["fwd_bwd_ms"]
            print(f"speed-up {r['backend']} vs reference, N={k[0]} {k[1]}^2: "
                  f"{r['speedup_fwd_bwd_vs_reference']:.1f}x (fwd+bwd)")
    if args.json:
        make_folder(args.json.parent)
        meta = dict(machine=platform.processor() or platform.machine(), torch=torch.__version__,
                    threads=torch.get_num_threads(), argv=sys.argv[1:])
        write_atomic(args.json, json.dumps(dict(meta=meta, rows=rows), indent=1), "table")
        print(f"wrote {args.json}")
    if args.markdown:
        make_folder(args.markdown.parent)
        write_atomic(args.markdown, markdown_table(rows, args.peak_gflops), "table")
        print(f"wrote {args.markdown}")


def label(row: dict) -> str:
    """'cpu', 'cuda', or 'reference (cuda)' for the pure-torch reference on a GPU."""
    dev = row.get("device", "cpu")
    return row["backend"] if row["backend"] != "reference" or dev == "cpu" else f"reference ({dev})"


def markdown_table(rows, peak_gflops) -> str:
    out = ["| backend | N | image | fwd ms | fwd+bwd ms | render() fwd+bwd ms | render() with torch projection "
           f"| pair evals/s | % of {peak_gflops:.0f} GFLOP/s | peak MB | vs reference (fwd+bwd) |",
           "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        sp = r.get("speedup_fwd_bwd_vs_reference")
        rt = r.get("render_torch_projection_fwd_bwd_ms")
        out.append(f"| {label(r)} | {r['n']:,} | {r['width']}x{r['height']} | {r['fwd_ms']:.1f} "
                   f"| {r['fwd_bwd_ms']:.1f} | {r['render_fwd_bwd_ms']:.1f} | {'' if rt is None else f'{rt:.1f}'} "
                   f"| {r['pair_evals_per_s']:.2e} | {100 * r['peak_fraction']:.1f} "
                   f"| {r['peak_mb']:.0f} | {'' if sp is None else f'{sp:.0f}x'} |")
    return "\n".join(out) + "\n"


if __name__ == "__main__":
    main()
