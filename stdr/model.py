"""The model: Gaussians, a deformation module and plug-ins, rendered at a time t.

`DynamicGaussians` is everything needed to render a trained scene and nothing about how it was
optimized (optimizers, learning rates, densification and the loop live in `stdr.train`):

    model = load_model("outputs/run/checkpoints/last.pt", device="cuda")
    out = model.render(camera, t=0.5)             # RenderOutput, image [H, W, 3]

Its checkpoint entry holds the resolved config, the training times and the background, so it
rebuilds without the training data. What a render does depends on the iteration the model was
trained to (`model.step`): before the baseline's static warm-up ends the Gaussians are not
deformed, the SH degree grows with the step, and plug-ins have phases (stdr.plugins).
"""
from __future__ import annotations

import sys

from pathlib import Path
from typing import Any, Optional

import numpy as np
import torch
from omegaconf import OmegaConf
from torch import Tensor

from .errors import BadInput
from .cameras import Camera
from .baselines import build_deformation, get_baseline
from .baselines.base import canonical_opacity, choose_precision, deform_gaussians
from .device import resolve_device
from .context import StepContext
from .plugins import Conditioner, Densifying, Plugin, enabled_plugins, plugin_node, registered_plugins
from .plugins.interface import roles
from .ops import RowView, rows_of, sigmoid
from .render import RenderOutput, render, resolve_backend
from .render.reference import ALPHA_MIN
from .schedule import Schedule
from .store import load_config, resolve_schedule
from .compression.codecs import nbytes
from .gaussians import Gaussians, activate, init_params, num_gaussians
from .io.checkpoint import load_checkpoint, save_checkpoint
from .compression.file import compact_source_note, decode_model, is_compact
from .data.dnerf import parse_background

CHECKPOINT_FORMAT = 2
CULL_MODES = ("off", "eval", "train")


def active_rows(opacities: Tensor) -> Tensor:
    """Rows [M] (ascending) whose opacity [N] reaches the rasterizer's cut-off 1/255, compared
    in the opacities' dtype as the rasterizer compares: the others change no pixel anywhere."""
    return torch.nonzero(opacities >= ALPHA_MIN).squeeze(1)


def build_plugins(cfg, schedule: Schedule, train_times: Optional[np.ndarray], device: torch.device) -> list[Plugin]:
    """The registered plug-ins the config switches on (`<name>.enabled`), in registration order,
    each built by its `from_config`."""
    return [s.plugin.from_config(plugin_node(cfg, s.name), cfg, schedule, train_times, device)
            for s in enabled_plugins(cfg)]


