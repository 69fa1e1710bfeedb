"""The single training loop shared by every baseline.

Baselines differ only in the deformation module (stdr.baselines) and their config.
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
from torch import Tensor

from ..data.load import load_scene
from ..device import resolve_device, synchronize
from ..metrics import fused_loss, image_loss, image_loss_compiled
from ..model import build_model, initial_points
from ..render.compiled import camera_values
from ..gaussians import scene_extent
from ..io.ply import save_ply
from ..densify.prune import prune_event
from ..densify.strategy import build_strategy
from .optim import adam_step
from ..io.checkpoint import load_checkpoint
from ..config import check_guard_config
from .guard import Guard, monitor_split, resolve_compiled_check, resolve_sync_free
from .optim import exp_lr
from .state import PAYLOAD_KEYS, CameraSampler, RunLog, RunState
from ..io.checkpoint import CKPT
from ..eval.evaluate import make_lpips, evaluate_state, evaluate_run

__all__ = ["CKPT", "PAYLOAD_KEYS", "CameraSampler", "Profiler", "RunLog", "RunState", "Trainer"]


class Profiler:
    """Accumulated wall time per named section of the training step.

    For benchmarks (`stdr-tool bench-train`): `device` set synchronizes it at every section
    boundary (CUDA runs asynchronously, so unsynchronized sections measure launches), and
    `split_backward` splits the backward at the tensors given to `watch`: each watched group
    names the part of the backward that ends when the gradient reaches the group (the last of
    its tensors); what follows the last group is `after`. The parts go to `backward_parts`, not
    into `seconds` (they are inside "backward"). Both are off in training: no hooks, no syncs."""

    def __init__(self, split_backward: bool = False, device: Optional[torch.device] = None,
                 after: str = "rest"):
        self.seconds: dict[str, float] = defaultdict(float)
        self.backward_parts: dict[str, float] = defaultdict(float)
        self.split_backward, self.device, self.after = split_backward, device, after
        self._marks: dict[str, float] = {}

    def _now(self) -> float:
        if self.device is not None:
            synchronize(self.device)
        return time.perf_counter()

    @contextmanager
    def __call__(self, name: str):
        t0 = self._now()
        yield
        self.seconds[name] += self._now() - t0

    def watch(self, name: str, tensors) -> None:
        """With split_backward: mark when the backward has reached `tensors` (those computed in
        this step's graph; a leaf's hook would outlive the step, so leaves are not watched)."""
        if not self.split_backward:
            return
        for t in tensors:
            if isinstance(t, Tensor) and t.requires_grad and t.grad_fn is not None:
                t.register_hook(lambda grad, n=name: self._mark(n))

    def _mark(self, name: str) -> None:
        self._marks[name] = self._now()

    def backward(self, loss: Tensor) -> None:
        """loss.backward() timed as "backward", split at the watched groups when asked."""
        t0 = self._now()
        loss.backward()
        t1 = self._now()
        self.seconds["backward"] += t1 - t0
        prev = t0
        for name, tm in sorted(self._marks.items(), key=lambda kv: kv[1]):
            self.backward_parts[name] += tm - prev
            prev = tm
        if self._marks:
            self.backward_parts[self.after] += t1 - prev
        self._marks.clear()


class Trainer:
    """Optimization of a `DynamicGaussians` model on a scene: optimizers and learning-rate
    schedules, the densification strategy, the camera sampler and the loop. The model is
    `trainer.state.model`; nothing here is needed to render it."""

    def __init__(self, cfg, run_dir: str | Path, splits=("train",), data_base: Optional[str] = None):
        self.cfg = cfg
        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        if cfg.train.threads > 0:
            torch.set_num_threads(cfg.train.threads)
        self.device = resolve_device(cfg.device)
        torch.manual_seed(cfg.seed)  # also seeds every CUDA device
        np.random.seed(cfg.seed)
        if cfg.train.eval_every > 0 or cfg.train.eval_at_warmup_end:  # evaluations during training need it
            splits = tuple(dict.fromkeys((*splits, cfg.data.eval_split)))
        check_guard_config(cfg.train.guard)
        # the divergence detector (periodic evaluations only) reads its own split, never test's
        self.monitor = (monitor_split(cfg.train.guard, cfg.data.format)
                        if cfg.train.guard.enabled and cfg.train.eval_every > 0 else None)
        if self.monitor is not None:
            splits = tuple(dict.fromkeys((*splits, self.monitor)))
        self.scene = load_scene(cfg.data, splits, base=data_base, seed=cfg.seed).to(self.device)  # images moved once
        for f in self.scene.frames("train"):  # each camera's host copy of its numbers, once (no sync in a step)
            camera_values(f.camera)
        has_train = "train" in self.scene.splits
        train_times = self.scene.train_times() if has_train else None
        pts, colors = initial_points(cfg.model, self.scene.init_points, self.scene.init_colors, cfg.seed,
                                     where=str(self.scene.root))
        background = torch.tensor(self.scene.background, dtype=torch.float32)
        model = build_model(cfg, train_times, background, self.device, pts, colors)
        self.strategy = build_strategy(cfg.densify)  # densify=<name> (stdr.densify.strategy)
        self.cull_train = model.cull_mode() == "train"
        if self.cull_train and self.strategy.count_invisible:
            raise ValueError("render.cull=train renders only the rows that can reach opacity 1/255, so "
                             "densification cannot count the others as seen: set densify.count_invisible=false "
                             "as well, or render.cull=eval to cull outside training only")
        extent = scene_extent(self.scene.camera_centers("train")) if has_train else 1.0
        white = all(float(c) >= 1.0 for c in self.scene.background)
        guard = Guard(peak_gaussians=len(pts), monitor=self.monitor, checks=bool(cfg.train.guard.enabled),
                      sync_free=resolve_sync_free(cfg.train.guard, self.device, self._fused_adam),
                      compiled=resolve_compiled_check(cfg.train.guard, self.device), cfg=cfg.train.guard)
        # the photometric loss as one compiled pass (optim.fused_loss) or its torch twin
        self.fused_loss = fused_loss(cfg.optim.fused_loss, self.device)
        self.image_loss = image_loss_compiled if self.fused_loss else image_loss
        # the run's state (stdr.train.state): what a checkpoint holds, what the guard and the evaluations see
        self.state = RunState(model=model, run_dir=self.run_dir, guard=guard,
                              strategy_state=self.strategy.initialize_state(len(pts), extent, white_background=white,
                                                                            device=self.device),
                              sampler=CameraSampler(len(self.scene.splits.get("train", [])), cfg.seed),
                              train_threads=torch.get_num_threads(),
                              train_loss="compiled" if self.fused_loss else "torch",
                              make_optimizers=self._make_optimizers)
        self.state.optimizers = self._make_optimizers()
        self.net_groups = self._net_groups()
        self.state.net_opt = torch.optim.Adam([{k: v for k, v in g.items() if k == "params" or k == "name"}
                                               for g in self.net_groups], lr=cfg.baseline.lr_init, eps=1e-15,
                                              fused=self._fused_adam)
        self.log = RunLog(self.run_dir)  # TensorBoard (run_dir/tb), opened by the loop or the guard
        self.profile = Profiler()

    @property
    def step(self) -> int:
        """Iterations trained (the model's)."""
        return self.state.model.step

    @step.setter
    def step(self, value: int) -> None:
        self.state.model.step = int(value)

    @property
    def backend(self) -> str:
        return self.state.model.backend

    def replace_gaussians(self, tensors: dict[str, Tensor]) -> None:
        """Continue from other Gaussians (e.g. a cost probe's N copies): the model's parameter dict
        becomes `tensors`; per-Gaussian tensors of the baseline and the plug-ins that are missing
        are created as for new Gaussians; the optimizers and the densification statistics restart."""
        params = self.state.model.params
        params.clear()
        for k, v in tensors.items():
            params[k] = torch.nn.Parameter(v.detach().to(self.device).clone())
        n = params["means"].shape[0]
        for k, v in self.state.model.deform.gaussian_params(n).items():
            if k not in params:
                params[k] = torch.nn.Parameter(v.to(self.device))
        for p in self.state.model.plugins:
            p.init_gaussians(params)
        self.state.optimizers = self._make_optimizers()
        st = self.state.strategy_state
        self.state.strategy_state = self.strategy.initialize_state(n, st["scene_extent"], st["white_background"], self.device)

    # ----------------------------------------------------------------- optimizers
    def _lr(self, key: str, step: int) -> float:
        o = self.cfg.optim
        s = o.spatial_lr_scale
        if key == "means":
            return exp_lr(step, o.means_lr_init * s, o.means_lr_final * s, o.means_lr_max_steps)
        fixed = {"scales": o.scales_lr * s, "quats": o.quats_lr, "opacities": o.opacities_lr,
                 "sh0": o.sh0_lr, "shN": o.shN_lr}
        if key in fixed:
            return fixed[key]
        for owner in [self.state.model.deform, *self.state.model.plugins]:
            lr = owner.gaussian_lr(key)
            if lr is not None:
                return lr
        raise KeyError(f"no learning rate configured for per-Gaussian parameter {key!r}")

    def _make_optimizers(self) -> dict[str, torch.optim.Optimizer]:
        """One Adam per per-Gaussian parameter, including those a plug-in freezes for a phase, so the
        optimizer set does not depend on the step; a parameter without a gradient is not updated."""
        frozen = self.state.model.frozen_keys()
        return {k: torch.optim.Adam([{"params": [p], "lr": self._lr(k, 0), "name": k}], eps=1e-15,
                                    fused=self._fused_adam)
                for k, p in self.state.model.params.items() if k not in frozen}

    @property
    def _fused_adam(self) -> bool:
        """optim.fused_adam: torch's fused Adam (one kernel per parameter instead of ~10
        elementwise passes) where torch has it (CPU and CUDA)."""
        return bool(self.cfg.optim.get("fused_adam", True)) and self.device.type in ("cpu", "cuda")

    def _net_groups(self) -> list[dict]:
        """Network parameter groups: the deformation's (each with an lr multiplier on the
        baseline's schedule), then each plug-in's (the baseline's schedule, or their own)."""
        groups = [dict(g) for g in self.state.model.deform.param_groups()]
        for p in self.state.model.plugins:
            groups += [dict(g) for g in p.param_groups()]
        return groups

    def _net_lr(self, g: dict, step: int) -> float:
        if "lr_init" in g:
            s = max(step - int(g.get("lr_delay", 0)), 0)
            return exp_lr(s, g["lr_init"], g["lr_final"], int(g["lr_max_steps"]))
        b = self.cfg.baseline
        s = max(step - b.warmup, 0) if b.lr_from_warmup else step
        return exp_lr(s, b.lr_init, b.lr_final, b.lr_max_steps) * g.get("lr_mult", 1.0)

    def _update_lrs(self, step: int) -> None:
        scale = self.state.guard.lr_scale  # 1 until a recovery lowers it (train.guard.lr_factor)
        for k, opt in self.state.optimizers.items():
            for g in opt.param_groups:
                g["lr"] = self._lr(k, step) * scale
        for spec, g in zip(self.net_groups, self.state.net_opt.param_groups):
            g["lr"] = self._net_lr(spec, step) * scale

    # ----------------------------------------------------------------- checkpoints
    def checkpoint_payload(self) -> dict[str, Any]:
        """The checkpoint's dict (RunState.payload)."""
        return self.state.payload()

    def save(self) -> None:
        """checkpoints/last.pt (atomic, checksummed; the one it replaces is kept as last.previous.pt)."""
        self.state.save()

    def load(self, path: str | Path) -> None:
        """Resume: the model, the optimizers, the strategy, the sampler, every RNG and the guard."""
        ck = load_checkpoint(path, require=PAYLOAD_KEYS)
        self.state.restore(ck, str(path))
        self.state.guard.load_state_dict(ck.get("guard", {}))
        self.state.guard.clear()
        self.state.guard.monitor = self.monitor  # this run's detector split, whatever the checkpoint's run had

    # ----------------------------------------------------------------- training
    def train_step(self) -> dict[str, Any]:
        """One optimization step. Returns 0-d tensors (loss, l1, dssim, psnr), `densify` (the
        strategy's counts), `losses` (each regularizer's weighted value: plug-in terms as
        `<plug-in>_<term>`, the baseline's by name) and the step's render `out` and `frame`."""
        cfg, it, prof, model = self.cfg, self.step, self.profile, self.state.model
        pruned = None
        if it in model.schedule.prune_steps and all(e["step"] != it for e in self.state.prune_log):
            # once `it` steps are done, before the next one: a checkpoint at `it` is from before
            # the event, so a run resumed from it (or branched from it with other prune.* keys)
            # prunes exactly as an uninterrupted one
            with prof("prune"):
                pruned = prune_event(model, self.scene.frames("train"), self.state.optimizers, self.state.strategy_state,
                                     cfg.prune, it)
            self.state.prune_log.append(pruned)
            print(f"[stdr] step {it}: contribution pruning removed {pruned['before'] - pruned['after']} of "
                  f"{pruned['before']} Gaussians (seen per frame {pruned['seen_before']:.1%} -> "
                  f"{pruned['seen_after']:.1%}; score pass over {pruned['frames']} frames "
                  f"{pruned['score_seconds']:.2f} s)")
        params = model.params
        self._update_lrs(it)
        frame = self.scene.frames("train")[self.state.sampler.next()]
        model.train(True)
        for p in model.plugins:
            p.configure_step(params, it)
        frozen = model.frozen_keys()
        for k in [k for k in self.state.optimizers if k not in params or k in frozen]:
            del self.state.optimizers[k]  # a plug-in holds it fixed from now on (e.g. an 8-bit mask): no more updates
        with prof("deform"):
            # one conditioning per step: the render, SC-GS's node resampling and its ARAP see the same
            cs = model.conditioning(it)
        model.deform.before_step(params, it, cs[0])
        with prof("deform"):
            g, rows = model.deformed_rows(frame.time, it, cs, cull=self.cull_train)
        with prof("render_fwd"):
            out = model.render_gaussians(g, frame.camera, it)
        pj = out.projection  # benchmarks split the backward here (no-ops in training); the
        # projection's opacities may be the deformed ones themselves, so only means2d and conics
        # (made by the projection alone) mark the end of the rasterizer's backward
        prof.watch("loss+rasterizer", (pj.means2d, pj.conics))
        prof.watch("projection+sh", (g.means, g.quats, g.scales, g.opacities, g.sh))
        with prof("loss"):  # (loss, l1, dssim, psnr); D-SSIM without a gradient where lambda_dssim = 0
            loss, loss_l1, loss_dssim, step_psnr = self.image_loss(out.image, frame.image, cfg.optim.lambda_dssim)
        terms: dict[str, Tensor] = {}
        for p in model.plugins:
            with prof(f"{p.name}_reg"):
                for k, v in p.regularizers(params, it).items():
                    terms[f"{p.name}_{k}"] = v
                    loss = loss + v
        if it >= model.warmup:  # the baseline's own terms (ARAP, HexPlane smoothness, ...)
            with prof("deform_reg"):
                for k, v in model.deform.regularizers(params, frame.time, it, cs[0]).items():
                    terms[k] = v
                    loss = loss + v
        prof.backward(loss)
        found_inf = None  # the sync-free guard's flag: fused Adam applies no update while it is 1
        if self.state.guard.sync_free:
            with prof("guard"):
                found_inf = self.state.guard.flag_step(self.state, loss, it + 1)
        elif cfg.train.guard.enabled:
            with prof("guard"):
                bad = self.state.guard.check_step(self.state, loss, it + 1)
            if bad is not None:  # nothing is applied: the caller restores the last good state
                self.zero_grads()
                self.step = it + 1
                return {"rejected": bad, "loss": float(loss.detach())}
        with prof("optimizer"):
            # every optimizer's step() at once (stdr.train.optim: the same fused kernels, fewer
            # launches); found_inf is read by torch's fused Adam as GradScaler sets it
            adam_step([*self.state.optimizers.values(), *([self.state.net_opt] if it >= model.warmup else [])], found_inf)
            self.zero_grads()
        with prof("densify"):
            info = self.strategy.step_post_backward(
                params, self.state.optimizers, self.state.strategy_state, it + 1, out.means2d, out.radii,
                frame.camera.width, frame.camera.height, opacity_fn=model.prune_opacity_fn(it),
                reset_fn=model.reset_opacity_fn(it), rows=rows, opacities=out.projection.opacities)
        if pruned is not None:
            info = {**info, "pruned_by_score": pruned["before"] - pruned["after"]}
        self.step = it + 1
        # scalars stay 0-d tensors (no host sync in an ordinary step): read them at log steps
        return {"loss": loss.detach(), "l1": loss_l1.detach(), "dssim": loss_dssim.detach(), "active": g.means.shape[0],
                "psnr": step_psnr.detach(), "densify": info,
                "losses": {k: v.detach() for k, v in terms.items()}, "out": out, "frame": frame}

    def network_params(self) -> list[tuple[str, Tensor]]:
        """(group name, parameter) of every network the run trains (RunState.network_params)."""
        return self.state.network_params()

    def zero_grads(self) -> None:
        self.state.zero_grads()

    @property
    def checkpoint_path(self) -> Path:
        return self.state.checkpoint_path

    def train(self) -> None:
        cfg = self.cfg
        ckpt = self.checkpoint_path
        if cfg.train.resume and ckpt.is_file():
            self.load(ckpt)
            print(f"[stdr] resumed from {ckpt} at iteration {self.step}")
        guard = cfg.train.guard
        if guard.enabled:
            self.state.guard.take_snapshot(self.state, self.log)
        if self.device.type == "cuda":
            torch.cuda.reset_peak_memory_stats(self.device)  # guard.peak_memory_mb: this run's peak
        total = cfg.optim.iterations
        tb = self.log.open()
        bar = None
        if cfg.train.progress:
            from tqdm import tqdm
            bar = tqdm(total=total, initial=self.step, dynamic_ncols=True, desc="train")
        warmup = cfg.baseline.warmup
        end = total if cfg.train.get("stop_at") is None else min(total, int(cfg.train.stop_at))
        if end < 1:
            raise ValueError(f"train.stop_at={cfg.train.stop_at}: must be a step >= 1 (null: train to optim.iterations)")
        while self.step < end:
            t0, c0 = time.perf_counter(), time.process_time()
            logs = self.train_step()
            dt = time.perf_counter() - t0
            self.state.train_seconds += dt
            if self.state.train_cpu_seconds is not None:
                self.state.train_cpu_seconds += time.process_time() - c0
            if "rejected" in logs:
                self.state.guard.recover(self.state, self.log, logs["rejected"])
                if bar is not None:
                    bar.n = self.step
                    bar.refresh()
                continue
            it = self.step
            if self.state.guard.sync_free and self._waits_for_the_device(it, end):
                hit = self.state.guard.poll()  # the sync-free check, read where the loop waits anyway
                if hit is not None:
                    self.state.guard.recover(self.state, self.log, hit[1], step=hit[0])
                    if bar is not None:
                        bar.n = self.step
                        bar.refresh()
                    continue
            self.state.guard.peak_gaussians = max(self.state.guard.peak_gaussians, self.state.model.num_gaussians)
            if it % cfg.train.log_every == 0 or it == total:
                self._log_scalars(tb, it, logs, dt)
                img_due = bool(cfg.train.image_every) and (it % cfg.train.image_every == 0 or it == total)
                for p in self.state.model.plugins:
                    p.log(tb, self.state.model.params, it - 1, images=img_due, x=it)
            if cfg.train.image_every and (it % cfg.train.image_every == 0 or it == total):
                self._log_image(tb, it, logs["out"].image.detach(), logs["frame"].image)
            if bar is not None:
                bar.update(1)
                if it % cfg.train.log_every == 0 or it == total:  # reading the scalars waits for the device
                    bar.set_postfix(loss=f"{float(logs['loss']):.4f}", psnr=f"{float(logs['psnr']):.2f}",
                                    N=self.state.model.num_gaussians)
            res = None
            if cfg.train.eval_at_warmup_end and it == warmup and warmup < total:
                res = self.evaluate(cfg.data.eval_split, tag="static_warmup", step=warmup - 1,
                                    frames=self.curve_frames(cfg.data.eval_split), lpips_fn=self._curve_lpips())
            elif cfg.train.eval_every and it % cfg.train.eval_every == 0 and it < total:
                res = self.evaluate(cfg.data.eval_split, tag="periodic", frames=self.curve_frames(cfg.data.eval_split),
                                    lpips_fn=self._curve_lpips())
            if res is not None and self.monitor is not None:
                reset = self.strategy.last_reset(it, bool(self.state.strategy_state.get("white_background")))
                self.state.guard.after_evaluation(self.state, self.log, self._monitor_psnr(res),
                                            after_reset=reset is not None and it - reset < guard.after_reset)
                if self.step != it:  # recovered: go on from the restored step
                    if bar is not None:
                        bar.n = self.step
                        bar.refresh()
                    continue
            if cfg.train.checkpoint_every and it % cfg.train.checkpoint_every == 0 and it < total:
                self.save()
            if guard.enabled and it % guard.snapshot_every == 0 and it < total:
                self.state.guard.take_snapshot(self.state, self.log)
        if bar is not None:
            bar.close()
        if self.step < total:
            print(f"[stdr] stopped at iteration {self.step} of {total} (train.stop_at); the same command without "
                  "train.stop_at resumes from the checkpoint")
        self.state.guard.note_memory(self.device)
        self.save()
        save_ply(self.state.model.params, self.run_dir / "point_cloud.ply")
        (self.run_dir / "train_profile.json").write_text(json.dumps(self.profile_summary(), indent=1))

    def _waits_for_the_device(self, it: int, end: int) -> bool:
        """Whether the loop reads the device after step `it` anyway (logging, an evaluation, a
        checkpoint, a snapshot, the end): where the sync-free guard's flag is read, so that no
        state after a faulty step is logged, evaluated, saved or kept as good."""
        t, g = self.cfg.train, self.cfg.train.guard
        return (it % t.log_every == 0 or it >= end or it % g.snapshot_every == 0
                or bool(t.eval_every and it % t.eval_every == 0) or bool(t.checkpoint_every and it % t.checkpoint_every == 0)
                or (t.eval_at_warmup_end and it == self.cfg.baseline.warmup))

    def profile_summary(self) -> dict[str, Any]:
        tot = sum(self.profile.seconds.values()) or 1.0
        out = {"seconds": dict(self.profile.seconds),
               "fraction": {k: v / tot for k, v in self.profile.seconds.items()},
               "iterations_timed": self.step}
        if self.profile.backward_parts:
            out["backward_parts"] = dict(self.profile.backward_parts)
        return out

    def _log_scalars(self, tb, it, logs, dt) -> None:
        for k in ("loss", "l1", "dssim"):
            tb.add_scalar(f"loss/{k}", logs[k], it)
        tb.add_scalar("train/psnr", logs["psnr"], it)
        tb.add_scalar("gaussians/count", self.state.model.num_gaussians, it)
        tb.add_scalar("gaussians/rendered", logs["active"], it)  # after temporal culling (render.cull=train)
        tb.add_scalar("time/seconds_per_iteration", dt, it)
        mb = self.state.guard.note_memory(self.device)
        if mb is not None:
            tb.add_scalar("memory/mb", mb, it)  # docs/stability.md: the process's memory (CUDA: peak allocated)
        for k, o in self.state.optimizers.items():
            tb.add_scalar(f"lr/{k}", o.param_groups[0]["lr"], it)
        for g in self.state.net_opt.param_groups:
            tb.add_scalar(f"lr/{g.get('name', 'deform')}", g["lr"], it)
        for k, v in logs["densify"].items():
            tb.add_scalar(f"densify/{k}", v, it)
        for k, v in logs["losses"].items():
            tb.add_scalar(f"loss/{k}", v, it)

    def _log_image(self, tb, it, img: Tensor, gt: Tensor, tag: str = "train/render_gt_error") -> None:
        err = (img - gt).abs().mean(-1, keepdim=True).expand(-1, -1, 3)
        grid = torch.cat([img.clamp(0, 1), gt, (err * 4).clamp(0, 1)], 1)  # [H, 3W, 3]
        tb.add_image(tag, grid, it, dataformats="HWC")

    # ----------------------------------------------------------------- evaluation
    def curve_frames(self, split: str, n: Optional[int] = None) -> Optional[list[int]]:
        """Indices of the frames a periodic (learning-curve) evaluation renders: all (None) with
        train.eval_frames=0, else a fixed subset of that many (or of `n`), drawn once from a
        generator seeded with the run's seed (the training RNG is not touched)."""
        n = int(self.cfg.train.eval_frames if n is None else n)
        total = len(self.scene.frames(split))
        if n <= 0 or n >= total:
            return None
        g = torch.Generator().manual_seed(int(self.cfg.seed))
        return sorted(torch.randperm(total, generator=g)[:n].tolist())

    def _monitor_psnr(self, res: dict[str, Any]) -> float:
        """The divergence detector's PSNR at a periodic evaluation `res` (of data.eval_split):
        its own when data.eval_split is the monitor split, else an evaluation of the monitor
        split's fixed subset of train.guard.monitor_frames frames (history tag 'guard')."""
        if self.monitor == self.cfg.data.eval_split:
            return float(res["psnr"])
        frames = self.curve_frames(self.monitor, n=self.cfg.train.guard.monitor_frames)
        return float(self.evaluate(self.monitor, tag="guard", frames=frames)["psnr"])

    def _curve_lpips(self):
        """The LPIPS network for periodic evaluations (train.eval_lpips), built once."""
        if not self.cfg.train.eval_lpips:
            return None
        if getattr(self, "_lpips", None) is None:
            lp = make_lpips(self.cfg.eval)
            if lp is None:
                raise ValueError("train.eval_lpips=true but no LPIPS weights were found (eval.lpips, "
                                 "eval.lpips_weights or STDR_LPIPS_WEIGHTS)")
            self._lpips = lp.to(self.device)
        return self._lpips

    @torch.no_grad()
    def evaluate(self, split: str, tag: str = "final", step: Optional[int] = None,
                 lpips_fn=None, save_dir: Optional[Path] = None, fps_warmup: int = 3,
                 frames: Optional[list[int]] = None, fps_repeats: int = 1, seen: bool = False) -> dict[str, Any]:
        """Render `split` (or the frames at indices `frames` of it) at the model's state and
        compute metrics (stdr.eval.evaluate.evaluate_state): a point of the run's learning curve
        (`history`), with the training seconds so far (evaluation excluded)."""
        fr = self.scene.frames(split)
        if frames is not None:
            fr = [fr[i] for i in frames]
        return evaluate_state(self.state, fr, split, tag=tag, step=step, log=self.log, lpips_fn=lpips_fn,
                              save_dir=save_dir, fps_warmup=fps_warmup, fps_repeats=fps_repeats, seen=seen)

    def evaluate_final(self, split: str, eval_cfg=None) -> dict[str, Any]:
        """The run's final evaluation of `split` into metrics.json (stdr.eval.evaluate.evaluate_run)."""
        return evaluate_run(self.state, self.scene, split, self.cfg.eval if eval_cfg is None else eval_cfg,
                            max_gaussians=getattr(self.strategy, "max_gaussians", 0), log=self.log)
