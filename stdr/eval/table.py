"""Every table, generated from run directories' metrics.json (never typed by hand).

* The paper-style table of `stdr-eval`: rows are methods, columns are scene x metric, plus the
  mean over scenes (`collect`, then Markdown, CSV, LaTeX and JSON: `write_tables`).
* The per-run tables of `stdr-tool` (runs, gap, densify-trace, identity-check) share the reader
  of a run folder (`load_run`), the cell formats, the Markdown writer (`markdown_table`) and the
  output pair OUT.md + OUT.json (`write_outputs`).
"""
from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path
from typing import Any

from ..errors import BadInput, MissingInput, MissingKey
from ..io.checkpoint import CKPT, checkpoint_identity
from ..io.files import make_folder, read_json, read_yaml, write_atomic
from ..plugins import RESERVED_KEYS, registered_plugins
from .evaluate import commit_stamp

METRICS = ("psnr", "ssim", "lpips", "fps", "num_gaussians", "train_seconds")
HEADERS = {"psnr": "PSNR↑", "ssim": "SSIM↑", "lpips": "LPIPS↓", "fps": "FPS↑",
           "num_gaussians": "#G", "train_seconds": "train s"}
FORMATS = {"psnr": "{:.2f}", "ssim": "{:.4f}", "lpips": "{:.4f}", "fps": "{:.1f}",
           "num_gaussians": "{:,.0f}", "train_seconds": "{:.0f}"}


def fmt_value(v, f: str) -> str:
    """A cell: `f.format(v)`, or an en dash for a missing value."""
    return "–" if v is None else f.format(v)


def markdown_table(header: list[str], rows: list[list[str]]) -> str:
    """Markdown lines of a table (no trailing newline)."""
    out = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    return "\n".join(out + ["| " + " | ".join(str(c) for c in r) + " |" for r in rows])


def json_text(data: Any) -> str:
    """JSON that any reader parses: a NaN or infinite number (a diverged run's PSNR) is written as
    null, never as the bare NaN that Python's json writes and JSON does not have."""
    def clean(x):
        if isinstance(x, float):
            return x if math.isfinite(x) else None
        if isinstance(x, dict):
            return {k: clean(v) for k, v in x.items()}
        if isinstance(x, (list, tuple)):
            return [clean(v) for v in x]
        return x
    return json.dumps(clean(data), indent=1, allow_nan=False)


def write_outputs(out: Path | None, md: str, data: Any) -> None:
    """Write OUT.md (the Markdown) and OUT.json (the numbers behind it), creating the folder."""
    if out is None:
        return
    out = Path(out)
    make_folder(out.parent)
    write_atomic(out.with_suffix(".md"), md, site="table")
    write_atomic(out.with_suffix(".json"), json_text(data) + "\n", site="table")


def read_metrics(run: str | Path, split: str) -> dict[str, Any]:
    """metrics.json[split] of a run folder; the errors name the file and the splits it has, and
    refuse an entry of another checkpoint than the run's last (stale_results)."""
    mp = Path(run) / "metrics.json"
    if not mp.is_file():
        raise MissingInput(f"{mp} not found: the run has not finished, or {run} is not a stdr run directory")
    allm = read_json(mp, "metrics")
    if not isinstance(allm, dict):
        raise BadInput(f"{mp} is damaged: it holds a {type(allm).__name__}, not the splits' metrics; re-evaluate "
                       "the run (stdr-eval RUN)")
    if split not in allm:
        raise MissingKey(f"{mp} has no {split!r} entry; it has "
                       f"{sorted(k for k, v in allm.items() if isinstance(v, dict) and 'psnr' in v)}")
    stale = stale_results(run, allm[split])
    if stale:  # a result never outlives the model it measured unnoticed
        raise BadInput(f"{stale}; re-evaluate it (stdr-eval {run} reevaluate=true), or restore the checkpoint its "
                       "results came from")
    return allm[split]


def stale_results(run: str | Path, entry: dict[str, Any], what: str = "metrics.json") -> str:
    """Why a result of `run` (a metrics.json entry, pack.json, ...: a dict with "checkpoint", the
    identity of the checkpoint it came from) is not of the run's last checkpoint; "" when it is,
    when the result predates recording it, or when the run keeps no checkpoint (a study's record)."""
    src = entry.get("checkpoint") if isinstance(entry, dict) else None
    if not isinstance(src, dict) or not src.get("sha256"):
        return ""
    now = checkpoint_identity(Path(run) / CKPT)
    if now is None or now["sha256"] == src["sha256"]:
        return ""
    return (f"{Path(run) / what} is of the checkpoint at iteration {src.get('step')} (SHA-256 {src['sha256'][:12]}), "
            f"but the run's {CKPT} is at iteration {now['step']} ({now['sha256'][:12]}): its numbers are not this "
            "model's")


