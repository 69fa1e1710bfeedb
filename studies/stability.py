"""The degradation study's table and chart: accuracy per method under each stress and level.

Reads the runs of `stdr-train -m +sweep=stability` (and of its seed runs: `stress=none
seed=0,1,2`) from their folders: config.yaml gives method, scene, seed and the stress preset
(data.stress.label / level), metrics.json[split] the numbers and the guard's record, and the
sweep's failures.jsonl the crashes. An input may also be a table.json this tool wrote: its
per-run records (`runs`) join those of the folders, so a study spread over machines or days
resumes from its committed table without the run folders. A folder that is also in a table
replaces its record; one run (method, scene, seed, stress, level) from two different sources is
an error. Writes OUT/table.md and table.json, and OUT/degradation_<metric>.{png,svg,csv}:

* per method x stress x level (seed 0; means over the scenes that have the unstressed run too):
  PSNR / SSIM / LPIPS, the PSNR drop against the same method's unstressed run on the same scene,
  the drop on the evaluation frames inside the stress's time window (window: times never
  trained on; sparse: sparsely trained), against the same frames of the unstressed run,
  runs, crashes, recoveries, non-finite metrics, the largest fall from the run's best periodic
  evaluation to its last one (a collapse the final number alone hides; train.eval_every),
  final Gaussians, whether the cap held, and the largest peak memory of the runs
  (metrics.json guard.peak_memory_mb; runs from before it was recorded: –);
* the seed spread of the unstressed runs: per method, mean ± sample std over seeds of the
  scene-mean PSNR;
* the chart: PSNR drop against level, one line per method (colour per baseline, dashed plain,
  solid +STDR), one panel per stress;
* provenance: the finished runs counted per machine and code commit (metrics.json
  conventions.machine, code.commit; kept in each run's record). The same seed gives other
  numbers on another machine, so runs from two machines compare as two seeds do.

    python -m studies.stability multirun/stability_cpu --split val --out research/measurements/stability
    python -m studies.stability research/measurements/stability/table.json multirun/stability_cpu \
        --split val --out research/measurements/stability        # add new runs to the committed ones
    python -m studies.stability --todo fraction_1:0 --todo sparse_1:0 research/measurements/stability/table.json
        # the sweep overrides that run what the table lacks of each preset and seed

`--todo PRESET:SEED` (repeatable) plans, it writes nothing: for the study sweep
(stdr/configs/sweep/stability.yaml: every registered baseline, plain and +STDR, on its scenes) it
prints `PRESET:SEED experiment=a,b data.name=x`, a line per group of scenes lacking the same
experiments, and nothing for a preset whose runs the given tables all hold.
studies/stability_study.py plans with it (missing_runs), so a study resumed on another machine runs only what its
committed table lacks.
"""
from __future__ import annotations

import argparse
import json
import math
import re
from collections import defaultdict
from pathlib import Path
from statistics import mean, stdev
from typing import Any

import yaml

from stdr.data.stress import thinned_window
from stdr.eval.evaluate import commit_stamp
from stdr.eval.table import fmt_value as fmt
from stdr.eval.table import markdown_table, method_name, write_outputs

REFERENCE = ("none", 0)


def _stress(cfg: dict) -> tuple[str, int]:
    st = (cfg.get("data") or {}).get("stress") or {}
    return str(st.get("label", "none")), int(st.get("level", 0))


def _finite(v) -> bool:
    return v is not None and isinstance(v, (int, float)) and math.isfinite(v)


def _frame_times(cfg: dict, split: str, m: dict, cache: dict) -> list[float] | None:
    """Normalized times of the evaluation frames, in per_frame_psnr's order: from metrics.json
    (per_frame_time), else (runs written before it was recorded) from the run's scene as the
    trainer loads it, once per scene and split; None where the data cannot be read."""
    if m.get("per_frame_time") is not None:
        return [float(t) for t in m["per_frame_time"]]
    from omegaconf import OmegaConf
    data = OmegaConf.create(cfg["data"])
    key = (str(data.get("path")), str(data.get("name")), split)
    if key not in cache:
        from stdr.data.load import load_scene
        try:
            cache[key] = [f.time for f in load_scene(data, [split]).splits[split]]
        except (OSError, ValueError, KeyError, AttributeError) as e:
            print(f"[stdr] stability: frame times of {key[0]} unavailable ({e}); no in-window drop for it")
            cache[key] = None
    return cache[key]