class DynamicGaussians:
    """Per-Gaussian parameters (one dict, plug-ins' tensors included), the deformation module and the
    plug-ins. Renders `deformed(t)` and saves / loads / moves itself."""

    def __init__(self, cfg, schedule: Schedule, params: torch.nn.ParameterDict, deform, plugins: list[Plugin],
                 train_times: Optional[np.ndarray], background: Tensor, device: torch.device):
        self.cfg = cfg
        self.schedule = schedule
        self.params = params
        self.deform = deform
        self.plugins = plugins
        self.train_times = None if train_times is None else np.asarray(train_times, dtype=np.float64)
        self.device = device
        self.background = background.to(device)  # [3]
        self.backend = resolve_backend(cfg.render.backend, device)
        self.step = 0  # iterations trained
        self.last_active: Optional[int] = None  # Gaussians rendered by the last `render` (after culling)

    # ----------------------------------------------------------------- plug-ins
    def plugin(self, name: str) -> Optional[Plugin]:
        """The plug-in called `name`, or None when it is off."""
        return next((p for p in self.plugins if p.name == name), None)

    def frozen_keys(self) -> set[str]:
        """Parameter keys the plug-ins hold fixed for good (Plugin.frozen_keys): no optimizer."""
        return set().union(*(p.frozen_keys(self.params) for p in self.plugins))

    @property
    def cond_dim(self) -> int:
        return sum(p.cond_dim for p in roles(self.plugins, Conditioner))

    def context(self, step: int, **fields) -> StepContext:
        """The hooks' context (stdr.context.StepContext) at `step`: the parameter dict, the warm-up's
        end and `fields` (t, camera, cond, deformed, rows, render)."""
        return StepContext(step, self.params, self.warmup, **fields)

    @property
    def warmup(self) -> int:
        """End of the static warm-up (the deformation is off before it), from the schedule."""
        return self.schedule.static_warmup_end

    @property
    def num_gaussians(self) -> int:
        return num_gaussians(self.params)

    # ----------------------------------------------------------------- rendering
    def sh_degree(self, step: int) -> int:
        m = self.cfg.model
        return min(m.sh_degree, step // max(m.sh_interval, 1))

    def conditioning(self, step: int) -> tuple[Optional[Tensor], Optional[Tensor]]:
        """(cond [N, cond_dim], delta scale [N, 1]) for the deformation network at `step`, from the
        plug-ins (concatenated / multiplied), or (None, None) without any or in the warm-up."""
        if step < self.warmup:
            return None, None
        conds, scale = [], None
        ctx = self.context(step)
        for p in roles(self.plugins, Conditioner):
            c, s = p.conditioning(ctx)
            if c is not None:
                conds.append(c)
            if s is not None:
                scale = s if scale is None else scale * s
        cond = None if not conds else conds[0] if len(conds) == 1 else torch.cat(conds, -1)
        return cond, scale

    def deformed(self, t: float, step: Optional[int] = None,
                 cond_scale: Optional[tuple[Optional[Tensor], Optional[Tensor]]] = None) -> Gaussians:
        """Activated Gaussians at time t: deformed after the static warm-up, opacity times the
        plug-ins' factors. cond_scale: this step's `conditioning` (computed when None)."""
        return self.deformed_rows(t, step, cond_scale, cull=False)[0]

    def can_cull(self, step: int) -> bool:
        """Whether a Gaussian's opacity at time t is known before the deformation runs (the
        module has no opacity deltas, or the static warm-up leaves the Gaussians as they are)."""
        return step < self.warmup or canonical_opacity(self.deform)

    def deformed_rows(self, t: float, step: Optional[int] = None,
                      cond_scale: Optional[tuple[Optional[Tensor], Optional[Tensor]]] = None,
                      cull: bool = False) -> tuple[Gaussians, Optional[Tensor]]:
        """(Gaussians at time t, rows [M] they are of the model, or None for all).

        cull: temporal culling. Rows whose opacity at t, sigmoid(o) times the plug-ins' factors,
        is below 1/255 cannot change a pixel or get a gradient from the render (the rasterizer's
        cut-off), so they skip the deformation network, the projection and
        the rasterizer. The image equals the unculled one; the culled rows get zero gradient,
        as they do without culling. Parts a baseline shares between Gaussians (SC-GS's node
        conditioning, SP-GS's superpoints) are still computed from every row
        (`Deformation.forward_rows`)."""
        step = self.step if step is None else step
        ctx = self.context(step, t=t)
        factors = [f for p in roles(self.plugins, Conditioner) if (f := p.opacity_factor(ctx)) is not None]
        rows = None
        if cull and self.can_cull(step):
            eff = sigmoid(self.params["opacities"])  # the value `apply` gives, times the factors
            for f in factors:
                eff = eff * f
            keep = active_rows(eff)
            rows = None if keep.shape[0] == eff.shape[0] else keep
        if step < self.warmup:
            g = activate(self.params if rows is None else RowView(self.params, rows))
        else:
            cond, scale = self.conditioning(step) if cond_scale is None else cond_scale
            g = deform_gaussians(self.deform, self.params, t, cond, scale, rows)
        for f in factors:
            g = g._replace(opacities=g.opacities * rows_of(f, rows))
        return g, rows

    def cull_mode(self) -> str:
        """render.cull: 'off', 'eval' (evaluation and rendering cull; training renders every
        row) or 'train' (training culls too: densification then counts a culled row as not seen,
        which needs densify.count_invisible=false)."""
        mode = str(self.cfg.render.get("cull", "off"))
        if mode not in CULL_MODES:
            raise ValueError(f"render.cull={mode!r}: use one of {CULL_MODES}")
        return mode

    def render_gaussians(self, g: Gaussians, camera: Camera, step: Optional[int] = None) -> RenderOutput:
        r = self.cfg.render
        return render(g.means, g.quats, g.scales, g.opacities, g.sh, camera,
                      sh_degree=self.sh_degree(self.step if step is None else step), background=self.background,
                      backend=self.backend, near=r.near, eps2d=r.eps2d, antialiased=r.antialiased,
                      tile_size=r.tile_size, compiled_projection=r.get("compiled_projection"))

    def render(self, camera: Camera, t: float, step: Optional[int] = None,
               cull: Optional[bool] = None) -> RenderOutput:
        """The model at time t seen from `camera` (at the trained iteration unless `step`).
        cull: temporal culling (`deformed_rows`); None follows render.cull (on unless 'off').
        The number of rows rendered is kept in `last_active`."""
        cull = self.cull_mode() != "off" if cull is None else cull
        g, rows = self.deformed_rows(t, step, cull=cull)
        self.last_active = g.means.shape[0]
        return self.render_gaussians(g, camera, step)

    def train(self, mode: bool = True) -> "DynamicGaussians":
        """Train mode (BatchNorm batch statistics, dropout) in train steps, eval mode elsewhere."""
        self.deform.train(mode)
        for p in self.plugins:
            for m in p.modules():
                m.train(mode)
        return self

    def eval(self) -> "DynamicGaussians":
        return self.train(False)

    # ----------------------------------------------------------------- densification hooks
    def prune_opacity_fn(self, step: int):
        """`opacity_fn` for the strategy: sigmoid(opacity) times the plug-ins' prune factors (None
        without plug-ins: the strategy then uses sigmoid(opacity)). The factors are computed only
        when the strategy prunes, never on the steps in between."""
        densifying = roles(self.plugins, Densifying)
        if not densifying:
            return None

        def fn(params):
            o = sigmoid(params["opacities"].detach())
            ctx = StepContext(step, params, self.warmup)
            for p in densifying:
                f = p.prune_factor(ctx)
                if f is not None:
                    o = o * f
            return o
        return fn

    def reset_opacity_fn(self, step: int):
        """`reset_fn` for the strategy: the first plug-in that handles the reset, else the strategy."""
        densifying = roles(self.plugins, Densifying)
        if not densifying:
            return None
        return lambda params, value: any(p.reset_opacity(StepContext(step, params, self.warmup), value)
                                         for p in densifying)

    # ----------------------------------------------------------------- state
    def to(self, device: torch.device | str) -> "DynamicGaussians":
        """Move parameters, networks and plug-ins to `device` (the parameter objects are replaced:
        build optimizers after moving)."""
        self.device = torch.device(device)
        for k in list(self.params.keys()):
            self.params[k] = torch.nn.Parameter(self.params[k].detach().to(self.device),
                                                requires_grad=self.params[k].requires_grad)
        self.deform.to(self.device)
        for p in self.plugins:
            p.to(self.device)
        self.background = self.background.to(self.device)
        self.backend = resolve_backend(self.cfg.render.backend, self.device)
        return self

    def state_dict(self) -> dict[str, Any]:
        return {
            "format": CHECKPOINT_FORMAT,
            "config": OmegaConf.to_container(self.cfg, resolve=True),
            "step": self.step,
            "params": {k: v.detach().clone() for k, v in self.params.items()},
            "deform": self.deform.state_dict(),
            "plugins": {p.name: p.state_dict() for p in self.plugins},
            "train_times": None if self.train_times is None else torch.from_numpy(self.train_times.copy()),
            "background": self.background.detach().cpu().clone(),
        }

    def load_state_dict(self, s: dict[str, Any], where: str = "checkpoint") -> None:
        have, want = sorted(p.name for p in self.plugins), sorted(s.get("plugins", {}))
        if have != want:
            raise BadInput(f"{where}: saved with plug-ins {want or 'none'} but this model has {have or 'none'} "
                             "(e.g. a plug-in's `enabled` differs); use the run's own config.yaml")
        self.params.clear()
        for k, v in s["params"].items():  # (an integer tensor, e.g. an 8-bit mask, takes no gradient)
            self.params[k] = torch.nn.Parameter(v.to(self.device), requires_grad=v.is_floating_point())
        self.deform.load_state_dict(s["deform"])
        for p in self.plugins:
            p.load_state_dict(s["plugins"][p.name], self.params)
        self.step = int(s["step"])

    def save(self, path: str | Path) -> None:
        """A checkpoint holding the model alone (no optimizer state): `load_model` reads it."""
        save_checkpoint(path, {"model": self.state_dict()})


def build_model(cfg, train_times: Optional[np.ndarray], background: Tensor, device: torch.device,
                points: Optional[Tensor] = None, colors: Optional[Tensor] = None) -> DynamicGaussians:
    """The model of a config: Gaussians at `points` (none: an empty dict for `load_state_dict`),
    the baseline's deformation module (built for the plug-ins' conditioning width) and the
    plug-ins, all reading their boundaries from the one schedule of the config. Random draws
    (network initializations) come from the global generator in a fixed
    order, so a seeded build is reproducible."""
    if points is None:
        params = torch.nn.ParameterDict()
    else:
        params = init_params(points.to(device), colors.to(device), sh_degree=cfg.model.sh_degree,
                             init_opacity=cfg.model.init_opacity)
    schedule = resolve_schedule(cfg)
    b = cfg.baseline
    if str(b.precision) == "auto":  # a run resolves it first (stdr.train.run); here before the plug-ins (their nets follow it)
        b.precision = choose_precision("auto", get_baseline(b.name).bf16_default, device, name=b.name)[0]
    plugins = build_plugins(cfg, schedule, train_times, device)
    if points is not None:
        for p in plugins:
            p.init_gaussians(params)
    deform = build_deformation(b, sum(p.cond_dim for p in roles(plugins, Conditioner)), train_times, seed=cfg.seed,
                               schedule=schedule).to(device)
    model = DynamicGaussians(cfg, schedule, params, deform, plugins, train_times, background, device)
    if points is not None:  # per-Gaussian state of the baseline (kept aligned by densification)
        deform.init_gaussians(params)
    return model


def has_model_entry(ck: dict[str, Any]) -> bool:
    """Whether a loaded checkpoint rebuilds its model alone (format 2 and later)."""
    return "model" in ck


def model_entry(ck: dict[str, Any], where: str) -> dict[str, Any]:
    """The model's part of a checkpoint (written by `DynamicGaussians.save` or by training)."""
    if has_model_entry(ck):
        return ck["model"]
    raise BadInput(f"{where}: a checkpoint from before format {CHECKPOINT_FORMAT} (no model entry, no training "
                     "times): stdr-eval reads it from its run folder; load_model cannot rebuild it alone")


def load_model(path: str | Path, device: str | torch.device = "auto", cfg=None,
               train_times: Optional[np.ndarray] = None) -> DynamicGaussians:
    """Rebuild a model from a checkpoint file, or a compact model file (`model.stdrc`,
    stdr.compression.file), on `device` ("auto", "cpu", "cuda", ...).

    cfg: the config to build with (default: the one saved in the checkpoint; a run's own
    config.yaml may override render settings). A checkpoint written before format 2 has no
    config or training times: pass both (stdr-eval does, from the run folder and its data)."""
    model = model_from_checkpoint(load_checkpoint(path), device, cfg, train_times, str(path))
    note = compact_source_note(path)
    if note:
        print(f"[stdr] {note}", file=sys.stderr, flush=True)
    return model





def model_from_checkpoint(ck: dict[str, Any], device: str | torch.device = "auto", cfg=None,
                          train_times: Optional[np.ndarray] = None, path: str = "checkpoint") -> DynamicGaussians:
    """`load_model` of an already loaded checkpoint dict."""
    dev = resolve_device(device) if isinstance(device, str) else torch.device(device)
    if is_compact(ck):  # a compact model file (stdr.compression.file): its entry, decoded
        ck = {"model": decode_model(ck, path)}
    if has_model_entry(ck):
        s = ck["model"]
    elif "params" in ck and cfg is not None and train_times is not None:  # format 1: a trainer payload
        s = {"step": ck["step"], "params": ck["params"], "deform": ck["deform"],
             # format 1 kept each plug-in's state at the top, under its name
             "plugins": {p.name: ck[p.name] for p in registered_plugins() if ck.get(p.name) is not None}, "train_times": None,
             "background": None}
    else:
        s = model_entry(ck, str(path))
    if cfg is None:
        cfg = load_config(s["config"], str(path))
    tt = s["train_times"].numpy() if s.get("train_times") is not None else train_times
    if tt is None:
        raise BadInput(f"{path}: no training times in the checkpoint; pass train_times")
    if s.get("background") is not None:
        bg = s["background"]
    else:
        bg = torch.tensor(parse_background(cfg.data.background))
    model = build_model(cfg, tt, bg.float(), dev)
    model.load_state_dict(s, str(path))
    return model


def model_bytes(model) -> int:
    """Bytes of the model's tensors (Gaussians, deformation module, plug-in state): the size a
    saved model takes without optimizer state."""
    return int(nbytes(model.state_dict()))
