"""The single training loop shared by every baseline.

Baselines differ only in the deformation module (stdr.deform) and their config.
"""
from __future__ import annotations

import json
import time
from collections import defaultdict
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Optional

import numpy as np
import torch
from omegaconf import OmegaConf
from torch import Tensor

from ..data.load import load_scene
from ..data.types import Frame
from ..decouple import MASK_KEY, STDR
from ..device import resolve_device
from ..deform import build_deformation, deformation_kwargs
from ..metrics import l1, psnr, ssim
from ..render import RenderOutput, render, resolve_backend
from ..scene.gaussians import Gaussians, activate, init_params, num_gaussians, random_cube_points, scene_extent
from ..scene.ply import save_ply
from ..scene.strategy import DensifyStrategy
from .checkpoint import load_checkpoint, rng_state, save_checkpoint, set_rng_state
from .schedule import exp_lr

CKPT = "checkpoints/last.pt"


class Profiler:
    """Accumulated wall time per named section of the training step."""

    def __init__(self):
        self.seconds: dict[str, float] = defaultdict(float)

    @contextmanager
    def __call__(self, name: str):
        t0 = time.perf_counter()
        yield
        self.seconds[name] += time.perf_counter() - t0


class CameraSampler:
    """Training frames drawn without replacement per epoch, from its own generator."""

    def __init__(self, n: int, seed: int):
        self.n = n
        self.gen = torch.Generator().manual_seed(seed)
        self.stack: list[int] = []

    def next(self) -> int:
        if not self.stack:
            self.stack = torch.randperm(self.n, generator=self.gen, device="cpu").tolist()
        return self.stack.pop()

    def state_dict(self):
        return {"gen": self.gen.get_state(), "stack": list(self.stack)}

    def load_state_dict(self, s):
        self.gen.set_state(s["gen"])
        self.stack = list(s["stack"])


def build_deformation_from_cfg(cfg, cond_dim: int = 0, train_times=None):
    b = cfg.baseline
    return build_deformation(b.name, **deformation_kwargs(b, cond_dim, train_times, seed=cfg.seed))