RUN_KEY = ("method", "scene", "seed", "stress", "level")
RECORD_FIELDS = ("run", "method", "baseline", "stdr", "scene", "seed", "stress", "level", "crashed", "error")


def load_records(path: Path, split: str) -> list[dict[str, Any]]:
    """The per-run records of a table.json written by this tool (its `runs`), checked: the same
    split, and every record with the fields a run folder gives."""
    try:
        t = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise SystemExit(f"python -m studies.stability: {path} is not a readable table.json ({e})") from None
    if not isinstance(t, dict) or not isinstance(t.get("runs"), list):
        raise SystemExit(f"python -m studies.stability: {path} has no 'runs' list; pass a table.json written by "
                         "python -m studies.stability (or a sweep or run folder)")
    if t.get("split") != split:
        raise SystemExit(f"python -m studies.stability: {path} holds the {t.get('split')!r} split, not {split!r}; "
                         f"pass --split {t.get('split')} or leave this table out")
    for i, r in enumerate(t["runs"]):
        missing = [k for k in RECORD_FIELDS if not isinstance(r, dict) or k not in r]
        finished = isinstance(r, dict) and not r.get("crashed")
        missing += [k for k in ("psnr", "ssim", "lpips", "nonfinite", "cap_held") if finished and k not in r]
        if missing:
            raise SystemExit(f"python -m studies.stability: {path}: runs[{i}] lacks {', '.join(missing)}; "
                             "regenerate that table from its run folders")
    return t["runs"]


def _merge(folder_runs: list[dict[str, Any]], unfinished: list[str],
           tables: list[tuple[Path, list[dict[str, Any]]]]) -> list[dict[str, Any]]:
    """Table records, then folder runs: a folder's state (finished, crashed or unfinished)
    replaces the record of the same run path; the same run from two sources is an error."""
    by_path: dict[str, tuple[str, dict[str, Any]]] = {}
    for path, recs in tables:
        for r in recs:
            prev = by_path.get(r["run"])
            if prev is not None and prev[1] != r:
                raise SystemExit(f"python -m studies.stability: run {r['run']} differs between {prev[0]} and {path}; "
                                 "pass one of them")
            by_path[r["run"]] = (str(path), r)
    for d in unfinished:
        by_path.pop(d, None)
    for r in folder_runs:
        by_path[r["run"]] = ("run folder", r)
    seen: dict[tuple, tuple[str, str]] = {}
    for src, r in by_path.values():
        key = tuple(r[k] for k in RUN_KEY)
        if key in seen:
            other_src, other_run = seen[key]
            raise SystemExit("python -m studies.stability: " + ", ".join(f"{k}={v}" for k, v in zip(RUN_KEY, key))
                             + f" comes twice: {other_run} ({other_src}) and {r['run']} ({src}); "
                             "leave one of them out")
        seen[key] = (src, r["run"])
    return [r for _, r in by_path.values()]


