"""ATen operators dispatched by one ordinary training step, per section of the trainer's profiler.

A machine-independent proxy for the launches of a GPU step (the step is launch-bound there:
docs/performance.md) and for the Python overhead of a CPU step. For each experiment: the
trainer at budget=cpu on a D-NeRF scene, set near the end of its schedule (every phase on:
the deformation, STDR's frozen mask, the full SH degree; densification off), three untimed
steps, then one step counted with `stdr.syncs.OpCounter`, split by profiler section
(deform, render_fwd, loss, regularizers, backward, guard, optimizer, densify) with the most
frequent operators of each. Two counts: every operator dispatched, and the "compute" ones that
launch work (views such as t, view, slice or detach launch no kernel on a GPU, nor do bare
allocations or profiler records). Counts are deterministic: they do not depend on the machine.

    python -m studies.ops_per_step --scene ../shared/data/dnerf/jumpingjacks --label after \\
        --out research/measurements/ops_per_step/counts
    python -m studies.ops_per_step --compare research/measurements/ops_per_step/counts/before.json \\
        research/measurements/ops_per_step/counts/after.json research/measurements/ops_per_step/counts/fused.json \\
        --out research/measurements/ops_per_step

(The counts are in the study's records archive: `python -m studies.records extract ops_per_step`.)
"""
from __future__ import annotations

import argparse
import json
import platform
import tempfile
from collections import Counter, defaultdict
from contextlib import contextmanager
from pathlib import Path

# allocations that fill nothing: no kernel on a GPU
ALLOCATIONS = {"aten.empty", "aten.empty_like", "aten.empty_strided", "aten.new_empty", "aten.new_empty_strided"}
EXPERIMENTS = ["dnerf_deform", "dnerf_deform_stdr", "dnerf_scgs", "dnerf_scgs_stdr", "dnerf_spgs",
               "dnerf_spgs_stdr", "dnerf_4dgs", "dnerf_4dgs_stdr"]


def count(exp: str, scene: Path, overrides: list[str]) -> dict:
    import torch  # noqa: F401  (imported here: --compare needs no torch)

    from torch.utils._python_dispatch import TorchDispatchMode

    from stdr.store import compose_config
    from stdr.train.timing import Profiler
    from stdr.train.trainer import Trainer

    class OpCounter(TorchDispatchMode):
        """Every ATen operator dispatched (`ops`, `by_op`) and those that launch work (`compute`):
        not a view (no kernel: t, view, slice, detach, ...), an allocation without a fill (empty,
        empty_like, ...) or a profiler record. The study's own counter, so that any commit's code
        is counted the same way."""

        def __init__(self):
            super().__init__()
            self.ops, self.compute, self.by_op, self.by_compute = 0, 0, Counter(), Counter()

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            name = str(func.overloadpacket)
            self.ops += 1
            self.by_op[name] += 1
            if not (func.is_view or name in ALLOCATIONS or name.startswith("profiler.")):
                self.compute += 1
                self.by_compute[name] += 1
            return func(*args, **(kwargs or {}))

    class SectionCounter(Profiler):
        """The trainer's profiler, counting operators per section instead of timing."""

        def __init__(self, oc):
            super().__init__()
            self.oc, self.ops, self.compute, self.by_op = oc, Counter(), Counter(), defaultdict(Counter)

        @contextmanager
        def __call__(self, name):
            n0, c0, b0 = self.oc.ops, self.oc.compute, Counter(self.oc.by_compute)
            yield
            self.ops[name] += self.oc.ops - n0
            self.compute[name] += self.oc.compute - c0
            self.by_op[name] += Counter(self.oc.by_compute) - b0

        def backward(self, loss):
            with self("backward"):
                loss.backward()

    cfg = compose_config([f"experiment={exp}", "budget=cpu", f"data.path={scene}", "train.progress=false",
                          "eval.lpips=false", "train.eval_every=0", "train.eval_at_warmup_end=false",
                          "densify.refine_start=1000000000", *overrides])
    with tempfile.TemporaryDirectory() as tmp:
        tr = Trainer(cfg, tmp, splits=("train",))
        tr.step = cfg.optim.iterations - 10
        for _ in range(3):
            tr.train_step()
        with OpCounter() as oc:
            tr.profile = SectionCounter(oc)
            tr.train_step()
        sections = dict(tr.profile.ops)
        sections["other"] = oc.ops - sum(sections.values())
        compute = dict(tr.profile.compute)
        compute["other"] = oc.compute - sum(compute.values())
        return {"experiment": exp, "ops": oc.ops, "compute_ops": oc.compute, "sections": sections,
                "compute_sections": compute, "backend": tr.backend, "gaussians": tr.state.model.num_gaussians,
                "top_compute": {s: c.most_common(8) for s, c in tr.profile.by_op.items() if c}}


