"""The conformance kit: what the suite checks of the built-in baselines and plug-ins, for any
registered one, built-in or from an outside package.

    stdr-tool check-baseline NAME [--plugin P] [--quick]
    stdr-tool check-plugin NAME [--baseline deform] [--quick]

Each check trains the embedded procedural scene at 64 px (stdr.testing.tiny_config) with a
60-step schedule that crosses every phase boundary (the static warm-up, densification and an
opacity reset, STDR's three phases, SC-GS's stages), on the CPU:

* `identity`: the plug-ins' conditioning starts at identity: just after the warm-up, the
  deformation with the conditioning the plug-ins give equals the one with that conditioning
  zeroed (a baseline that declares the capability 'conditioning' starts its cond columns at zero weight);
* `device`: the run trains with torch's default device set to "meta" and ends bit-identical to
  the same run without it: no tensor is created on a hard-coded device;
* `resume`: stopped at step 30 and resumed, the run ends bit-identical to an uninterrupted one;
* `culling`: evaluation's temporal culling (render.cull) renders the image of the full render,
  with most Gaussians below 1/255 (not applicable to a module with opacity deltas);
* `compact`: the compact model file (model.stdrc) reads back through load_model and renders every
  test frame within 0.05 dB PSNR of the trained model;
* `learns`: training raises test PSNR by at least 1 dB over the untrained model, at budget=demo
  (the README's first command; `--quick`: the 60-step run).

It prints one line per check and exits 1 when one fails.
"""
from __future__ import annotations

import argparse
import io
import sys
import tempfile
import time
from contextlib import contextmanager, redirect_stdout
from pathlib import Path

import torch

from ..baselines import BASELINES
from ..baselines.base import deform_gaussians
from ..baselines.registry import capabilities
from ..compact.pack import write_compact
from ..eval.evaluate import evaluate_model
from ..model import load_model
from ..plugins import PLUGINS
from ..store import experiment_names
from ..testing import tiny_config
from ..train.trainer import Trainer
from .identity_check import SCHEDULE, STDR_PHASES

STEPS = 60
STOP = 30
#: an opacity logit well below 1/255 (the rasterizer's cut-off): rows the culling check switches off
FAINT = -12.0


class CheckFailed(AssertionError):
    pass


def _require(ok: bool, why: str) -> None:
    if not ok:
        raise CheckFailed(why)


@contextmanager
def default_device(device: str):
    """torch's default device set to `device` (e.g. "meta") while open, except inside torch's
    optimizer steps (torch's own code)."""
    from torch.optim.optimizer import register_optimizer_step_post_hook, register_optimizer_step_pre_hook
    torch.set_default_device(device)
    hooks = [register_optimizer_step_pre_hook(lambda *a: torch.set_default_device(None)),
             register_optimizer_step_post_hook(lambda *a: torch.set_default_device(device))]
    try:
        yield
    finally:
        for h in hooks:
            h.remove()
        torch.set_default_device(None)