def find_run_dirs(paths: list[str | Path]) -> list[Path]:
    """Run folders from the arguments: a run folder itself (config.yaml), a folder holding runs at
    any depth (a Hydra multirun folder, a sweep), or a stdr-eval table.json (its runs)."""
    out: list[Path] = []
    for p in map(Path, paths):
        if p.is_file() and p.suffix == ".json":
            t = json.loads(p.read_text())
            if "cells" not in t:
                raise BadInput(f"{p}: not a stdr-eval table.json (no 'cells')")
            out += [Path(d) for m in t["cells"].values() for c in m.values() for d in c["run_dirs"]]
        elif (p / "config.yaml").is_file():
            out.append(p)
        elif p.is_dir():
            found = sorted(c.parent for c in p.rglob("config.yaml") if not c.parent.name.startswith("."))
            done = [d for d in found if (d / "metrics.json").is_file()]
            if not done:
                raise BadInput(f"{p}: no finished run directories (folders with config.yaml and metrics.json) "
                                 f"under it{f' ({len(found)} unfinished)' if found else ''}")
            if len(done) < len(found):  # a sweep still running: chart what has finished, say what not
                print(f"[stdr] {p}: skipping {len(found) - len(done)} unfinished runs (no metrics.json): "
                      + ", ".join(str(d) for d in found if d not in done))
            out += done
        else:
            raise MissingInput(f"{p}: neither a run directory, a folder of runs nor a table.json")
    if not out:
        raise BadInput("no runs given")
    return list(dict.fromkeys(out))


def load_run(run: str | Path, split: str) -> dict[str, Any]:
    """One run folder's numbers for a split: {run_dir, config (config.yaml as a dict), metrics
    (metrics.json[split]), method, scene, seed, backend (resolved; '<configured>*' for runs
    that predate recording it), profile (train_profile.json or None)}. Errors name the file."""
    run = Path(run)
    cp = run / "config.yaml"
    if not cp.is_file():
        raise MissingInput(f"{cp} not found: {run} is not a stdr run directory")
    m = read_metrics(run, split)
    cfg = read_yaml(cp)
    if not isinstance(cfg, dict) or not isinstance(cfg.get("data"), dict) or not isinstance(cfg.get("render"), dict):
        raise BadInput(f"{cp} is not a run's config (no data and render sections): restore the file the run wrote")
    prof = run / "train_profile.json"
    return {"run_dir": str(run), "config": cfg, "metrics": m, "method": method_name(cfg),
            "scene": cfg["data"]["name"], "seed": cfg.get("seed"),
            "backend": m.get("conventions", {}).get("render_backend", cfg["render"]["backend"] + "*"),
            "profile": json.loads(prof.read_text()) if prof.is_file() else None}


def method_suffix(cfg: dict) -> str:
    """What follows the baseline's name in a row label: each enabled plug-in's label and its
    row tags (PluginSpec.row_tags; e.g. '+<label> w/o <switch>'). `cfg` is a run's config as a
    plain dict; a plug-in node of a plug-in not registered in this process is labelled '+<name>'."""
    out = ""
    known = {s.name: s for s in registered_plugins()}
    for key, node in cfg.items():
        if not (isinstance(node, dict) and node.get("enabled") is True) or key in RESERVED_KEYS:
            continue
        spec = known.get(key)
        if spec is None:
            out += f"+{key}"
            continue
        tags = spec.row_tags(node)
        out += spec.label + (" " + ", ".join(tags) if tags else "")
    return out


def method_name(cfg) -> str:
    """Row label: the baseline, then each enabled plug-in's label and the tags it gives its
    non-default switches (method_suffix; e.g. 'deform+<label> w/o <switch>'), then
    the contribution pruning when on ('pruned 0.3x2': share x events; ' tw1': its time weight),
    so ablation rows, and a compact run beside its full one, never merge."""
    return cfg["baseline"]["name"] + method_suffix(cfg) + prune_tag(cfg)


def prune_tag(cfg) -> str:
    """' pruned <share>x<events>[ tw<w>]' for a run with contribution pruning, else ''."""
    p = cfg.get("prune") or {}
    share = float(p.get("share") or 0.0)
    if share <= 0:
        return ""
    tw = float(p.get("time_weight") or 0.0)
    return f" pruned {share:g}x{len(p.get('at') or [])}" + (f" tw{tw:g}" if tw else "")


