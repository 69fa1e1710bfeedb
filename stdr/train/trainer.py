"""The single training loop shared by every baseline.

Baselines differ only in the deformation module (stdr.baselines) and their config.
"""
from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any, Optional

import torch
from torch import Tensor

from ..plugins import Reporting
from ..plugins.interface import roles
from ..io.ply import save_ply
from ..densify.prune import prune_event
from .optim import adam_step, make_optimizers, update_lrs
from ..io.checkpoint import checkpoint_identity, load_checkpoint, source_line
from ..io.files import write_atomic, writing
from .evaluations import Evaluations
from .resume import preemption
from .timing import Profiler
from .build import build_run
from .state import PAYLOAD_KEYS, RunLog

#: the clock of train.checkpoint_minutes (monotonic: a change of the system's time moves no checkpoint)
_clock = time.monotonic


def _rewind(bar, step: int) -> None:
    """The progress bar back to `step` after a recovery restored an earlier state."""
    if bar is not None:
        bar.n = step
        bar.refresh()


class Trainer(Evaluations):
    """Optimization of a `DynamicGaussians` model on a scene: optimizers and learning-rate
    schedules, the densification strategy, the camera sampler and the loop. The model is
    `trainer.state.model`; nothing here is needed to render it."""

    def __init__(self, cfg, run_dir: str | Path, splits=("train",), data_base: Optional[str] = None):
        self.cfg = cfg
        self.run_dir = Path(run_dir)
        self._last_save = _clock()  # train.checkpoint_minutes counts from here
        parts = build_run(cfg, self.run_dir, splits, data_base)
        self.device, self.fused_adam, self.monitor, self.scene = parts.device, parts.fused_adam, parts.monitor, parts.scene
        self.strategy, self.cull_train, self.state, self.net_groups = parts.strategy, parts.cull_train, parts.state, parts.net_groups
        self.fused_loss, self.image_loss = parts.fused_loss, parts.image_loss
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
        becomes `tensors`; the baseline's init_gaussians creates its per-Gaussian tensors that are
        missing and sets up what it derives from the Gaussians (4DGS's bounds), the plug-ins'
        init_gaussians run as for new Gaussians; the optimizers and the densification statistics
        restart."""
        params = self.state.model.params
        params.clear()
        for k, v in tensors.items():
            params[k] = torch.nn.Parameter(v.detach().to(self.device).clone())
        n = params["means"].shape[0]
        self.state.model.deform.init_gaussians(params)
        for p in self.state.model.plugins:
            p.init_gaussians(params)
        self.state.optimizers = make_optimizers(self.cfg, self.state.model, self.fused_adam)
        st = self.state.strategy_state
        self.state.strategy_state = self.strategy.initialize_state(n, st["scene_extent"], st["white_background"], self.device)

    # ----------------------------------------------------------------- checkpoints
    def save(self) -> None:
        """checkpoints/last.pt (atomic, checksummed; the one it replaces is kept as last.previous.pt)."""
        self.state.save()
        self._last_save = _clock()

    def load(self, path: str | Path) -> None:
        """Resume: the model, the optimizers, the strategy, the sampler, every RNG and the guard."""
        ck = load_checkpoint(path, require=PAYLOAD_KEYS)
        self.state.restore(ck, str(path))
        self.state.checkpoint_id = checkpoint_identity(path)
        self.state.guard.load_state_dict(ck.get("guard", {}))
        self.state.guard.clear()
        self.state.guard.monitor = self.monitor  # this run's detector split, whatever the checkpoint's run had

    # ----------------------------------------------------------------- training
    def train_step(self) -> dict[str, Any]:
        """One optimization step. Returns 0-d tensors (loss, l1, dssim, psnr), `densify` (the
        strategy's counts), `losses` (each regularizer's weighted value: plug-in terms as
        `<plug-in>_<term>`, the baseline's by name) and the step's render `out` and `frame`."""
        cfg, it, prof, model = self.cfg, self.step, self.profile, self.state.model
        pruned = self._prune_if_due(it)
        params = model.params
        update_lrs(self.cfg, self.state, self.net_groups, it)
        frame = self.scene.frames("train")[self.state.sampler.next()]
        model.train(True)
        ctx = model.context(it, t=frame.time, camera=frame.camera)  # the hooks' one context, filled as the step goes
        for p in model.plugins:
            p.before_step(ctx)
        frozen = model.frozen_keys()
        for k in [k for k in self.state.optimizers if k not in params or k in frozen]:
            del self.state.optimizers[k]  # a plug-in holds it fixed from now on (e.g. an 8-bit mask): no more updates
        with prof("deform"):
            # one conditioning per step: the render, SC-GS's node resampling and its ARAP see the same
            cs = model.conditioning(it)
        ctx.cond = cs[0]
        model.deform.before_step(ctx)
        with prof("deform"):
            g, rows = model.deformed_rows(frame.time, it, cs, cull=self.cull_train)
        with prof("render_fwd"):
            out = model.render_gaussians(g, frame.camera, it)
        ctx.deformed, ctx.rows, ctx.render = g, rows, out
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
                for k, v in p.regularizers(ctx).items():
                    terms[f"{p.name}_{k}"] = v
                    loss = loss + v
        if it >= model.warmup:  # the baseline's own terms (ARAP, HexPlane smoothness, ...)
            with prof("deform_reg"):
                for k, v in model.deform.regularizers(ctx).items():
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
                self.state.zero_grads()
                self.step = it + 1
                return {"rejected": bad, "loss": float(loss.detach())}
        with prof("optimizer"):
            # every optimizer's step() at once (stdr.train.optim: the same fused kernels, fewer
            # launches); found_inf is read by torch's fused Adam as GradScaler sets it
            adam_step([*self.state.optimizers.values(), *([self.state.net_opt] if it >= model.warmup else [])], found_inf)
            self.state.zero_grads()
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

    def _prune_if_due(self, it: int) -> Optional[dict[str, Any]]:
        """The contribution-pruning event of step `it` (prune.at), once: after `it` steps are done,
        before the next one, so a checkpoint at `it` is from before the event and a run resumed from
        it (or branched from it with other prune.* keys) prunes exactly as an uninterrupted one."""
        model = self.state.model
        if it not in model.schedule.prune_steps or any(e["step"] == it for e in self.state.prune_log):
            return None
        with self.profile("prune"):
            pruned = prune_event(model, self.scene.frames("train"), self.state.optimizers, self.state.strategy_state,
                                 self.cfg.prune, it)
        self.state.prune_log.append(pruned)
        print(f"[stdr] step {it}: contribution pruning removed {pruned['before'] - pruned['after']} of "
              f"{pruned['before']} Gaussians (seen per frame {pruned['seen_before']:.1%} -> "
              f"{pruned['seen_after']:.1%}; score pass over {pruned['frames']} frames {pruned['score_seconds']:.2f} s)")
        return pruned

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
        end = total if cfg.train.get("stop_at") is None else min(total, int(cfg.train.stop_at))
        if end < 1:
            raise ValueError(f"train.stop_at={cfg.train.stop_at}: must be a step >= 1 (null: train to optim.iterations)")
        deadline = cfg.train.get("deadline")
        with preemption() as pre:  # a cluster's warning signal: checkpoint this step, then requeue
            self._loop(end, total, deadline, tb, bar, pre)
            if bar is not None:
                bar.close()
            if self.step < total:
                if pre is not None and pre.stopped_by is not None and not pre.warned:
                    print(f"[stdr] stopped at iteration {self.step} of {total} ({pre.stopped_by.name}); checkpoint "
                          f"{self.checkpoint_path}: the same command resumes from it", flush=True)
                elif pre is not None and pre.requested:
                    print(f"[stdr] stopped at iteration {self.step} of {total} (a cluster's warning signal); the "
                          "requeued job resumes from the checkpoint")
                else:
                    why = "train.stop_at" if self.step >= end else "train.deadline"
                    print(f"[stdr] stopped at iteration {self.step} of {total} ({why}); the same command without "
                          f"{why} resumes from the checkpoint")
            self.state.guard.note_memory(self.device)
            self.save()
            src = source_line(self.state.checkpoint_id)  # the checkpoint just written: the PLY's source
            save_ply(self.state.model.params, self.run_dir / "point_cloud.ply", comments=[src] if src else [])
            self.log.flush()  # TensorBoard's events on the disk: a fault there is named now, not lost
            write_atomic(self.run_dir / "train_profile.json", json.dumps(self.profile_summary(), indent=1),
                         site="profile")
            if pre is not None and pre.requested:
                pre.hand_over()  # exit 130/143, or submitit requeues the job; the checkpoint above is where it resumes

    def _loop(self, end: int, total: int, deadline, tb, bar, pre) -> None:
        """The steps up to `end` (train.stop_at or optim.iterations), a deadline or a warning signal."""
        cfg, guard = self.cfg, self.cfg.train.guard
        while self.step < end and (deadline is None or time.time() < deadline) and not (pre and pre.requested):
            t0, c0 = time.perf_counter(), time.process_time()
            logs = self.train_step()
            dt = time.perf_counter() - t0
            self.state.train_seconds += dt
            if self.state.train_cpu_seconds is not None:
                self.state.train_cpu_seconds += time.process_time() - c0
            if "rejected" in logs:
                self.state.guard.recover(self.state, self.log, logs["rejected"])
                _rewind(bar, self.step)
                continue
            it = self.step
            if self.state.guard.sync_free and (self._waits_for_the_device(it, end) or (pre is not None and pre.requested)):
                hit = self.state.guard.poll()  # the sync-free check, read where the loop waits anyway
                if hit is not None:
                    self.state.guard.recover(self.state, self.log, hit[1], step=hit[0])
                    _rewind(bar, self.step)
                    continue
            self.state.guard.peak_gaussians = max(self.state.guard.peak_gaussians, self.state.model.num_gaussians)
            self._log_step(tb, bar, it, total, logs, dt)
            res = self._evaluation_due(it, total)
            if res is not None and self.monitor is not None:
                reset = self.strategy.last_reset(it, bool(self.state.strategy_state.get("white_background")))
                self.state.guard.after_evaluation(self.state, self.log, self._monitor_psnr(res),
                                            after_reset=reset is not None and it - reset < guard.after_reset)
                if self.step != it:  # recovered: go on from the restored step
                    _rewind(bar, self.step)
                    continue
            if it < total and ((cfg.train.checkpoint_every and it % cfg.train.checkpoint_every == 0)
                               or self._checkpoint_due_by_time()):
                self.save()
            if guard.enabled and it % guard.snapshot_every == 0 and it < total:
                self.state.guard.take_snapshot(self.state, self.log)

    def _checkpoint_due_by_time(self) -> bool:
        """train.checkpoint_minutes of wall time since the last checkpoint this process wrote (or
        its start): bounds what a hard kill (SIGKILL, a power cut) can lose."""
        minutes = self.cfg.train.get("checkpoint_minutes")
        return bool(minutes) and _clock() - self._last_save >= 60.0 * float(minutes)

    def _log_step(self, tb, bar, it: int, total: int, logs: dict[str, Any], dt: float) -> None:
        """TensorBoard scalars and the plug-ins' entries every train.log_every steps, the render
        beside its ground truth every train.image_every, the progress bar every step."""
        t = self.cfg.train
        due = it % t.log_every == 0 or it == total
        img_due = bool(t.image_every) and (it % t.image_every == 0 or it == total)
        if due:
            self.log.step_scalars(it, logs, dt, self.state, self.device)
            with writing(self.log.dir, "tensorboard"):
                model = self.state.model
                for p in roles(model.plugins, Reporting):
                    p.log(tb, model.context(it - 1), images=img_due, x=it)
        if img_due:
            self.log.render_and_truth(it, logs["out"].image.detach(), logs["frame"].image)
        if bar is not None:
            bar.update(1)
            if due:  # reading the scalars waits for the device
                bar.set_postfix(loss=f"{float(logs['loss']):.4f}", psnr=f"{float(logs['psnr']):.2f}",
                                N=self.state.model.num_gaussians)

    def _waits_for_the_device(self, it: int, end: int) -> bool:
        """Whether the loop reads the device after step `it` anyway (logging, an evaluation, a
        checkpoint, a snapshot, the end): where the sync-free guard's flag is read, so that no
        state after a faulty step is logged, evaluated, saved or kept as good."""
        t, g = self.cfg.train, self.cfg.train.guard
        return (it % t.log_every == 0 or it >= end or it % g.snapshot_every == 0
                or bool(t.eval_every and it % t.eval_every == 0) or bool(t.checkpoint_every and it % t.checkpoint_every == 0)
                or (t.eval_at_warmup_end and it == self.cfg.baseline.warmup))

    def profile_summary(self) -> dict[str, Any]:
        return self.profile.summary(self.step)
