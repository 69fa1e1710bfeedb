"""Speed against accuracy, drawn from run directories (`stdr-chart`).

Charts (each written as PNG and SVG, with the plotted numbers as CSV):
* `speed_accuracy`: the metric against render FPS (log axis), one marker per method: colour
  per baseline, hollow for plain and filled with a plug-in, an arrow from each plain point to
  the same baseline with a plug-in at its defaults (the plug-in's label), the Pareto frontier;
  a panel for the mean over scenes, then one per scene;
* `learning_curves`: the metric against training seconds from each run's curve
  (metrics.json `curve`, train.eval_every), one line per method, mean over scenes;
* `size_accuracy`: the metric against the number of Gaussians and against the model's
  megabytes (mean over scenes).

Runs are grouped with the rule of `stdr-eval`'s table (stdr.eval.table.collect): runs of one
method and scene are averaged over seeds, and runs whose configs differ otherwise are refused.
"""
from __future__ import annotations

import csv
import io
import math
from pathlib import Path
from typing import Any

from ..io.files import atomic_path, make_folder, write_atomic
from ..plugins import registered_plugins
from .table import collect, find_run_dirs as find_runs, load_run, method_suffix, table_row
from ..baselines import BASELINES

METRIC_LABELS = {"psnr": "PSNR (dB) ↑", "ssim": "SSIM ↑", "lpips": "LPIPS ↓"}
HIGHER_IS_BETTER = {"psnr": True, "ssim": True, "lpips": False}
CHARTS = ("speed_accuracy", "learning_curves", "size_accuracy")


# ------------------------------------------------------------------ reading runs
def labelled(paths: list[str | Path]) -> list[tuple[str | None, Path]]:
    """(label, run) for every run under `paths`. An argument LABEL=PATH (PATH existing, the whole
    string not) names the method of every run under PATH (e.g. 2k=outputs/budget/deform_2k), so
    runs that differ in config, such as lengths, are charted as separate methods."""
    out = []
    for p in paths:
        label, path = None, Path(p)
        if not path.exists() and "=" in str(p):
            lb, rest = str(p).split("=", 1)
            if not Path(rest).exists():
                raise FileNotFoundError(f"{p}: neither a path nor LABEL=PATH with an existing PATH ({rest})")
            if not lb:
                raise ValueError(f"{p}: empty label before '='")
            label, path = lb, Path(rest)
        out += [(label, r) for r in find_runs([path])]
    return out


def read_runs(runs: list, split: str, metric: str) -> list[dict[str, Any]]:
    """One row per run (stdr.eval.table.load_run), checked for what the charts need. `runs`:
    run folders, or (label, folder) pairs whose label replaces the method name."""
    rows = []
    for item in runs:
        label, r = item if isinstance(item, tuple) else (None, item)
        x = load_run(r, split)
        m = x["metrics"]
        for k in (metric, "fps", "num_gaussians"):
            if m.get(k) is None:
                raise ValueError(f"{r}/metrics.json [{split}] has no {k!r}"
                                 + (" (LPIPS weights were not found when it was evaluated)" if k == "lpips" else ""))
        cfg = x["config"]
        row = {**table_row(cfg, split, m, str(r)), "baseline": cfg["baseline"]["name"],
               "variant": method_suffix(cfg),  # "" (plain), or the plug-ins' labels and tags
               "pruned": float((cfg.get("prune") or {}).get("share") or 0) > 0}  # contribution pruning (compact)
        if label is not None:
            row["method"] = label
        rows.append(row)
    return rows