def collect_runs(paths: list[str | Path], split: str) -> tuple[list[dict[str, Any]], list[str]]:
    """Every run folder (config.yaml) under `paths`: finished ones with their numbers, crashed
    ones (recorded in a failures.jsonl of the sweep) with the error; unfinished ones named.
    A path that is a file is a table.json of this tool: its run records join (load_records)."""
    failures: dict[str, str] = {}
    folders: list[Path] = []
    tables: list[tuple[Path, list[dict[str, Any]]]] = []
    for p in map(Path, paths):
        if not p.exists():
            raise SystemExit(f"python -m studies.stability: {p} does not exist")
        if p.is_file():
            tables.append((p, load_records(p, split)))
            continue
        if (p / "config.yaml").is_file():
            folders.append(p)
            continue
        folders += sorted(c.parent for c in p.rglob("config.yaml") if not c.parent.name.startswith("."))
        for f in p.rglob("failures.jsonl"):
            for line in f.read_text().splitlines():
                if line.strip():
                    rec = json.loads(line)
                    failures[str(Path(rec["run_dir"]).resolve())] = rec.get("error", "?")
    if not folders and not tables:
        raise SystemExit(f"python -m studies.stability: no run folders (config.yaml) under {', '.join(map(str, paths))}")
    runs, unfinished, times_cache = [], [], {}
    for d in dict.fromkeys(f.resolve() for f in folders):  # absolute: a table's records name runs so
        cfg = yaml.safe_load((d / "config.yaml").read_text())
        label, level = _stress(cfg)
        row = {"run": str(d), "method": method_name(cfg), "baseline": cfg["baseline"]["name"],
               "stdr": bool((cfg.get("stdr") or {}).get("enabled")), "scene": cfg["data"]["name"],
               "seed": cfg.get("seed", 0), "stress": label, "level": level, "crashed": False, "error": None}
        mp = d / "metrics.json"
        m = json.loads(mp.read_text()).get(split) if mp.is_file() else None
        if m is None:
            err = failures.get(str(d.resolve()))
            if err is None:
                unfinished.append(str(d))
                continue
            row.update(crashed=True, error=err)
        else:
            g = m.get("guard") or {}
            cap = g.get("max_gaussians")
            row.update({k: m.get(k) for k in ("psnr", "ssim", "lpips", "num_gaussians")})
            frames = m.get("per_frame_psnr")
            times = _frame_times(cfg, split, m, times_cache) if frames else None
            stress = (cfg.get("data") or {}).get("stress") or {}
            row.update(window=thinned_window(stress), per_frame_psnr=frames,
                       per_frame_time=times if times is not None and len(times) == len(frames) else None)
            best, last = m.get("best") or {}, m.get("last") or {}
            row.update(fall=best["psnr"] - last["psnr"]
                       if _finite(best.get("psnr")) and _finite(last.get("psnr")) else None,
                       best_step=best.get("step"))
            code = m.get("code") or {}
            row.update(machine=(m.get("conventions") or {}).get("machine"),
                       commit=commit_stamp(code) if code.get("commit") else None)
            row.update(recoveries=g.get("n_recoveries", 0), peak=g.get("peak_gaussians"), cap=cap,
                       peak_memory_mb=g.get("peak_memory_mb"),
                       nonfinite=not all(_finite(m.get(k)) for k in ("psnr", "ssim")),
                       cap_held=None if not cap or g.get("peak_gaussians") is None else g["peak_gaussians"] <= cap)
        runs.append(row)
    runs = _merge(runs, unfinished, tables)
    if not runs:
        raise SystemExit(f"python -m studies.stability: no finished or crashed run with a {split!r} entry "
                         f"({len(unfinished)} unfinished)")
    return runs, unfinished


def window_drop(run: dict[str, Any], ref: dict[str, Any]) -> tuple[float, int] | None:
    """(unstressed minus stressed mean PSNR, frame count) over the evaluation frames whose time
    lies in the run's stress window; None without a window, frame times or such frames."""
    w, t = run.get("window"), run.get("per_frame_time")
    if not w or t is None or ref.get("per_frame_psnr") is None or len(ref["per_frame_psnr"]) != len(t):
        return None
    inside = [i for i, x in enumerate(t) if w[0] <= x <= w[1]]
    if not inside:
        return None
    return (mean(ref["per_frame_psnr"][i] for i in inside) - mean(run["per_frame_psnr"][i] for i in inside),
            len(inside))