class Kit:
    """The runs the checks share, made once each in `work`."""

    def __init__(self, experiment: str, plugin: str | None, work: Path, quick: bool):
        self.experiment, self.plugin, self.work, self.quick = experiment, plugin, Path(work), quick
        stdr_keys = STDR_PHASES if plugin == "stdr" else []
        self.overrides = [o for o in SCHEDULE if not o.startswith("optim.iterations=")] + stdr_keys + [
            f"experiment={self.experiment}", f"optim.iterations={STEPS}"]
        self._full = None

    def config(self, *extra):
        return tiny_config(self.work, [*self.overrides, *extra])

    def trainer(self, folder: str, *extra, splits=("train", "test")) -> Trainer:
        return Trainer(self.config(*extra), self.work / folder, splits=splits)

    def full(self) -> Trainer:
        """The uninterrupted 60-step run."""
        if self._full is None:
            self._full = self.trainer("full")
            self._full.train()
        return self._full

    def same(self, a: Trainer, b: Trainer, what: str) -> None:
        _require(a.step == b.step == STEPS, f"{what}: ended at steps {a.step} and {b.step}, not {STEPS}")
        pa, pb = a.state.model.params, b.state.model.params
        _require(set(pa) == set(pb), f"{what}: per-Gaussian keys differ ({sorted(set(pa) ^ set(pb))})")
        for k in pa:
            _require(pb[k].device == pa[k].device and torch.equal(pa[k], pb[k]), f"{what}: params[{k!r}] differ")
        sa, sb = a.state.model.deform.state_dict(), b.state.model.deform.state_dict()
        for k in sa:
            _require(torch.equal(sa[k], sb[k]), f"{what}: the deformation's {k!r} differs")

    # ------------------------------------------------------------------ the checks
    def check_identity(self) -> str:
        tr = self.trainer("identity", splits=("train",))
        model = tr.state.model.eval()  # no dropout in the plug-ins' networks
        step = STEPS - 1  # every phase of the plug-ins on, the untrained model
        cond, scale = model.conditioning(step)
        if cond is None:
            return "no plug-in feeds conditioning: nothing to check"
        _require(cond.shape == (model.num_gaussians, model.deform.cond_dim),
                 f"the conditioning is {tuple(cond.shape)}, the module was built for [N, {model.deform.cond_dim}]")
        frame = tr.scene.frames("train")[len(tr.scene.frames("train")) // 2]
        with torch.no_grad():
            model.deform.before_step(model.context(step, t=frame.time, camera=frame.camera, cond=cond))  # what the loop does first (SP-GS: its superpoints)
            a = deform_gaussians(model.deform, model.params, frame.time, cond, scale)
            b = deform_gaussians(model.deform, model.params, frame.time, torch.zeros_like(cond), scale)
        for field in a._fields:
            diff = (getattr(a, field) - getattr(b, field)).abs().max().item()
            _require(diff <= 1e-6, f"{field} moves by {diff:.3g} with the conditioning at step {step}: start the "
                                   "module's cond columns at zero weight")
        return f"cond [N, {cond.shape[1]}] at step {step} changes nothing"

    def check_device(self) -> str:
        run = self.trainer("meta")
        with default_device("meta"):
            run.train()
        self.same(self.full(), run, "with the default device set to 'meta'")
        return "the run with torch's default device 'meta' is bit-identical"

    def check_resume(self) -> str:
        self.trainer("resumed", f"train.stop_at={STOP}").train()
        run = self.trainer("resumed")
        said = io.StringIO()
        with redirect_stdout(said):  # the trainer says where it resumed
            run.train()
        _require(f"at iteration {STOP}" in said.getvalue(),
                 f"the second call did not resume from the checkpoint of step {STOP}: {said.getvalue()[-300:]!r}")
        self.same(self.full(), run, f"stopped at {STOP} and resumed")
        return f"stopped at {STOP}, resumed to {STEPS}: bit-identical"

    def check_culling(self) -> str:
        tr = self.full()
        model = tr.state.model.eval()
        if not model.can_cull(model.step):
            return "not applicable: the module has opacity deltas (capability 'opacity_deltas'), culling is off"
        gen = torch.Generator().manual_seed(0)
        with torch.no_grad():
            faint = (torch.rand(model.num_gaussians, generator=gen) < 0.6).to(model.params["opacities"].device)
            model.params["opacities"][faint] = FAINT
        frame = tr.scene.frames("test")[1]
        with torch.no_grad():
            g, rows = model.deformed_rows(frame.time, cull=False)
            full = model.render_gaussians(g, frame.camera).image
            g, rows = model.deformed_rows(frame.time, cull=True)
            culled = model.render_gaussians(g, frame.camera).image
        _require(rows is not None and rows.numel() < model.num_gaussians, "culling kept every row")
        diff = (full - culled).abs().max().item()
        _require(diff <= 1e-6, f"the culled image differs from the full one by {diff:.3g}")
        return f"{rows.numel():,} of {model.num_gaussians:,} rows rendered, the same image (max diff {diff:.1g})"

    def check_compact(self) -> str:
        tr = self.trainer("compact")  # a run of its own: the culling check edits the full run's opacities
        tr.train()
        path = self.work / "model.stdrc"
        rec = write_compact(tr.state.model, path)
        small = load_model(path, "cpu")
        frames = tr.scene.frames("test")
        a = evaluate_model(tr.state.model, frames, fps_warmup=0)
        b = evaluate_model(small, frames, fps_warmup=0)
        worst = max(abs(x - y) for x, y in zip(a["per_frame_psnr"], b["per_frame_psnr"]))
        _require(worst < 0.05, f"the compact file renders a test frame {worst:.3f} dB away from the model")
        return f"{rec['bytes']:,} bytes ({rec['bytes'] / rec['full_bytes']:.1%} of the model); worst frame {worst:.3f} dB"

    def check_learns(self) -> str:
        if self.quick:
            tr = self.trainer("learns")
        else:  # the embedded experiment's own budget (demo), on the 64 px scene
            tr = Trainer(tiny_config(self.work, [f"experiment={self.experiment}", "budget=demo"]), self.work / "learns",
                         splits=("train", "test"))
        before = tr.evaluate("test")["psnr"]
        tr.train()
        after = tr.evaluate("test")["psnr"]
        _require(after >= before + 1.0, f"test PSNR {before:.2f} -> {after:.2f} dB after {tr.step} steps: it does not learn")
        return f"test PSNR {before:.2f} -> {after:.2f} dB in {tr.step} steps"


CHECKS = ("identity", "device", "resume", "culling", "compact", "learns")


def run_kit(baseline: str, plugin: str | None = None, quick: bool = False, work: Path | None = None,
            checks=CHECKS, out=print) -> dict[str, tuple[str, str]]:
    """Every check on `baseline` (with `plugin` on): {check: (status, detail)}, status 'pass' or 'FAIL'."""
    from ..store import register  # noqa: PLC0415 (the registries' entry points, before the names are checked)
    register()
    if baseline not in BASELINES:
        raise SystemExit(f"{baseline!r} is not a registered baseline ({', '.join(sorted(BASELINES))})")
    if plugin is not None and plugin not in PLUGINS:
        raise SystemExit(f"{plugin!r} is not a registered plug-in ({', '.join(PLUGINS)})")
    exp = f"embedded_{baseline}" + (f"_{plugin}" if plugin else "")
    if exp not in experiment_names():
        raise SystemExit(f"{plugin} does not apply to {baseline} (its capabilities: "
                         f"{', '.join(sorted(capabilities(BASELINES[baseline].module))) or 'none'}): no experiment {exp}")
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        kit = Kit(exp, plugin, Path(work) if work else Path(tmp), quick)
        for name in checks:
            t0 = time.perf_counter()
            try:
                results[name] = ("pass", getattr(kit, f"check_{name}")())
            except CheckFailed as e:
                results[name] = ("FAIL", str(e))
            except Exception as e:  # a check that crashes fails, with what crashed
                results[name] = ("FAIL", f"{type(e).__name__}: {e}")
            out(f"{exp:>28}  {name:<9} {results[name][0]:<5} {results[name][1]}  ({time.perf_counter() - t0:.0f} s)")
    return results


def main(argv=None, kind: str = "baseline") -> int:
    """`stdr-tool check-baseline` (kind "baseline") and `check-plugin` ("plugin"); 1 when a check fails."""
    argv = list(sys.argv[1:] if argv is None else argv)
    ap = argparse.ArgumentParser(prog=f"stdr-tool check-{kind}", description=__doc__.split("\n")[0])
    ap.add_argument("name", help=f"a registered {'baseline' if kind == 'baseline' else 'plug-in'}")
    if kind == "baseline":
        ap.add_argument("--plugin", default=None, help="with this plug-in on (e.g. stdr)")
    else:
        ap.add_argument("--baseline", default="deform", help="the baseline it runs on (default: deform)")
    ap.add_argument("--quick", action="store_true", help="`learns` on the 60-step run instead of budget=demo")
    ap.add_argument("--check", nargs="+", choices=CHECKS, default=list(CHECKS), help="only these checks")
    a = ap.parse_args(argv)
    base, plug = (a.name, a.plugin) if kind == "baseline" else (a.baseline, a.name)
    res = run_kit(base, plug, quick=a.quick, checks=a.check)
    failed = [k for k, (s, _) in res.items() if s != "pass"]
    print(f"{len(res) - len(failed)} of {len(res)} checks passed" + (f"; failed: {', '.join(failed)}" if failed else ""))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