def caption(rows: list[dict[str, Any]]) -> str:
    """Machine, device, budget, resolution and seeds of the runs, for a chart's caption."""
    def uniq(vals):
        vals = [v for v in dict.fromkeys(vals) if v is not None]
        return ", ".join(map(str, vals)) if vals else "not recorded"
    conv = [r["metrics"].get("conventions", {}) for r in rows]
    res = uniq(f"{r['metrics']['width']}x{r['metrics']['height']}" if "width" in r["metrics"] else None
               for r in rows)
    return (f"machine: {uniq(c.get('machine') for c in conv)}; device: {uniq(c.get('device_name') for c in conv)} "
            f"({uniq(c.get('render_backend') for c in conv)} rasterizer); budget: "
            f"{uniq(r['config'].get('budget') for r in rows)}; resolution: {res}; "
            f"seeds: {uniq(sorted({r['config'].get('seed') for r in rows}, key=str))}")


# ------------------------------------------------------------------ data behind each chart
def _kinds(rows) -> dict[str, dict[str, Any]]:
    """method -> {baseline, variant, pruned} (one config per method: collect refuses mixed ones)."""
    return {r["method"]: {"baseline": r["baseline"], "variant": r["variant"], "pruned": r.get("pruned", False)}
            for r in rows}


def speed_points(rows: list[dict[str, Any]], metric: str) -> list[dict[str, Any]]:
    """(method, scene | 'mean', fps, metric, gaussians, model MB) per method and panel."""
    t = collect(rows)
    kinds = _kinds(rows)
    pts = []
    for m in t["methods"]:
        panels = [("mean", t["means"][m])] + [(s, t["cells"][m][s]) for s in t["scenes"] if s in t["cells"][m]]
        for scene, c in panels:
            if c.get(metric) is None or c.get("fps") is None:
                continue  # a method without every scene has no mean
            mb = [r["metrics"].get("model_mb") for r in rows if r["method"] == m and (scene == "mean" or r["scene"] == scene)]
            pts.append({"method": m, **kinds[m], "scene": scene,
                        "fps": c["fps"], metric: c[metric], f"{metric}_std": c.get(f"{metric}_std"),
                        "num_gaussians": c["num_gaussians"],
                        "model_mb": sum(mb) / len(mb) if mb and None not in mb else None,
                        "n_runs": c.get("n_runs", c.get("n_seeds"))})
    return pts


def curve_points(rows: list[dict[str, Any]], metric: str) -> list[dict[str, Any]]:
    """Per method and curve step: the metric and training seconds averaged over the scenes (and
    seeds) whose curves have that step. Runs without a curve are skipped; a method none of
    whose runs has one is left out."""
    by: dict[tuple[str, int], list[dict]] = {}
    for r in rows:
        for p in r["metrics"].get("curve") or []:
            if p.get(metric) is not None and p.get("train_seconds") is not None:  # older runs lack seconds
                by.setdefault((r["method"], p["step"]), []).append({**p, "scene": r["scene"]})
    kinds, pts = _kinds(rows), []
    for (m, step), ps in sorted(by.items(), key=lambda kv: (kv[0][0], kv[0][1])):
        pts.append({"method": m, **kinds[m], "step": step,
                    "train_seconds": sum(p["train_seconds"] for p in ps) / len(ps),
                    metric: sum(p[metric] for p in ps) / len(ps), "n_runs": len(ps),
                    "scenes": len({p["scene"] for p in ps}), "frames": min(p.get("frames") or 0 for p in ps)})
    return pts


def pareto(points: list[tuple[float, float]], higher_is_better: bool = True) -> list[tuple[float, float]]:
    """The (x, y) points no other point beats in both larger x and better y, sorted by x."""
    sign = 1.0 if higher_is_better else -1.0
    front, best = [], -math.inf
    for x, y in sorted(points, key=lambda p: (-p[0], -sign * p[1])):
        if sign * y > best:
            front.append((x, y))
            best = sign * y
    return sorted(front)


# ------------------------------------------------------------------ drawing
def baseline_colors(baselines: list[str]):
    """One colour per baseline, stable across charts: the registry's order, then any other."""
    import matplotlib

    cmap = matplotlib.colormaps["tab10"]
    order = sorted(BASELINES) + sorted(set(baselines) - set(BASELINES))
    present = set(baselines)
    return {b: cmap(i % 10) for i, b in enumerate(order) if b in present}