def degradation(runs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per method x stress x level at seed 0, averaged over the scenes where the method's
    unstressed seed-0 run exists (the others are listed in `scenes_without_reference`)."""
    ref = {(r["method"], r["scene"]): r for r in runs
           if (r["stress"], r["level"]) == REFERENCE and r["seed"] == 0 and not r["crashed"]}
    groups: dict[tuple, list] = defaultdict(list)
    for r in runs:
        if r["seed"] == 0:
            groups[(r["method"], r["stress"], r["level"])].append(r)
    rows = []
    for (method, stress, level), rs in sorted(groups.items(), key=lambda kv: (kv[0][1] != "none", kv[0][1],
                                                                             kv[0][0], kv[0][2])):
        ok = [r for r in rs if not r["crashed"] and (method, r["scene"]) in ref]
        good = [r for r in ok if not r["nonfinite"]]
        drops = [ref[(method, r["scene"])]["psnr"] - r["psnr"] for r in good]
        win = [w for r in good for w in [window_drop(r, ref[(method, r["scene"])])] if w is not None]
        avg = lambda k, good=good: mean(r[k] for r in good) if good and all(_finite(r[k]) for r in good) else None  # noqa: E731
        rows.append({"method": method, "baseline": rs[0]["baseline"], "stdr": rs[0]["stdr"], "stress": stress,
                     "level": level, "scenes": sorted(r["scene"] for r in good),
                     "scenes_without_reference": sorted(r["scene"] for r in rs if not r["crashed"]
                                                        and (method, r["scene"]) not in ref),
                     "runs": len(rs), "crashes": sum(r["crashed"] for r in rs),
                     "nonfinite": sum(bool(r.get("nonfinite")) for r in rs if not r["crashed"]),
                     "recoveries": sum(r.get("recoveries") or 0 for r in rs if not r["crashed"]),
                     "psnr": avg("psnr"), "ssim": avg("ssim"), "lpips": avg("lpips"),
                     "psnr_drop": mean(drops) if drops else None,
                     "window_drop": mean(d for d, _ in win) if win else None,
                     "window_frames": sum(n for _, n in win),
                     "fall_max": max((r["fall"] for r in good if r.get("fall") is not None), default=None),
                     "gaussians": avg("num_gaussians"),
                     "memory_max_mb": max((r["peak_memory_mb"] for r in ok if _finite(r.get("peak_memory_mb"))),
                                          default=None),
                     "cap_held": None if not ok or any(r["cap_held"] is None for r in ok)
                     else all(r["cap_held"] for r in ok)})
    return rows


def seed_spread(runs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Unstressed runs: per method, the scene-mean PSNR of each seed (scenes every seed has),
    then their mean and sample std."""
    by: dict[str, dict[int, dict[str, float]]] = defaultdict(lambda: defaultdict(dict))
    for r in runs:
        if (r["stress"], r["level"]) == REFERENCE and not r["crashed"] and _finite(r.get("psnr")):
            by[r["method"]][r["seed"]][r["scene"]] = r["psnr"]
    out = []
    for method, seeds in sorted(by.items()):
        common = set.intersection(*(set(s) for s in seeds.values()))
        if not common:
            continue
        per_seed = {s: mean(v[sc] for sc in common) for s, v in sorted(seeds.items())}
        vals = list(per_seed.values())
        out.append({"method": method, "seeds": sorted(per_seed), "scenes": sorted(common),
                    "psnr_mean": mean(vals), "psnr_std": stdev(vals) if len(vals) > 1 else None,
                    "per_seed": per_seed})
    return out


def provenance(runs: list[dict[str, Any]]) -> str:
    """'machine × code commit: runs' for the finished runs (records from before these were kept: 'not recorded')."""
    count: dict[tuple[str, str], int] = defaultdict(int)
    for r in runs:
        if not r["crashed"]:
            count[(r.get("machine") or "machine not recorded", r.get("commit") or "commit not recorded")] += 1
    return "; ".join(f"{mach}, code {code}: {n} runs" for (mach, code), n in sorted(count.items()))


def markdown(rows, spread, unfinished, split, runs) -> str:
    head = ["method", "stress", "level", "PSNR↑", "drop (dB)", "drop in window (dB)", "SSIM↑", "LPIPS↓", "runs", "crashes",
            "non-finite", "recoveries", "fell from best (dB)", "Gaussians", "cap held", "peak memory (MiB)", "scenes"]
    body = [[r["method"], r["stress"], str(r["level"]), fmt(r["psnr"], "{:.2f}"), fmt(r["psnr_drop"], "{:+.2f}"),
             fmt(r["window_drop"], "{:+.2f}") + (f" ({r['window_frames']} fr.)" if r["window_drop"] is not None else ""),
             fmt(r["ssim"], "{:.4f}"), fmt(r["lpips"], "{:.4f}"), str(r["runs"]), str(r["crashes"]), str(r["nonfinite"]),
             str(r["recoveries"]), fmt(r["fall_max"], "{:.2f}"), fmt(r["gaussians"], "{:,.0f}"),
             {True: "yes", False: "**no**", None: "–"}[r["cap_held"]], fmt(r.get("memory_max_mb"), "{:,.0f}"),
             ", ".join(r["scenes"]) or "–"]
            for r in rows]
    md = [f"Degradation under stress ({split} split, seed 0; drop = unstressed PSNR − stressed PSNR, "
          "mean over the scenes listed; drop in window = the same on the evaluation frames whose time "
          "lies in the stress's window (window, sparse), with their count; fell from best = the largest "
          "best-minus-last PSNR of the periodic evaluations over those scenes)", "", markdown_table(head, body)]
    if spread:
        md += ["", "Seed spread of the unstressed runs (scene-mean PSNR per seed)", "",
               markdown_table(["method", "seeds", "PSNR mean ± std", "scenes"],
                              [[s["method"], ", ".join(map(str, s["seeds"])),
                                fmt(s["psnr_mean"], "{:.2f}") + (f" ± {s['psnr_std']:.2f}" if s["psnr_std"] is not None
                                                              else ""), ", ".join(s["scenes"])] for s in spread])]
    md += ["", "Provenance (finished runs; the same seed gives other numbers on another machine, "
           "so compare across machines as across seeds): " + provenance(runs)]
    missing = sorted({sc for r in rows for sc in r["scenes_without_reference"]})
    if missing:
        md += ["", f"Runs without an unstressed reference (left out of the means): scenes {', '.join(missing)}"]
    if unfinished:
        md += ["", f"Unfinished (no metrics.json, no recorded failure): {len(unfinished)} runs"]
    return "\n".join(md) + "\n"


def draw(rows, out: Path, split: str) -> dict[str, Path]:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D
    from matplotlib.ticker import MaxNLocator

    from stdr.eval.chart import baseline_colors, save_chart
    stresses = sorted({r["stress"] for r in rows if r["stress"] != "none"})
    if not stresses:
        raise SystemExit("python -m studies.stability: no stressed runs to chart")
    # one panel per stress over all evaluation frames; a stress with a time window (window,
    # sparse) gets a second panel over the frames inside it, where the mean over all frames
    # hides the loss (frames outside the window often gain)
    panels = [(st, key, frames) for st in stresses
              for key, frames in (("psnr_drop", "all"), ("window_drop", "in window"))
              if key == "psnr_drop" or any(r["stress"] == st and r["window_drop"] is not None for r in rows)]
    colors = baseline_colors(sorted({r["baseline"] for r in rows}))
    ncol = min(len(panels), 4)
    nrow = -(-len(panels) // ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(3.2 * ncol, 3.0 * nrow), squeeze=False, sharey=True)
    for ax in axes.flat[len(panels):]:
        ax.set_visible(False)
    data = []
    for ax, (st, key, frames) in zip(axes.flat, panels):
        for method in sorted({r["method"] for r in rows}):
            pts = sorted((r["level"], r[key]) for r in rows
                         if r["method"] == method and r["stress"] == st and r[key] is not None)
            ref = [r for r in rows if r["method"] == method and (r["stress"], r["level"]) == REFERENCE]
            if not pts or not ref:
                continue
            pts = [(0, 0.0)] + pts
            r0 = ref[0]
            ax.plot(*zip(*pts), marker="o", ms=4, color=colors[r0["baseline"]], ls="-" if r0["stdr"] else "--",
                    lw=1.4)
            data += [[st, frames, method, lv, f"{d:.4f}"] for lv, d in pts]
        ax.set_title(st if frames == "all" else f"{st}: frames in the window", fontsize=9)
        ax.set_xlabel("severity level")
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.grid(True, alpha=0.3)
    for row in axes:
        row[0].set_ylabel(f"PSNR drop (dB, {split}) ↓")
    handles = [Line2D([], [], color=c, label=b) for b, c in colors.items()]
    handles += [Line2D([], [], color="k", ls="--", label="plain"), Line2D([], [], color="k", label="+STDR")]
    fig.legend(handles=handles, loc="lower center", ncol=len(handles), frameon=False, fontsize=8,
               bbox_to_anchor=(0.5, -0.08))
    fig.tight_layout()
    return save_chart(fig, out, "degradation_psnr", ["stress", "frames", "method", "level", "psnr_drop_db"], data)


def study_grid(data: str = "dnerf") -> tuple[list[tuple[str, str]], list[str]]:
    """The study sweep's methods as (experiment, method name) pairs, every registered baseline
    plain and +STDR, and its scenes (stdr/configs/sweep/stability.yaml)."""
    from stdr.config import CONFIG_DIR
    from stdr.store import experiments_on
    exps = []
    for e in experiments_on(data).split(","):
        base = e[len(data) + 1:]
        cfg = {"baseline": {"name": base.removesuffix("_stdr")}, "stdr": {"enabled": base.endswith("_stdr")}}
        exps.append((e, method_name(cfg)))
    sweep = yaml.safe_load((CONFIG_DIR / "sweep" / "stability.yaml").read_text())
    scenes = str(sweep["hydra"]["sweeper"]["params"]["data.name"]).split(",")
    return exps, scenes


def todo_overrides(have: set[tuple], grid: tuple[list[tuple[str, str]], list[str]], preset: str,
                   seed: int) -> list[str]:
    """Hydra overrides for the runs of one stress preset and seed of the study grid
    (study_grid) whose RUN_KEY is not in `have` (a crashed run counts as held: it is a result).
    One line per group of scenes that lack the same experiments, e.g.
    'experiment=dnerf_spgs,dnerf_spgs_stdr data.name=standup'."""
    missing = missing_runs(have, grid, preset, seed)
    groups: dict[tuple[str, ...], list[str]] = {}
    for scene in grid[1]:
        lack = tuple(e for e, sc in missing if sc == scene)
        if lack:
            groups.setdefault(lack, []).append(scene)
    return [f"experiment={','.join(lack)} data.name={','.join(sc)}" for lack, sc in groups.items()]


def missing_runs(have: set[tuple], grid: tuple[list[tuple[str, str]], list[str]], preset: str,
                 seed: int) -> list[tuple[str, str]]:
    """The (experiment, scene) runs of one stress preset and seed of the study grid (study_grid)
    whose RUN_KEY is not in `have`, scene by scene (a crashed run counts as held: it is a result)."""
    from stdr.config import CONFIG_DIR
    f = CONFIG_DIR / "stress" / f"{preset}.yaml"
    if not f.is_file():
        raise SystemExit(f"python -m studies.stability: --todo {preset}:{seed}: no stress preset {f}")
    # `# @package data.stress`: the preset's keys sit at the top of its file
    label, level = _stress({"data": {"stress": yaml.safe_load(f.read_text()) or {}}})
    exps, scenes = grid
    return [(e, scene) for scene in scenes for e, method in exps if (method, scene, seed, label, level) not in have]


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(prog="python -m studies.stability", description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="*", help="sweep folders, run folders or table.json files of this tool "
                    "(with --todo: table.json files only)")
    ap.add_argument("--split", default="val")
    ap.add_argument("--out", type=Path, help="folder for table.md/.json and the chart")
    ap.add_argument("--no-chart", action="store_true")
    ap.add_argument("--todo", metavar="PRESET:SEED", action="append", help="print, as 'PRESET:SEED overrides', "
                    "the sweep overrides for the runs of this stress preset and seed that the given tables "
                    "lack, and write nothing (repeatable)")
    a = ap.parse_args(argv)
    if a.todo:
        bad = [t for t in a.todo if not re.fullmatch(r"[A-Za-z0-9_]+:\d+", t)]
        if bad:
            ap.error(f"--todo {bad[0]}: want PRESET:SEED, e.g. fraction_1:0")
        not_tables = [r for r in a.runs if not Path(r).is_file()]
        if not_tables:
            ap.error(f"--todo reads table.json files; {', '.join(not_tables)} is not one")
        have = {tuple(r[k] for k in RUN_KEY) for t in a.runs for r in load_records(Path(t), a.split)}
        grid = study_grid()
        for t in a.todo:
            preset, _, seed = t.partition(":")
            for line in todo_overrides(have, grid, preset, int(seed)):
                print(t, line)
        return
    if not a.runs or a.out is None:
        ap.error("give the runs (sweep folders, run folders or table.json files) and --out")
    runs, unfinished = collect_runs(a.runs, a.split)
    rows = degradation(runs)
    spread = seed_spread(runs)
    md = markdown(rows, spread, unfinished, a.split, runs)
    write_outputs(a.out / "table", md, {"split": a.split, "rows": rows, "seed_spread": spread, "runs": runs,
                                        "unfinished": unfinished})
    print(md)
    if not a.no_chart:
        paths = draw(rows, a.out, a.split)
        print(f"[stdr] chart: {paths['png']}")


if __name__ == "__main__":
    main()
