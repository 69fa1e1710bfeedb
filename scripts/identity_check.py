#!/usr/bin/env python
"""Bit-identity of training between two commits: every baseline with and without STDR.

`run` trains each of the eight configurations for 60 steps on the tiny embedded scene of the
tests, on a schedule that crosses every phase boundary (static warm-up, densification with an
opacity reset, STDR's warm-up / regularized / frozen phases, SC-GS's node -> skinning switch),
and saves the final parameters, deformation state and test PSNR. `compare` says, for each
configuration, whether two saved files hold bit-identical tensors.

    # the code of another commit: a worktree on PYTHONPATH, run from inside it
    git worktree add /tmp/old <commit> && (cd /tmp/old && PYTHONPATH=/tmp/old python <this file> run /tmp/old.pt)
    scripts/run.sh python scripts/identity_check.py run /tmp/new.pt
    scripts/run.sh python scripts/identity_check.py compare /tmp/old.pt /tmp/new.pt --labels <old> <new> --out X
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


def run(out: Path) -> None:
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
            t = Trainer(_tiny(d, SCHEDULE + extra + [f"experiment=embedded_{name}"]), d / "run",
                        splits=("train", "test"))
            t.train()
            psnr = t.evaluate("test")["psnr"]
            m = getattr(t, "model", t)  # the model object (since checkpoint format 2), or the old trainer
            res[name] = {"params": {k: v.detach().cpu().clone() for k, v in m.params.items()},
                         "deform": {k: v.cpu().clone() for k, v in m.deform.state_dict().items()}, "psnr": psnr}
            print(f"{name}: {m.params['means'].shape[0]} Gaussians, test PSNR {psnr!r}", flush=True)
    torch.save(res, out)


def compare(a_path: Path, b_path: Path, labels: list[str], out: Path | None) -> bool:
    a, b = torch.load(a_path, weights_only=True), torch.load(b_path, weights_only=True)
    rows = []
    for name in NAMES:
        x, y = a[name], b[name]
        same = (x["params"].keys() == y["params"].keys() and x["deform"].keys() == y["deform"].keys()
                and all(torch.equal(x["params"][k], y["params"][k]) for k in x["params"])
                and all(torch.equal(x["deform"][k], y["deform"][k]) for k in x["deform"]))
        rows.append({"config": name, "bit_identical": same, "psnr": [x["psnr"], y["psnr"]],
                     "gaussians": [int(x["params"]["means"].shape[0]), int(y["params"]["means"].shape[0])]})
    md = [f"Training bit-identity, {labels[0]} vs {labels[1]} (60 steps, every phase boundary; "
          "scripts/identity_check.py).", "",
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run")
    r.add_argument("out", type=Path)
    c = sub.add_parser("compare")
    c.add_argument("a", type=Path)
    c.add_argument("b", type=Path)
    c.add_argument("--labels", nargs=2, default=["a", "b"])
    c.add_argument("--out", type=Path, default=None, help="write OUT.md and OUT.json")
    args = ap.parse_args()
    if args.cmd == "run":
        run(args.out)
    elif not compare(args.a, args.b, args.labels, args.out):
        raise SystemExit(1)


if __name__ == "__main__":
    main()
