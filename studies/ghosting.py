"""The ghosting case: an object jumps between two places (procedural motion=jump).

Trains the baseline and the baseline + STDR on the same tiny scene, then prints test PSNR per run
and, for STDR, the mean activated mask of the Gaussians near each place at that place's times
and at the other place's times. JSON goes to --out. About a minute on 2 CPU cores.

    python -m studies.ghosting --out outputs/ghosting.json [--iterations 600]
"""
from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from stdr.config import CONFIG_DIR
from stdr.store import register
from stdr.data.procedural import JUMP_A, JUMP_B, SceneOptions, jump_at_a
from stdr.plugins.stdr import MASK_KEY
from stdr.train.trainer import Trainer


def overrides(iterations: int, cache: Path) -> list[str]:
    return ["data.procedural.resolution=64", "data.procedural.n_train=40", "data.procedural.n_val=2",
            "data.procedural.n_test=8", "data.procedural.motion=jump", f"data.cache_dir={cache}",
            "model.init_num=2000", "eval.lpips=false", "train.progress=false", "eval.save_images=false",
            f"optim.iterations={iterations}", f"baseline.warmup={iterations // 3}", "densify.refine_start=50",
            f"densify.refine_stop={iterations * 3 // 4}", "densify.refine_every=50", "densify.max_gaussians=6000",
            "train.eval_at_warmup_end=false", "train.image_every=0", "train.checkpoint_every=0"]


def mask_by_place(t: Trainer) -> dict:
    opt = SceneOptions(**OmegaConf.to_container(t.cfg.data.procedural))
    at_a = torch.from_numpy(jump_at_a(t.state.model.plugin("stdr").knots.numpy(), opt))
    a = torch.sigmoid(t.state.model.params[MASK_KEY].detach())
    out = {}
    for name, place, on in (("A", JUMP_A, at_a), ("B", JUMP_B, ~at_a)):
        near = (t.state.model.params["means"].detach() - torch.tensor(place, dtype=torch.float32)).norm(dim=1) < 0.3
        out[name] = {"gaussians_near": int(near.sum()), "mask_at_own_times": float(a[near][:, on].mean()),
                     "mask_at_other_times": float(a[near][:, ~on].mean())}
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(prog="python -m studies.ghosting", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--iterations", type=int, default=600)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    register()
    res = {}
    with tempfile.TemporaryDirectory() as tmp, initialize_config_dir(config_dir=str(CONFIG_DIR), version_base=None):
        for exp in ("embedded_deform", "embedded_deform_stdr"):
            cfg = compose("train", overrides=overrides(args.iterations, Path(tmp) / "cache") +
                          [f"experiment={exp}", f"seed={args.seed}"])
            t = Trainer(cfg, Path(tmp) / exp, splits=("train", "test"))
            t.train()
            ev = t.evaluate("test")
            res[exp] = {"psnr": ev["psnr"], "per_frame_psnr": ev["per_frame_psnr"],
                        "num_gaussians": ev["num_gaussians"], "train_seconds": t.state.train_seconds}
            if t.state.model.plugin("stdr") is not None:
                res[exp]["mask_by_place"] = mask_by_place(t)
            print(exp, json.dumps(res[exp]))
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