def table_row(cfg: dict[str, Any], split: str, metrics: dict[str, Any], run_dir: str) -> dict[str, Any]:
    """One run's row for `collect`, from its resolved config (a plain dict)."""
    return {"method": method_name(cfg), "scene": cfg["data"]["name"], "split": split, "metrics": metrics,
            "run_dir": run_dir, "config": {k: v for k, v in cfg.items() if k not in ("eval", "train")}}


def _code_stamp(metrics: dict[str, Any]) -> str:
    return commit_stamp(metrics.get("code"))


#: what the runs of one table row must share (beside the method): name -> the run's value
ROW_FACTS = {
    "iterations": lambda r: r["metrics"].get("iterations", (r.get("config", {}).get("optim") or {}).get("iterations")),
    "budget": lambda r: r.get("config", {}).get("budget"),
    "code": lambda r: _code_stamp(r["metrics"]),
}


def check_mixed_rows(rows: list[dict[str, Any]], allow: bool = False) -> list[dict[str, Any]]:
    """A row (one method over scenes and seeds) stands for one training setting: its runs must
    share the iteration count, the budget and the code version. A row that mixes them is refused
    naming the runs and the values (BadInput); with allow=True it is kept and its label says what
    differs, e.g. 'deform [mixed iterations 100/1500]'. Returns the rows (relabelled)."""
    by_method: dict[str, list[dict[str, Any]]] = {}
    for r in rows:
        by_method.setdefault(r["method"], []).append(r)
    labels: dict[str, str] = {}
    for m, rs in by_method.items():
        mixed = []
        for fact, get in ROW_FACTS.items():
            vals = {}
            for r in rs:
                vals.setdefault(str(get(r)), r["run_dir"])
            if len(vals) > 1:
                mixed.append((fact, vals))
        if not mixed:
            continue
        if not allow:
            said = "; ".join(f"{fact} " + ", ".join(f"{v} ({d})" for v, d in vals.items()) for fact, vals in mixed)
            raise BadInput(f"the {m!r} row mixes runs of different training: {said}. Tabulate them apart, or add "
                           "allow_mixed=true to keep the row (its label then names what differs)")
        labels[m] = m + " [mixed " + "; ".join(f"{fact} {'/'.join(sorted(vals))}" for fact, vals in mixed) + "]"
    return [{**r, "method": labels.get(r["method"], r["method"])} for r in rows]


def flatten(d: dict, prefix: str = "") -> dict:
    """{"a": {"b": 1}} -> {"a.b": 1} (lists are values)."""
    out = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        out.update(flatten(v, key + ".") if isinstance(v, dict) else {key: v})
    return out


SEED_KEYS = ("seed",)  # runs of one method and scene may differ only here; they are averaged


def _std(vals: list[float]) -> float | None:
    """Sample standard deviation (n - 1), None below two values."""
    if len(vals) < 2:
        return None
    m = sum(vals) / len(vals)
    return (sum((v - m) ** 2 for v in vals) / (len(vals) - 1)) ** 0.5


def _seed_spread(rs: list[dict[str, Any]], scenes: list[str], k: str) -> tuple[float | None, int]:
    """Spread over seeds of one method's mean over scenes: each seed that has a run on every
    scene gives one scene-mean; returns (sample std of those means, how many seeds had them)."""
    by_seed: dict[Any, dict[str, float]] = {}
    for r in rs:
        seed = r.get("config", {}).get("seed")
        v = r["metrics"].get(k)
        if seed is None or v is None:
            continue
        by_seed.setdefault(seed, {})[r["scene"]] = v
    means = [sum(d[s] for s in scenes) / len(scenes) for d in by_seed.values() if all(s in d for s in scenes)]
    return _std(means), len(means)