def _code(c) -> str:
    """A code_version() record as its commit stamp (stdr.eval.evaluate.commit_stamp)."""
    from stdr.eval.evaluate import commit_stamp
    return commit_stamp(c) if isinstance(c, dict) else str(c)


def markdown(res: dict) -> str:
    secs = sorted({s for r in res["rows"] for s in r["compute_sections"]})
    head = ["experiment", "ops/step", "compute ops/step", *(f"{s} (compute)" for s in secs)]
    lines = [f"Operators per ordinary training step ({res['label']}; studies/ops_per_step.py), budget=cpu, "
             f"{Path(res['scene']).name}; code {_code(res['code'])}, torch {res['torch']}, {res['machine']}. "
             "ops: every ATen operator dispatched; compute: those that launch work (not views, bare "
             "allocations or profiler records); sections: the compute ops of each profiler section.", "",
             "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in res["rows"]:
        lines.append("| " + " | ".join([r["experiment"], str(r["ops"]), str(r["compute_ops"]),
                                        *(str(r["compute_sections"].get(s, 0)) for s in secs)]) + " |")
    return "\n".join(lines) + "\n"


def compare(a: dict, *later: dict) -> str:
    """Each later count against the first, per experiment: operators and compute operators, with
    the ratio to the first."""
    rows = [{r["experiment"]: r for r in res["rows"]} for res in later]
    codes = "; ".join(f"{res['label']} (code {_code(res['code'])})" for res in later)
    lines = [f"Operators per ordinary training step: {a['label']} (code {_code(a['code'])}) against {codes}; "
             f"studies/ops_per_step.py, budget=cpu, {Path(later[-1]['scene']).name}. Ratios are to {a['label']}.", ""]
    head = ["experiment", f"ops {a['label']}"] + [f"ops {r['label']} (ratio)" for r in later] + \
        [f"compute ops {a['label']}"] + [f"compute ops {r['label']} (ratio)" for r in later]
    lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in a["rows"]:
        e = r["experiment"]
        if not all(e in rs for rs in rows):
            continue
        o, c = r["ops"], r["compute_ops"]
        cells = [e, str(o)] + [f"{rs[e]['ops']} ({rs[e]['ops'] / o:.2f})" for rs in rows] + [str(c)] + \
            [f"{rs[e]['compute_ops']} ({rs[e]['compute_ops'] / c:.2f})" for rs in rows]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", type=Path, help="a D-NeRF scene folder")
    ap.add_argument("--experiments", nargs="+", default=EXPERIMENTS)
    ap.add_argument("--label", default="this checkout")
    ap.add_argument("--out", type=Path, help="folder: <label>.json and .md (with --compare: compare.md)")
    ap.add_argument("--compare", nargs="+", type=Path, metavar="JSON",
                    help="two or more counts: each later one against the first")
    ap.add_argument("overrides", nargs="*", help="config overrides for every experiment")
    a = ap.parse_args(argv)
    if a.compare:
        if len(a.compare) < 2:
            ap.error("--compare needs at least two counts (JSON files)")
        text = compare(*(json.loads(p.read_text()) for p in a.compare))
        print(text, end="")
        if a.out:
            a.out.mkdir(parents=True, exist_ok=True)
            (a.out / "compare.md").write_text(text)
        return 0
    if a.scene is None:
        ap.error("--scene is required (a D-NeRF scene folder), unless --compare")
    import torch

    from stdr.eval.evaluate import code_version, machine_name
    rows = []
    for exp in a.experiments:
        r = count(exp, a.scene.resolve(), a.overrides)
        print(f"{exp}: {r['ops']} ops/step, {r['compute_ops']} compute " +
              " ".join(f"{k}={v}" for k, v in r["compute_sections"].items()), flush=True)
        rows.append(r)
    res = {"label": a.label, "scene": str(a.scene), "code": code_version(), "machine": machine_name(),
           "platform": platform.platform(), "torch": torch.__version__, "overrides": a.overrides, "rows": rows}
    if a.out:
        a.out.mkdir(parents=True, exist_ok=True)
        (a.out / f"{a.label}.json").write_text(json.dumps(res, indent=1) + "\n")
        (a.out / f"{a.label}.md").write_text(markdown(res))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