class Trainer:
    def __init__(self, cfg, run_dir: str | Path, splits=("train",), data_base: Optional[str] = None,
                 init_gaussians: bool = True):
        """Set up a run. With init_gaussians=False the Gaussians are left empty for `load()`."""
        self.cfg = cfg
        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        if cfg.train.threads > 0:
            torch.set_num_threads(cfg.train.threads)
        self.device = resolve_device(cfg.device)
        torch.manual_seed(cfg.seed)  # also seeds every CUDA device
        np.random.seed(cfg.seed)
        self.scene = load_scene(cfg.data, splits, base=data_base).to(self.device)  # images moved once
        self.background = torch.tensor(self.scene.background, dtype=torch.float32, device=self.device)
        self.backend = resolve_backend(cfg.render.backend, self.device)
        gen = torch.Generator().manual_seed(cfg.seed)  # initial points and colours: drawn on the CPU, the same on every device
        m = cfg.model
        if not init_gaussians:
            pts = None
        elif m.init == "random":
            pts = random_cube_points(m.init_num, m.init_extent, gen)
        elif m.init == "points":
            if self.scene.init_points is None:
                raise ValueError(f"model.init=points but {self.scene.root} provides no points; use model.init=random")
            pts = torch.from_numpy(self.scene.init_points).float()
        else:
            raise ValueError(f"model.init={m.init!r}: use 'random' or 'points'")
        if pts is None:
            self.params = torch.nn.ParameterDict()
        else:
            colors = torch.rand(pts.shape[0], 3, generator=gen)
            if m.init == "points" and self.scene.init_colors is not None:
                colors = torch.from_numpy(self.scene.init_colors).float()
            self.params = init_params(pts.to(self.device), colors.to(self.device), sh_degree=m.sh_degree,
                                      init_opacity=m.init_opacity)
        self.stdr = self._make_stdr() if cfg.stdr.enabled else None
        if self.stdr is not None and pts is not None:
            self.stdr.add_mask(self.params)
        train_times = self.scene.train_times() if "train" in self.scene.splits else None
        self.deform = build_deformation_from_cfg(cfg, cond_dim=self.stdr.cond_dim if self.stdr else 0,
                                                 train_times=train_times).to(self.device)
        if self.stdr is not None:
            moved = self.stdr.avoid_stage_switches(self.deform.stage_switches())
            if moved:
                print(moved)
        if pts is not None:  # per-Gaussian state of the baseline (kept aligned by densification)
            self.deform.setup(self.params, train_times)
            for k, v in self.deform.gaussian_params(len(pts)).items():
                self.params[k] = torch.nn.Parameter(v.to(self.device))
        self.optimizers = self._make_optimizers()
        groups = [dict(g) for g in self.deform.param_groups()]
        if self.stdr is not None and self.stdr.field is not None:  # trained on the deformation's schedule
            groups.append({"params": list(self.stdr.field.parameters()), "name": "stdr_field", "lr_mult": 1.0})
        self.deform_opt = torch.optim.Adam(groups, lr=cfg.baseline.lr_init, eps=1e-15)
        self.strategy = DensifyStrategy(**OmegaConf.to_container(cfg.densify))
        extent = scene_extent(self.scene.camera_centers("train")) if "train" in self.scene.splits else 1.0
        white = all(float(c) >= 1.0 for c in self.scene.background)
        self.strategy_state = self.strategy.initialize_state(len(pts) if pts is not None else 0, extent,
                                                             white_background=white, device=self.device)
        self.sampler = CameraSampler(len(self.scene.splits.get("train", [])), cfg.seed)
        self.step = 0
        self.train_seconds = 0.0
        self.profile = Profiler()
        self.history: list[dict[str, Any]] = []
        self.writer = None

    def _make_stdr(self) -> STDR:
        """The STDR plug-in; its time knots come from the training split (or later the checkpoint)."""
        c = self.cfg
        knots = STDR.knots_for(c.stdr, self.scene.train_times()) if "train" in self.scene.splits else None
        return STDR(c.stdr, c.baseline.warmup, knots, xyz_freqs=c.baseline.xyz_freqs, seed=c.seed,
                    iterations=c.optim.iterations, init_opacity=c.model.init_opacity, device=self.device)

    # ----------------------------------------------------------------- optimizers
    def _lr(self, key: str, step: int) -> float:
        o = self.cfg.optim
        s = o.spatial_lr_scale
        if key == "means":
            return exp_lr(step, o.means_lr_init * s, o.means_lr_final * s, o.means_lr_max_steps)
        fixed = {"scales": o.scales_lr * s, "quats": o.quats_lr, "opacities": o.opacities_lr,
                 "sh0": o.sh0_lr, "shN": o.shN_lr, MASK_KEY: self.cfg.stdr.mask_lr}
        if key not in fixed and self.deform.gaussian_lr(key) is not None:
            return self.deform.gaussian_lr(key)
        if key not in fixed:
            raise KeyError(f"no learning rate configured for per-Gaussian parameter {key!r}")
        return fixed[key]

    def _make_optimizers(self) -> dict[str, torch.optim.Optimizer]:
        """One Adam per per-Gaussian parameter, including those frozen for a phase (STDR), so the
        optimizer set does not depend on the step; a parameter without a gradient is not updated."""
        return {k: torch.optim.Adam([{"params": [p], "lr": self._lr(k, 0), "name": k}], eps=1e-15)
                for k, p in self.params.items()}

    def _update_lrs(self, step: int) -> None:
        for k, opt in self.optimizers.items():
            for g in opt.param_groups:
                g["lr"] = self._lr(k, step)
        b = self.cfg.baseline
        s = max(step - b.warmup, 0) if b.lr_from_warmup else step
        for g in self.deform_opt.param_groups:
            g["lr"] = exp_lr(s, b.lr_init, b.lr_final, b.lr_max_steps) * g.get("lr_mult", 1.0)

    # ----------------------------------------------------------------- rendering
    def sh_degree(self, step: int) -> int:
        m = self.cfg.model
        return min(m.sh_degree, step // max(m.sh_interval, 1))

    def conditioning(self, step: int) -> tuple[Optional[Tensor], Optional[Tensor]]:
        """(cond [N, cond_dim], delta scale [N, 1]) for the deformation network at `step`: STDR's
        separated field, or (None, None) without it or during the static warm-up."""
        if self.stdr is None or step < self.cfg.baseline.warmup:
            return None, None
        return self.stdr.conditioning(self.params, step)

    def deformed(self, t: float, step: int,
                 cond_scale: Optional[tuple[Optional[Tensor], Optional[Tensor]]] = None) -> Gaussians:
        """Activated Gaussians at time t: deformed after the static warm-up, opacity times the
        STDR mask when it is on. cond_scale: this step's `conditioning` (computed when None)."""
        s = self.stdr
        if step < self.cfg.baseline.warmup:
            g = activate(self.params)
        else:
            cond, scale = self.conditioning(step) if cond_scale is None else cond_scale
            g = self.deform.deform(self.params, t, cond, scale)
        if s is not None:
            f = s.opacity_factor(self.params, t, step)
            if f is not None:
                g = g._replace(opacities=g.opacities * f)
        return g

    def set_training(self, mode: bool) -> None:
        """Train mode (BatchNorm batch statistics, dropout) in train steps, eval mode elsewhere."""
        self.deform.train(mode)
        if self.stdr is not None and self.stdr.field is not None:
            self.stdr.field.train(mode)

    def render_gaussians(self, g: Gaussians, frame: Frame, step: int) -> RenderOutput:
        r = self.cfg.render
        return render(g.means, g.quats, g.scales, g.opacities, g.sh, frame.camera,
                      sh_degree=self.sh_degree(step), background=self.background, backend=self.backend,
                      near=r.near, eps2d=r.eps2d, antialiased=r.antialiased, tile_size=r.tile_size)

    def render_frame(self, frame: Frame, step: int) -> RenderOutput:
        """Deformed (after warm-up) Gaussians at the frame's time, rendered from its camera."""
        return self.render_gaussians(self.deformed(frame.time, step), frame, step)

    # ----------------------------------------------------------------- checkpoints
    def checkpoint_payload(self) -> dict[str, Any]:
        return {
            "step": self.step,
            "params": {k: v.detach().clone() for k, v in self.params.items()},
            "optimizers": {k: o.state_dict() for k, o in self.optimizers.items()},
            "deform": self.deform.state_dict(),
            "deform_opt": self.deform_opt.state_dict(),
            "strategy_state": self.strategy_state,
            "sampler": self.sampler.state_dict(),
            "rng": rng_state(),
            "train_seconds": self.train_seconds,
            "history": self.history,
            "stdr": None if self.stdr is None else self.stdr.state_dict(),
        }

    def save(self) -> None:
        save_checkpoint(self.run_dir / CKPT, self.checkpoint_payload())

    def load(self, path: str | Path, training: bool = True) -> None:
        ck = load_checkpoint(path)
        if (self.stdr is None) != (ck.get("stdr") is None):
            raise ValueError(f"{path}: checkpoint has stdr={'off' if ck.get('stdr') is None else 'on'} but the "
                             f"config has stdr.enabled={self.cfg.stdr.enabled}; use the run's own config.yaml")
        self.params.clear()
        for k, v in ck["params"].items():
            self.params[k] = torch.nn.Parameter(v.to(self.device))
        self.deform.load_state_dict(ck["deform"])
        if self.stdr is not None:
            self.stdr.load_state_dict(ck["stdr"], self.params)
        self.step = int(ck["step"])
        self.train_seconds = float(ck["train_seconds"])
        self.history = list(ck.get("history", []))
        if training:
            self.optimizers = self._make_optimizers()
            for k, o in self.optimizers.items():
                o.load_state_dict(ck["optimizers"][k])
            self.deform_opt.load_state_dict(ck["deform_opt"])
            self.strategy_state = {k: v.to(self.device) if torch.is_tensor(v) else v
                                   for k, v in ck["strategy_state"].items()}
            self.sampler.load_state_dict(ck["sampler"])
            set_rng_state(ck["rng"])

    # ----------------------------------------------------------------- training
    def _tb(self):
        if self.writer is None:
            from torch.utils.tensorboard import SummaryWriter
            self.writer = SummaryWriter(str(self.run_dir / "tb"))
        return self.writer

    def train_step(self) -> dict[str, float]:
        cfg, it, prof = self.cfg, self.step, self.profile
        self._update_lrs(it)
        frame = self.scene.frames("train")[self.sampler.next()]
        self.set_training(True)
        if self.stdr is not None:
            self.stdr.configure_step(self.params, it)
        with prof("deform"):
            # one conditioning per step: the render, SC-GS's node resampling and its ARAP see the same
            cs = self.conditioning(it)
        self.deform.before_step(self.params, it, cs[0])
        with prof("deform"):
            g = self.deformed(frame.time, it, cs)
        with prof("render_fwd"):
            out = self.render_gaussians(g, frame, it)
        with prof("loss"):
            lam = cfg.optim.lambda_dssim
            loss_l1 = l1(out.image, frame.image)
            loss_dssim = 1.0 - ssim(out.image, frame.image)
            loss = (1 - lam) * loss_l1 + lam * loss_dssim
        regs: dict[str, Tensor] = {}
        if self.stdr is not None:
            with prof("stdr_reg"):
                regs = self.stdr.regularizers(self.params, it)
                for v in regs.values():
                    loss = loss + v
        dregs: dict[str, Tensor] = {}
        if it >= cfg.baseline.warmup:  # the baseline's own terms (ARAP, HexPlane smoothness, ...)
            with prof("deform_reg"):
                dregs = self.deform.regularizers(self.params, frame.time, it, cs[0])
                for v in dregs.values():
                    loss = loss + v
        with prof("backward"):
            loss.backward()
        with prof("optimizer"):
            for o in self.optimizers.values():
                o.step()
                o.zero_grad(set_to_none=True)
            if it >= cfg.baseline.warmup:
                self.deform_opt.step()
            self.deform_opt.zero_grad(set_to_none=True)
        with prof("densify"):
            opacity_fn = reset_fn = None
            if self.stdr is not None:
                reset_fn = lambda p, v: self.stdr.reset_opacity(p, v, it)  # noqa: E731
                if self.cfg.stdr.prune_by_mask:
                    opacity_fn = lambda p: self.stdr.effective_opacity(p, it)  # noqa: E731
            info = self.strategy.step_post_backward(
                self.params, self.optimizers, self.strategy_state, it + 1, out.means2d, out.radii,
                frame.camera.width, frame.camera.height, opacity_fn=opacity_fn, reset_fn=reset_fn)
        self.step = it + 1
        return {"loss": loss.item(), "l1": loss_l1.item(), "dssim": loss_dssim.item(),
                "psnr": float(psnr(out.image.detach(), frame.image)), **{f"densify_{k}": v for k, v in info.items()},
                **{f"stdr_{k}": v.item() for k, v in regs.items()},
                **{f"reg_{k}": v.item() for k, v in dregs.items()},
                "_out": out, "_frame": frame}

    def train(self) -> None:
        cfg = self.cfg
        ckpt = self.run_dir / CKPT
        if cfg.train.resume and ckpt.is_file():
            self.load(ckpt)
            print(f"[stdr] resumed from {ckpt} at iteration {self.step}")
        total = cfg.optim.iterations
        tb = self._tb()
        bar = None
        if cfg.train.progress:
            from tqdm import tqdm
            bar = tqdm(total=total, initial=self.step, dynamic_ncols=True, desc="train")
        warmup = cfg.baseline.warmup
        while self.step < total:
            t0 = time.perf_counter()
            logs = self.train_step()
            dt = time.perf_counter() - t0
            self.train_seconds += dt
            it = self.step
            if it % cfg.train.log_every == 0 or it == total:
                self._log_scalars(tb, it, logs, dt)
                if self.stdr is not None:
                    img_due = bool(cfg.train.image_every) and (it % cfg.train.image_every == 0 or it == total)
                    self.stdr.log(tb, self.params, it - 1, images=img_due, x=it)
            if cfg.train.image_every and (it % cfg.train.image_every == 0 or it == total):
                self._log_image(tb, it, logs["_out"].image.detach(), logs["_frame"].image)
            if bar is not None:
                bar.update(1)
                bar.set_postfix(loss=f"{logs['loss']:.4f}", psnr=f"{logs['psnr']:.2f}",
                                N=num_gaussians(self.params))
            if cfg.train.eval_at_warmup_end and it == warmup and warmup < total:
                self.evaluate(cfg.data.eval_split, tag="static_warmup", step=warmup - 1)
            elif cfg.train.eval_every and it % cfg.train.eval_every == 0 and it < total:
                self.evaluate(cfg.data.eval_split, tag="periodic")
            if cfg.train.checkpoint_every and it % cfg.train.checkpoint_every == 0 and it < total:
                self.save()
        if bar is not None:
            bar.close()
        self.save()
        save_ply(self.params, self.run_dir / "point_cloud.ply")
        (self.run_dir / "train_profile.json").write_text(json.dumps(self.profile_summary(), indent=1))

    def profile_summary(self) -> dict[str, Any]:
        tot = sum(self.profile.seconds.values()) or 1.0
        return {"seconds": dict(self.profile.seconds),
                "fraction": {k: v / tot for k, v in self.profile.seconds.items()},
                "iterations_timed": self.step}

    def _log_scalars(self, tb, it, logs, dt) -> None:
        for k in ("loss", "l1", "dssim"):
            tb.add_scalar(f"loss/{k}", logs[k], it)
        tb.add_scalar("train/psnr", logs["psnr"], it)
        tb.add_scalar("gaussians/count", num_gaussians(self.params), it)
        tb.add_scalar("time/seconds_per_iteration", dt, it)
        for k, o in self.optimizers.items():
            tb.add_scalar(f"lr/{k}", o.param_groups[0]["lr"], it)
        for g in self.deform_opt.param_groups:
            tb.add_scalar(f"lr/{g.get('name', 'deform')}", g["lr"], it)
        for k, v in logs.items():
            if k.startswith("densify_"):
                tb.add_scalar(f"densify/{k[8:]}", v, it)
            elif k.startswith("stdr_"):
                tb.add_scalar(f"loss/{k}", v, it)
            elif k.startswith("reg_"):
                tb.add_scalar(f"loss/{k[4:]}", v, it)

    def _log_image(self, tb, it, img: Tensor, gt: Tensor, tag: str = "train/render_gt_error") -> None:
        err = (img - gt).abs().mean(-1, keepdim=True).expand(-1, -1, 3)
        grid = torch.cat([img.clamp(0, 1), gt, (err * 4).clamp(0, 1)], 1)  # [H, 3W, 3]
        tb.add_image(tag, grid, it, dataformats="HWC")

    # ----------------------------------------------------------------- evaluation
    @torch.no_grad()
    def evaluate(self, split: str, tag: str = "final", step: Optional[int] = None,
                 lpips_fn=None, save_dir: Optional[Path] = None, fps_warmup: int = 3) -> dict[str, Any]:
        """Render `split` at the model's state and compute metrics (see stdr.eval.evaluate)."""
        from ..eval.evaluate import evaluate_trainer
        self.set_training(False)
        res = evaluate_trainer(self, split, step=self.step if step is None else step, lpips_fn=lpips_fn,
                               save_dir=save_dir, fps_warmup=fps_warmup)
        rec = {"tag": tag, "iteration": self.step, "split": split,
               **{k: res[k] for k in ("psnr", "ssim", "lpips", "num_gaussians")}}
        self.history.append(rec)
        if self.writer is not None:
            for k in ("psnr", "ssim", "lpips"):
                if res[k] is not None:
                    self.writer.add_scalar(f"eval_{split}/{k}", res[k], self.step)
        return res