def _log_ticks(ax):
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter
    ax.xaxis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
    ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    ax.xaxis.set_minor_formatter(NullFormatter())


def _marker(ax, x, y, color, filled, size=60, shape="o"):
    ax.scatter([x], [y], s=size, marker=shape, facecolors=color if filled else "none", edgecolors=[color],
               linewidths=1.6, zorder=3)


def _full_of(q, pts):
    """The unpruned point a pruned (compact) point was made from: same baseline, the plug-ins on
    or off alike, and a method label the compact one's starts with; None if absent."""
    for p in pts:
        if not p.get("pruned") and p["baseline"] == q["baseline"] and bool(p["variant"]) == bool(q["variant"]) \
                and q["method"].startswith(p["method"] + " "):
            return p
    return None


def _methods_panel(ax, pts, metric, colors, xkey, logx):
    higher = HIGHER_IS_BETTER[metric]
    for p in pts:
        _marker(ax, p[xkey], p[metric], colors[p["baseline"]], bool(p["variant"]),
                shape="s" if p.get("pruned") else "o")
    for q in pts:  # a dotted arrow from each full model to its compact (pruned) twin
        p = _full_of(q, pts) if q.get("pruned") else None
        if p is not None:
            ax.annotate("", xy=(q[xkey], q[metric]), xytext=(p[xkey], p[metric]),
                        arrowprops=dict(arrowstyle="->", color=colors[p["baseline"]], lw=0.9, ls=":", alpha=0.8))
    labels = {s.label for s in registered_plugins()}
    for p in pts:  # an arrow from each plain point to the same baseline with one plug-in at its defaults
        if p["variant"]:
            continue
        for q in pts:
            if q["variant"] in labels and q["baseline"] == p["baseline"] and q["method"] == p["method"] + q["variant"]:
                ax.annotate("", xy=(q[xkey], q[metric]), xytext=(p[xkey], p[metric]),
                            arrowprops=dict(arrowstyle="->", color=colors[p["baseline"]], lw=1.0, alpha=0.8))
    front = pareto([(p[xkey], p[metric]) for p in pts], higher)
    if len(front) > 1:
        ax.plot(*zip(*front), ls="--", color="0.5", lw=1.0, zorder=1, label="Pareto frontier")
    if logx:
        ax.set_xscale("log")
        _log_ticks(ax)
    else:
        from matplotlib.ticker import MaxNLocator
        ax.xaxis.set_major_locator(MaxNLocator(5))
    ax.grid(True, which="both", alpha=0.3)


def _variants(pts) -> str:
    """The plug-in labels among the points, for legends."""
    labels = {s.label for s in registered_plugins()}
    return ", ".join(sorted({p["variant"] for p in pts if p["variant"] in labels})) or "with plug-in"


def _legend(fig, colors, pts, pareto_line=True):
    from matplotlib.lines import Line2D
    handles = [Line2D([], [], marker="o", ls="", markerfacecolor=c, markeredgecolor=c, label=b)
               for b, c in colors.items()]
    handles += [Line2D([], [], marker="o", ls="", markerfacecolor="none", markeredgecolor="k", label="plain"),
                Line2D([], [], marker="o", ls="", markerfacecolor="k", markeredgecolor="k", label=_variants(pts))]
    if any(p.get("pruned") for p in pts):
        handles.append(Line2D([], [], marker="s", ls=":", color="k", markerfacecolor="none", markeredgecolor="k",
                              label="compact (pruned), from its full model"))
    if pareto_line:
        handles.append(Line2D([], [], ls="--", color="0.5", label="Pareto frontier"))
    fig.legend(handles=handles, loc="lower center", ncol=len(handles), frameon=False, fontsize=8)


