"""The capture check: `stdr-data capture` on the real phone capture in ../shared against that
capture's own cameras (protocol: research/measurements/capture_toy/README.md).

    python -m studies.capture_check run  --toy ../shared/data/nerfies/toy-capture --work /tmp/capture_check
    python -m studies.capture_check table --work /tmp/capture_check --out research/measurements/capture_toy

`run` (resumable: each finished step leaves its record in WORK/records.json and is skipped next time):
1. capture the toy capture's 2x images (`stdr-data capture FOLDER --frames 0`), timed per stage;
2. pose errors of the captured cameras against the capture's own camera files (similarity-aligned);
3. two training runs per seed with the same budget, the same training ids and the same held-out
   ids (the ids both datasets have, split by the capture's every-8th rule): on the captured
   dataset, and on the capture's own cameras (its rgb/2x images undistorted by the loader);
   val PSNR / SSIM of each.
`table` writes records.json and README.md's generated block (stamped with commit and machine).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import time
from pathlib import Path

import numpy as np

from stdr.tools.runqueue import run_one

ROOT = Path(__file__).resolve().parents[1]

BUDGET = ["budget=cpu", "eval.lpips=false", "train.progress=false", "eval.save_images=false",
          "train.image_every=0", "device=cpu"]


def _load(work: Path) -> dict:
    p = work / "records.json"
    return json.loads(p.read_text()) if p.is_file() else {}


def _save(work: Path, rec: dict) -> None:
    (work / "records.json").write_text(json.dumps(rec, indent=2))


def _stamp() -> dict:
    from studies.common import commit as code_stamp
    commit = code_stamp()
    cpu = next((ln.split(":", 1)[1].strip() for ln in Path("/proc/cpuinfo").read_text().splitlines()
                if ln.startswith("model name")), platform.processor())
    return {"commit": commit, "cpu": cpu, "cores": os.cpu_count(), "date": time.strftime("%Y-%m-%d")}


def _link_tree(src: Path, dst: Path, names) -> None:
    dst.mkdir(parents=True, exist_ok=True)
    for n in names:
        if (src / n).exists():
            (dst / n).symlink_to((src / n).resolve())


def _split(ids_a, ids_b, every=8):
    """The ids both datasets have, held out by the capture's rule (every-th by rank, offset every//2)."""
    common = [i for i in ids_a if i in set(ids_b)]
    val = [i for n, i in enumerate(common) if n % every == every // 2]
    return [i for i in common if i not in set(val)], val


def run(toy: Path, work: Path, seeds) -> None:
    from stdr.data import capture as cap
    from stdr.data.pose_error import ray_errors
    work.mkdir(parents=True, exist_ok=True)
    rec = _load(work)
    rec.setdefault("stamp", _stamp())
    out = work / "captured"
    if "capture" not in rec:
        shutil.rmtree(out, ignore_errors=True)
        t0 = time.perf_counter()
        info = cap.capture(toy / "rgb" / "2x", out, cap.CaptureConfig(frames=None))
        rec["capture"] = {"seconds": time.perf_counter() - t0, "timings_s": info["timings_s"], "sfm": info["sfm"],
                          "num_points": info["num_points"], "frames": len(info["frames"])}
        _save(work, rec)
    ids_cap = json.loads((out / "dataset.json").read_text())["ids"]
    ids_toy = json.loads((toy / "dataset.json").read_text())["ids"]
    if "poses" not in rec:
        common = [i for i in ids_toy if i in set(ids_cap)]

        def cams(folder, ids):
            return [json.loads((folder / "camera" / f"{i}.json").read_text()) for i in ids]
        rec["poses"] = {"common_ids": len(common), "toy_ids": len(ids_toy), "captured_ids": len(ids_cap),
                        **ray_errors(cams(out, common), cams(toy, common))}
        _save(work, rec)
    train, val = _split(ids_cap, ids_toy)
    split = {"ids": sorted(set(train) | set(val)), "train_ids": train, "val_ids": val}
    for name, src, scale, extra in (("captured", out, 1, ["rgb", "camera", "metadata.json", "scene.json", "points.npy",
                                                          "colmap"]),
                                    ("own_cameras", toy, 2, ["rgb", "camera", "metadata.json", "scene.json", "colmap"])):
        folder = work / f"data_{name}"
        if not folder.is_dir():
            _link_tree(src, folder, extra)
            (folder / "dataset.json").write_text(json.dumps({"count": len(split["ids"]), **split}, indent=2))
        for seed in seeds:
            key = f"{name}/s{seed}"
            if key in rec.get("runs", {}):
                continue
            run_dir = work / "runs" / name / f"s{seed}"
            shutil.rmtree(run_dir, ignore_errors=True)
            overrides = ["experiment=nerfies_deform", f"data.path={folder}", "data.split_mode=ids",
                         f"data.image_scale={scale}", "data.eval_split=val", f"seed={seed}", *BUDGET]
            print("[capture_check] stdr-train", " ".join(overrides), f"(in {run_dir})", flush=True)
            run_one(overrides, run_dir, threads=os.cpu_count() or 1)  # the project's run queue; raises on failure
            m = json.loads((run_dir / "metrics.json").read_text())["val"]
            rec.setdefault("runs", {})[key] = {k: m[k] for k in ("psnr", "ssim", "num_gaussians", "train_seconds")}
            rec["runs"][key]["size"] = m["data"].get("num_ids")
            _save(work, rec)


def table(work: Path, out: Path) -> None:
    rec = _load(work)
    out.mkdir(parents=True, exist_ok=True)
    (out / "records.json").write_text(json.dumps(rec, indent=2))
    p, c = rec["poses"], rec["capture"]
    lines = [f"Generated by `studies/capture_check.py table` from records.json (commit {rec['stamp']['commit']}, "
             f"{rec['stamp']['cpu']}, {rec['stamp']['cores']} cores, {rec['stamp']['date']}).", "",
             f"* Capture of the toy capture's {c['frames']} images (rgb/2x): {c['sfm']['registered']} registered, "
             f"{c['num_points']:,} points kept, reprojection error {c['sfm']['mean_reprojection_error_px']:.2f} px; "
             "stage times " + ", ".join(f"{k} {v:.0f} s" for k, v in c["timings_s"].items()) + f" ({c['seconds']:.0f} s in all).",
             f"* Poses on the {p['common_ids']} ids both have (the capture's own cameras: {p['toy_ids']}): centre error "
             f"median {100 * p['position_median']:.2f} %, max {100 * p['position_max']:.2f} % of the trajectory's extent; "
             f"orientation (angle between the rays through the same image points) median {p['ray_median_deg']:.2f} deg, "
             f"max {p['ray_max_deg']:.2f} deg.", "",
             "| cameras | seed | val PSNR (dB) | val SSIM | Gaussians | train s |", "|---|---|---|---|---|---|"]
    runs = rec.get("runs", {})
    for key in sorted(runs):
        r = runs[key]
        name, seed = key.split("/")
        lines.append(f"| {name} | {seed[1:]} | {r['psnr']:.2f} | {r['ssim']:.4f} | {r['num_gaussians']:,} | "
                     f"{r['train_seconds']:.0f} |")
    diffs = [runs[f"captured/{s}"]["psnr"] - runs[f"own_cameras/{s}"]["psnr"]
             for s in {k.split("/")[1] for k in runs} if f"captured/{s}" in runs and f"own_cameras/{s}" in runs]
    if diffs:
        lines += ["", f"Captured minus own cameras, val PSNR: {', '.join(f'{d:+.2f}' for d in diffs)} dB "
                  f"(mean {np.mean(diffs):+.2f} dB over {len(diffs)} seed(s))."]
    readme = out / "README.md"
    text = readme.read_text() if readme.is_file() else "<!-- capture:begin -->\n<!-- capture:end -->\n"
    a, b = text.index("<!-- capture:begin -->"), text.index("<!-- capture:end -->")
    readme.write_text(text[:a] + "<!-- capture:begin -->\n" + "\n".join(lines) + "\n" + text[b:])
    print("\n".join(lines))


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run")
    r.add_argument("--toy", type=Path, default=ROOT.parent / "shared" / "data" / "nerfies" / "toy-capture")
    r.add_argument("--work", type=Path, required=True)
    r.add_argument("--seeds", type=int, nargs="+", default=[0])
    t = sub.add_parser("table")
    t.add_argument("--work", type=Path, required=True)
    t.add_argument("--out", type=Path, default=ROOT / "research" / "measurements" / "capture_toy")
    a = ap.parse_args(argv)
    if a.cmd == "run":
        run(a.toy, a.work, a.seeds)
    else:
        table(a.work, a.out)


if __name__ == "__main__":
    main()