def collect(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """rows: {method, scene, split, metrics, run_dir[, config]}. Returns {methods, scenes, cells, means}.

    Several runs of one method on one scene (seeds) are averaged, and `n_runs` records how many;
    `<metric>_std` is their sample std. A method's mean over scenes gets `<metric>_std`, the
    spread over seeds of each seed's own mean over scenes (seeds with a run on every scene,
    counted in `n_seeds`). If runs of one cell differ in config beyond the seed, that is an error
    naming the keys.
    """
    methods = list(dict.fromkeys(r["method"] for r in rows))
    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    groups: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault((r["method"], r["scene"]), []).append(r)
    cells: dict[str, dict[str, dict[str, Any]]] = {m: {} for m in methods}
    for (m, sc), rs in groups.items():
        if len(rs) > 1 and all("config" in r for r in rs):
            base = flatten(rs[0]["config"])
            for r in rs[1:]:
                other = flatten(r["config"])
                diff = sorted(k for k in base.keys() | other.keys()
                              if base.get(k) != other.get(k) and k not in SEED_KEYS)
                if diff:
                    raise BadInput(f"runs {rs[0]['run_dir']} and {r['run_dir']} are both {m!r} on {sc!r} "
                                     f"but their configs differ in {diff[:8]}; tabulate them separately")
        cell: dict[str, Any] = {}
        for k in METRICS:
            vals = [r["metrics"].get(k) for r in rs]
            cell[k] = None if any(v is None for v in vals) else sum(vals) / len(vals)
            cell[f"{k}_std"] = None if cell[k] is None else _std(vals)
        cell["n_runs"] = len(rs)
        cell["run_dirs"] = [r["run_dir"] for r in rs]
        cells[m][sc] = cell
    means = {}
    for m in methods:
        means[m] = {}
        runs = [r for r in rows if r["method"] == m]
        for k in METRICS:
            vals = [cells[m][s][k] for s in scenes if s in cells[m] and cells[m][s][k] is not None]
            complete = len(vals) == len(scenes)
            means[m][k] = sum(vals) / len(vals) if vals and complete else None
            spread, means[m]["n_seeds"] = _seed_spread(runs, scenes, k)
            means[m][f"{k}_std"] = spread if means[m][k] is not None else None
    return {"methods": methods, "scenes": scenes, "cells": cells, "means": means}


def _fmt(k, v, std=None, pm=" ± ") -> str:
    """A value, with its seed spread when there is one (e.g. '27.54 ± 0.04')."""
    if v is None:
        return "–"
    return fmt_value(v, FORMATS[k]) + ("" if std is None else pm + fmt_value(std, FORMATS[k]))


def to_rows(t: dict[str, Any], metrics=METRICS, pm=" ± ") -> tuple[list[str], list[list[str]]]:
    cols = ["method"]
    for s in t["scenes"] + ["mean"]:
        cols += [f"{s} {HEADERS[k]}" for k in metrics]
    body = []
    for m in t["methods"]:
        row = [m]
        for s in t["scenes"]:
            c = t["cells"][m].get(s, {})
            row += [_fmt(k, c.get(k), c.get(f"{k}_std"), pm) for k in metrics]
        mean = t["means"][m]
        row += [_fmt(k, mean[k], mean.get(f"{k}_std"), pm) for k in metrics]
        body.append(row)
    return cols, body


def markdown(t) -> str:
    cols, body = to_rows(t)
    return markdown_table(cols, body) + "\n"


def latex(t, metrics=("psnr", "ssim", "lpips")) -> str:
    scenes = t["scenes"] + ["mean"]
    hdr = {"psnr": "PSNR$\\uparrow$", "ssim": "SSIM$\\uparrow$", "lpips": "LPIPS$\\downarrow$",
           "fps": "FPS$\\uparrow$", "num_gaussians": "\\#G", "train_seconds": "train s"}
    out = ["\\begin{tabular}{l" + "c" * (len(metrics) * len(scenes)) + "}", "\\toprule"]
    out.append("Method & " + " & ".join(f"\\multicolumn{{{len(metrics)}}}{{c}}{{{s}}}" for s in scenes) + " \\\\")
    out.append(" & " + " & ".join(hdr[k] for _ in scenes for k in metrics) + " \\\\")
    out.append("\\midrule")
    _, body = to_rows(t, metrics, pm=" $\\pm$ ")
    for r in body:
        out.append(" & ".join(x.replace("_", "\\_") for x in r) + " \\\\")
    out += ["\\bottomrule", "\\end{tabular}"]
    return "\n".join(out) + "\n"


def write_tables(t: dict[str, Any], out_dir: Path) -> dict[str, Path]:
    """table.md, .csv, .tex and .json in out_dir, each written atomically (stdr.io.files)."""
    make_folder(out_dir)
    paths = {"md": out_dir / "table.md", "csv": out_dir / "table.csv", "tex": out_dir / "table.tex",
             "json": out_dir / "table.json"}
    cols, body = to_rows(t)
    buf = io.StringIO(newline="")
    w = csv.writer(buf)
    w.writerow(cols)
    w.writerows(body)
    for k, text in (("md", markdown(t)), ("csv", buf.getvalue()), ("tex", latex(t)), ("json", json_text(t))):
        write_atomic(paths[k], text, site="table")
    return paths