def palette_png(path: Path) -> None:
    """Rewrite a chart's PNG with a palette of 256 colours (a plot has far fewer): about a third of
    the bytes, the same picture to the eye. The SVG beside it stays exact."""
    from PIL import Image
    with Image.open(path) as im:
        q = im.convert("RGB").quantize(colors=256, method=Image.Quantize.MEDIANCUT)
    q.save(path, format="PNG", optimize=True)


def save_chart(fig, out: Path, name: str, header: list[str], data: list[list[Any]]) -> dict[str, Path]:
    """Write a matplotlib figure as out/name.png (palette PNG), .svg and the plotted data as .csv
    (`header`, then the rows), each through the atomic writer (a full disk leaves the previous
    file and names the path); closes the figure. Returns the three paths."""
    import matplotlib.pyplot as plt
    make_folder(out)
    paths = {ext: out / f"{name}.{ext}" for ext in ("png", "svg", "csv")}
    try:
        with atomic_path(paths["png"], "chart") as tmp:
            fig.savefig(tmp, dpi=130, bbox_inches="tight", format="png")
            palette_png(tmp)
        with atomic_path(paths["svg"], "chart") as tmp:
            fig.savefig(tmp, bbox_inches="tight", format="svg")
        rows = io.StringIO(newline="")
        w = csv.writer(rows)
        w.writerow(header)
        w.writerows(data)
        write_atomic(paths["csv"], rows.getvalue(), "chart")
    finally:
        plt.close(fig)
    return paths


def draw_speed_accuracy(pts, metric, cap, out: Path) -> dict[str, Path]:
    import matplotlib.pyplot as plt
    colors = baseline_colors([p["baseline"] for p in pts])
    scenes = ["mean"] + sorted({p["scene"] for p in pts} - {"mean"})
    cols = min(len(scenes), 3)
    nrows = math.ceil(len(scenes) / cols)
    fig, axes = plt.subplots(nrows, cols, figsize=(4.2 * cols, 3.4 * nrows), squeeze=False)
    for ax, sc in zip(axes.flat, scenes):
        _methods_panel(ax, [p for p in pts if p["scene"] == sc], metric, colors, "fps", logx=True)
        ax.set_title("mean over scenes" if sc == "mean" else sc, fontsize=10)
        ax.set_xlabel("render speed (frames per second, log scale)")
        ax.set_ylabel(METRIC_LABELS[metric])
    for ax in list(axes.flat)[len(scenes):]:
        ax.set_visible(False)
    fig.suptitle(f"{METRIC_LABELS[metric].split(' ')[0]} against render speed\n{cap}", fontsize=9)
    _legend(fig, colors, pts)
    fig.tight_layout(rect=(0, 0.05, 1, 1))
    data = [[p["method"], p["scene"], p["fps"], p[metric], p[f"{metric}_std"], p["num_gaussians"], p["model_mb"]]
            for p in pts]
    return save_chart(fig, out, f"speed_accuracy_{metric}", ["method", "scene", "fps", metric, f"{metric}_std",
                                                           "num_gaussians", "model_mb"], data)


def draw_size_accuracy(pts, metric, cap, out: Path) -> dict[str, Path]:
    import matplotlib.pyplot as plt
    colors = baseline_colors([p["baseline"] for p in pts])
    mean = [p for p in pts if p["scene"] == "mean"]
    panels = [("num_gaussians", "Gaussians (final count)")]
    if mean and all(p["model_mb"] is not None for p in mean):
        panels.append(("model_mb", "model size (MiB, tensors as stored)"))
    fig, axes = plt.subplots(1, len(panels), figsize=(4.6 * len(panels), 3.6), squeeze=False)
    for ax, (key, label) in zip(axes.flat, panels):
        # fewer is better on x: flip it so the frontier logic (larger x better) applies
        flipped = [{**p, key: -p[key]} for p in mean]
        _methods_panel(ax, flipped, metric, colors, key, logx=False)
        ax.xaxis.set_major_formatter(_neg_formatter())
        ax.set_xlabel(label + " (smaller to the right)")
        ax.set_ylabel(METRIC_LABELS[metric])
        ax.set_title("mean over scenes", fontsize=10)
    fig.suptitle(f"{METRIC_LABELS[metric].split(' ')[0]} against model size\n{cap}", fontsize=9)
    _legend(fig, colors, mean)
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    data = [[p["method"], p["num_gaussians"], p["model_mb"], p[metric]] for p in mean]
    return save_chart(fig, out, f"size_accuracy_{metric}", ["method", "num_gaussians", "model_mb", metric], data)


