"""Bit-identity of training between two commits: every baseline with and without STDR.

`run` trains each of the eight configurations for 60 steps on the tiny embedded scene of the
tests, on a schedule that crosses every phase boundary (static warm-up, densification with an
opacity reset, STDR's warm-up / regularized / frozen phases, SC-GS's node -> skinning switch),
and saves the final parameters, deformation state and test PSNR. `compare` says, for each
configuration, whether two saved files hold bit-identical tensors.

    # the code of another commit: a worktree on PYTHONPATH, this file run by its path from inside it
    git worktree add /tmp/old <commit> && (cd /tmp/old && PYTHONPATH=/tmp/old python <this file> run /tmp/old.pt)
    stdr-tool identity-check run /tmp/new.pt
    stdr-tool identity-check compare /tmp/old.pt /tmp/new.pt --labels <old> <new> --out X

`configs` composes every experiment under every budget (the resolved config `stdr-train` would
run with) into a JSON file; `compare-configs` says which composed configs differ between two such
files. Keys a commit removed on purpose are named with --removed (dotted paths, `*` matches one
level) and reported apart from real differences.

It imports stdr inside its functions, and looks names up where each commit keeps them
(`_of_checkout`): the code it runs is that of whichever commit is checked out, not this one's.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import torch

SCHEDULE = ["optim.iterations=60", "baseline.warmup=20", "densify.refine_start=10", "densify.refine_every=10",
            "densify.reset_every=30", "densify.prune_big_after=30", "train.checkpoint_every=0",
            "train.eval_at_warmup_end=false", "baseline.scgs.node_stage_end=40", "baseline.scgs.main_warmup=5",
            "baseline.scgs.num_nodes=64", "baseline.scgs.arap_steps=[0,10,20,30,31]",
            "baseline.spgs.num_superpoints=50", "baseline.hexplane.base_res=16"]
STDR_PHASES = ["stdr.warmup_end=20", "stdr.freeze_at=30"]
NAMES = [f"{b}{s}" for b in ("deform", "scgs", "spgs", "4dgs") for s in ("", "_stdr")]


def _dnerf_config(scene: Path, overrides: list[str]):
    """budget=cpu on a D-NeRF scene (1500 initial points, 100 px wide, no LPIPS) with the short
    schedule, composed by the checked-out code's own Hydra configs (any commit)."""
    from hydra import compose, initialize_config_dir

    from stdr.config import CONFIG_DIR
    register = _of_checkout("register", "stdr.store", "stdr.config")
    try:  # per-baseline configs reject other baselines' keys
        from stdr.testing import applicable
    except ImportError:
        def applicable(o, name):
            return o
    register()
    base = [f"data.path={scene}", f"data.name={scene.name}", "budget=cpu", "data.max_width=100",
            "model.init_num=1500", "eval.lpips=false", "train.progress=false", "eval.save_images=false",
            "train.image_every=0", *overrides]
    name = next(o.split("=", 1)[1] for o in overrides if o.startswith("experiment=")).split("_")[1]
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base=None):
        return compose("train", overrides=applicable(base, name))


def run(out: Path, scene: Path | None = None) -> None:
    """scene: a D-NeRF scene folder (experiments dnerf_*), else the tiny embedded scene."""
    try:  # the tiny scene of the checked-out code: stdr.testing, or the tests of commits before it
        from stdr.testing import tiny_config as _tiny
    except ImportError:
        sys.path.insert(0, str(Path.cwd() / "tests"))
        from test_train import _tiny

    from stdr.train.trainer import Trainer
    res = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name in NAMES:
            extra = STDR_PHASES if name.endswith("_stdr") else []
            d = Path(tmp) / name
            cfg = (_tiny(d, SCHEDULE + extra + [f"experiment=embedded_{name}"]) if scene is None
                   else _dnerf_config(scene.resolve(), SCHEDULE + extra + [f"experiment=dnerf_{name}"]))
            t = Trainer(cfg, d / "run", splits=("train", "test"))
            t.train()
            psnr = t.evaluate("test")["psnr"]
            # the model: in the run's state (RunState), on the trainer (checkpoint format 2), or the old trainer itself
            m = t.state.model if hasattr(t, "state") else getattr(t, "model", t)
            res[name] = {"params": {k: v.detach().cpu().clone() for k, v in m.params.items()},
                         "deform": {k: v.cpu().clone() for k, v in m.deform.state_dict().items()}, "psnr": psnr}
            print(f"{name}: {m.params['means'].shape[0]} Gaussians, test PSNR {psnr!r}", flush=True)
    torch.save(res, out)


def compare(a_path: Path, b_path: Path, labels: list[str], out: Path | None,
            scene: str = "tiny embedded scene") -> bool:
    a, b = torch.load(a_path, weights_only=True), torch.load(b_path, weights_only=True)
    rows = []
    for name in NAMES:
        x, y = a[name], b[name]
        same = (x["params"].keys() == y["params"].keys() and x["deform"].keys() == y["deform"].keys()
                and all(torch.equal(x["params"][k], y["params"][k]) for k in x["params"])
                and all(torch.equal(x["deform"][k], y["deform"][k]) for k in x["deform"]))
        rows.append({"config": name, "bit_identical": same, "psnr": [x["psnr"], y["psnr"]],
                     "gaussians": [int(x["params"]["means"].shape[0]), int(y["params"]["means"].shape[0])]})
    md = [f"Training bit-identity, {labels[0]} vs {labels[1]} ({scene}; 60 steps, every phase boundary; "
          "stdr-tool identity-check).", "",
          f"| config | bit-identical | test PSNR {labels[0]} | test PSNR {labels[1]} | #G |", "|---|---|---|---|---|"]
    for r in rows:
        md.append(f"| {r['config']} | {'yes' if r['bit_identical'] else 'NO'} | {r['psnr'][0]!r} | {r['psnr'][1]!r} | "
                  f"{r['gaussians'][0]} / {r['gaussians'][1]} |")
    text = "\n".join(md) + "\n"
    print(text, end="")
    if out is not None:
        out.with_suffix(".md").write_text(text)
        out.with_suffix(".json").write_text(json.dumps({"labels": labels, "rows": rows}, indent=1) + "\n")
    return all(r["bit_identical"] for r in rows)


