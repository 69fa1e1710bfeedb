"""The evaluations a training run makes of itself: the learning curve's points (the static
warm-up's end, every train.eval_every steps, on a fixed subset of frames), the divergence
detector's reading and the final evaluation into metrics.json. A part of `Trainer`
(stdr.train.trainer), which it reads through self.cfg, self.scene, self.state and self.log."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Optional

import torch

from ..eval.evaluate import evaluate_run, evaluate_state, make_lpips


class Evaluations:
    """Trainer's evaluations of its own state (a mixin of stdr.train.trainer.Trainer)."""

    def _evaluation_due(self, it: int, total: int) -> Optional[dict[str, Any]]:
        """The evaluation after step `it`, if one is due: at the static warm-up's end
        (train.eval_at_warmup_end) or every train.eval_every steps; else None."""
        cfg = self.cfg
        split, warmup = cfg.data.eval_split, cfg.baseline.warmup
        if cfg.train.eval_at_warmup_end and it == warmup and warmup < total:
            return self.evaluate(split, tag="static_warmup", step=warmup - 1, frames=self.curve_frames(split),
                                 lpips_fn=self._curve_lpips())
        if cfg.train.eval_every and it % cfg.train.eval_every == 0 and it < total:
            return self.evaluate(split, tag="periodic", frames=self.curve_frames(split), lpips_fn=self._curve_lpips())
        return None

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