def _neg_formatter():
    from matplotlib.ticker import FuncFormatter
    return FuncFormatter(lambda v, _: f"{-v:,.0f}" if abs(v) >= 10 else f"{-v:.2g}")


def draw_learning_curves(pts, metric, cap, out: Path) -> dict[str, Path]:
    import matplotlib
    import matplotlib.pyplot as plt
    colors = baseline_colors([p["baseline"] for p in pts])
    methods = list(dict.fromkeys(p["method"] for p in pts))
    kinds = {(p["baseline"], p["variant"]) for p in pts}
    # labelled runs of one baseline (e.g. training lengths) get a colour each, not the baseline's
    own = len(methods) > len(kinds)
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for i, m in enumerate(methods):
        ps = [p for p in pts if p["method"] == m]
        col = matplotlib.colormaps["tab10"](i % 10) if own else colors[ps[0]["baseline"]]
        ax.plot([p["train_seconds"] for p in ps], [p[metric] for p in ps], marker="o", ms=3,
                color=col, ls="-" if ps[0]["variant"] else "--", label=m)
    ax.set_xlabel("training time (s, evaluation excluded)")
    ax.set_ylabel(METRIC_LABELS[metric])
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8, title=f"solid: {_variants(pts)}, dashed: plain", title_fontsize=8)
    n = sorted({p["scenes"] for p in pts})
    fig.suptitle(f"{METRIC_LABELS[metric].split(' ')[0]} against training time (mean over {', '.join(map(str, n))} "
                 f"scenes)\n{cap}", fontsize=9)
    fig.tight_layout()
    data = [[p["method"], p["step"], p["train_seconds"], p[metric], p["n_runs"], p["frames"]] for p in pts]
    return save_chart(fig, out, f"learning_curves_{metric}", ["method", "step", "train_seconds", metric, "n_runs",
                                                           "min_frames"], data)


def chart(paths: list[str | Path], out: str | Path, metric: str = "psnr", split: str = "test",
          charts=CHARTS) -> dict[str, dict[str, Path]]:
    """Read the runs under `paths` and write the charts into `out`; returns the files per chart."""
    import matplotlib
    matplotlib.use("Agg")
    if metric not in METRIC_LABELS:
        raise ValueError(f"metric={metric!r}: one of {sorted(METRIC_LABELS)}")
    unknown = set(charts) - set(CHARTS)
    if unknown:
        raise ValueError(f"unknown charts {sorted(unknown)}: choose from {list(CHARTS)}")
    rows = read_runs(labelled(paths), split, metric)
    cap = caption(rows)
    out = Path(out)
    files = {}
    pts = speed_points(rows, metric)
    if "speed_accuracy" in charts:
        files["speed_accuracy"] = draw_speed_accuracy(pts, metric, cap, out)
    if "size_accuracy" in charts:
        files["size_accuracy"] = draw_size_accuracy(pts, metric, cap, out)
    if "learning_curves" in charts:
        cpts = curve_points(rows, metric)
        if cpts:
            files["learning_curves"] = draw_learning_curves(cpts, metric, cap, out)
        elif list(charts) != list(CHARTS):  # asked for explicitly
            raise ValueError("no run has a learning curve (metrics.json 'curve'): train with train.eval_every > 0")
    return files