BUDGETS = ("cpu", "demo", "paper")


def _of_checkout(name: str, *modules: str):
    """`name` from the first of `modules` (newest place first) that has it in the checked-out
    code: the commits compared keep their configs' helpers in different modules."""
    import importlib
    for m in modules:
        try:
            return getattr(importlib.import_module(m), name)
        except (ImportError, AttributeError):
            continue
    raise ImportError(f"{name} is in none of {modules} in this checkout")


def experiment_names() -> list[str]:
    """Every selectable experiment: the registered ones (derived), else the YAML files of older commits."""
    try:
        return _of_checkout("experiment_names", "stdr.store", "stdr.config")()
    except ImportError:
        from stdr.config import CONFIG_DIR
        return sorted(p.stem for p in (Path(CONFIG_DIR) / "experiment").glob("*.yaml"))


def configs(out: Path) -> None:
    from omegaconf import OmegaConf

    compose_config = _of_checkout("compose_config", "stdr.store", "stdr.cli.common")
    res = {}
    for name in experiment_names():
        for budget in BUDGETS:
            cfg = compose_config([f"experiment={name}", f"budget={budget}", "data.path=/data/scene"])
            res[f"{name}/{budget}"] = OmegaConf.to_container(cfg, resolve=True)
    out.write_text(json.dumps(res, indent=1, sort_keys=True) + "\n")
    print(f"{len(res)} composed configs -> {out}")


def _matches(key: str, pattern: str) -> bool:
    k, p = key.split("."), pattern.split(".")
    return len(k) >= len(p) and all(a == b or b == "*" for a, b in zip(k, p))


def compare_configs(a_path: Path, b_path: Path, removed: list[str], labels: list[str], out: Path | None) -> bool:
    from stdr.eval.table import flatten
    a, b = json.loads(a_path.read_text()), json.loads(b_path.read_text())
    rows = []
    for name in sorted(set(a) | set(b)):
        if name not in a or name not in b:
            rows.append({"config": name, "status": f"only in {labels[0] if name in a else labels[1]}"})
            continue
        fa, fb = flatten(a[name]), flatten(b[name])
        gone = sorted(k for k in set(fa) - set(fb) if any(_matches(k, p) for p in removed))
        diff = sorted(k for k in set(fa) | set(fb) if k not in gone and fa.get(k, "<absent>") != fb.get(k, "<absent>"))
        rows.append({"config": name, "status": "differs" if diff else "identical", "differences": diff,
                     "removed_keys": len(gone)})
    same = sum(r["status"] == "identical" for r in rows)
    common = sum(not r["status"].startswith("only") for r in rows)
    added = [r["config"] for r in rows if r["status"] == f"only in {labels[1]}"]
    text = (f"Composed configs, {labels[0]} vs {labels[1]}: {same} of the {common} in both identical"
            f" (keys removed on purpose: {', '.join(removed) or 'none'}); {len(added)} new in {labels[1]}"
            + (f" ({', '.join(sorted({a.split('/')[0] for a in added}))})" if added else "") + ".\n")
    for r in rows:
        if r["status"] not in ("identical", f"only in {labels[1]}"):
            text += f"  {r['config']}: {r['status']} {r.get('differences', '')}\n"
    print(text, end="")
    if out is not None:
        out.with_suffix(".md").write_text(text + "\n(stdr-tool identity-check configs / compare-configs; every "
                                          f"experiment x budgets {', '.join(BUDGETS)}.)\n")
        out.with_suffix(".json").write_text(json.dumps({"labels": labels, "removed": removed, "rows": rows},
                                                       indent=1) + "\n")
    return same == common and common + len(added) == len(rows)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(prog="stdr-tool identity-check", description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run")
    r.add_argument("out", type=Path)
    r.add_argument("--dnerf", type=Path, default=None, metavar="SCENE",
                   help="train on this D-NeRF scene folder (budget=cpu, 100 px) instead of the tiny embedded scene")
    c = sub.add_parser("compare")
    c.add_argument("a", type=Path)
    c.add_argument("b", type=Path)
    c.add_argument("--labels", nargs=2, default=["a", "b"])
    c.add_argument("--out", type=Path, default=None, help="write OUT.md and OUT.json")
    c.add_argument("--scene", default="tiny embedded scene", help="what the runs trained on, for the report")
    g = sub.add_parser("configs")
    g.add_argument("out", type=Path)
    h = sub.add_parser("compare-configs")
    h.add_argument("a", type=Path)
    h.add_argument("b", type=Path)
    h.add_argument("--removed", nargs="*", default=[])
    h.add_argument("--labels", nargs=2, default=["a", "b"])
    h.add_argument("--out", type=Path, default=None, help="write OUT.md and OUT.json")
    args = ap.parse_args(argv)
    if args.cmd == "run":
        run(args.out, args.dnerf)
    elif args.cmd == "configs":
        configs(args.out)
    elif args.cmd == "compare-configs":
        if not compare_configs(args.a, args.b, args.removed, args.labels, args.out):
            raise SystemExit(1)
    elif not compare(args.a, args.b, args.labels, args.out, args.scene):
        raise SystemExit(1)


if __name__ == "__main__":
    main()
