"""STDR as a plug-in (stdr.plugins.interface: Plugin with the roles Conditioner, Densifying and
Reporting, and the compact file's form): mask, phases, regularizers, separated field.

The model and the loop ask it, whatever the baseline (each hook with the step's context, ctx):
  - `init_gaussians(params)`: the mask logits [N, K] join the parameter dict (lr stdr.mask_lr);
  - `before_step(ctx)`: which of opacity / mask train in this phase (`frozen_keys`: the 8-bit
    mask is fixed for good);
  - `conditioning(ctx)`: the per-Gaussian input of the deformation network (and the dynamic
    probability, when it scales the deltas);
  - `opacity_factor(ctx)`: the activated mask at time ctx.t, multiplied into opacity;
  - `regularizers(ctx)`: the weighted L_temp and L_spatial;
  - `reset_opacity` / `prune_factor`: the densification's reset and pruning see the mask;
  - `param_groups()`: the separated field, on the deformation's schedule or its own.
Phases (steps count from 0): warm-up [0, warmup_end) - opacity frozen, mask trains;
regularized [0, freeze_at); frozen [freeze_at, end) - mask frozen, field on.
Everything per Gaussian lives in the parameter dict (key `stdr_mask`), so densification keeps
it aligned; p = softmax_t(m) is a cache recomputed whenever the mask tensor is replaced.
"""
from __future__ import annotations

import sys
from typing import Any, Optional

import torch
from torch import Tensor

from ...ops import sigmoid
from ...encoding import positional_encoding, positional_encoding_dim
from ...context import StepContext
from ..interface import Conditioner, Densifying, Plugin, Reporting
from .compact_form import CompactMask
from ...device import cpu_bf16_flags, emulated_bf16_note
from .field import FIELD_PRECISIONS, SeparatedField
from .mask import BETWEEN, COND_KEY, MASK_KEY, activated, knot_times, logits_of, mask_at, quantize
from .monitor import log_to, stats_of
from .regularizers import NeighbourCache, regularizer_terms
from .phases import Phase, add_stages, logit, phase_at, resolve_init


#: whether stdr.field_precision=auto follows the deformation network into bf16: the field's bf16
#: step is faster (deform+STDR 1.27-1.28x at 11k-20k Gaussians) and passed the val rule: mean val
#: delta PSNR -0.038 dB over 8 budget=cpu pairs and +0.016 over 2 cpu_long pairs
#: (research/measurements/precision_val, "STDR's separated field in bf16"; docs/performance.md)
FIELD_BF16_DEFAULT = True
#: the baselines beside whose fp32 network stdr.field_precision=auto still trains the field in bf16
#: on a CPU with bf16 matrix instructions: the +STDR step is faster and the val rule passed with the
#: network in fp32 (research/measurements/precision_val, "STDR's field in bf16 beside SC-GS, SP-GS
#: and 4DGS"; docs/performance.md)
FIELD_BF16_BESIDE_FP32 = frozenset({"scgs", "spgs", "4dgs"})


def field_precision(requested: str, network_precision: str, device, baseline: str = "", cpu_flags=None) -> str:
    """stdr.field_precision resolved: auto follows the deformation network's (`network_precision`,
    baseline.precision as resolved for the run) where FIELD_BF16_DEFAULT, and is bf16 beside the fp32
    network of a baseline of FIELD_BF16_BESIDE_FP32 on a CPU with bf16 matrix instructions
    (stdr.device.cpu_bf16_flags, or `cpu_flags`); fp32 otherwise. An explicit bf16 on a CPU without
    bf16 matrix instructions runs, and says in one line that it is slower there."""
    if requested not in ("auto", *FIELD_PRECISIONS):
        raise ValueError(f"stdr.field_precision={requested!r}: use one of {('auto', *FIELD_PRECISIONS)}")
    if requested == "auto":
        if not FIELD_BF16_DEFAULT:
            return "fp32"
        if network_precision == "bf16":
            return "bf16"
        cpu = torch.device(device).type == "cpu"
        flags = (cpu_bf16_flags() if cpu_flags is None else tuple(cpu_flags)) if cpu else ()
        return "bf16" if baseline in FIELD_BF16_BESIDE_FP32 and flags else "fp32"
    if requested == "bf16" and torch.device(device).type == "cpu" and not cpu_bf16_flags():
        print(f"[stdr] {emulated_bf16_note('stdr.field_precision')}", file=sys.stderr)
    return requested


def _same_key(a: tuple, b: tuple) -> bool:
    """Two conditioning keys ((tensor, version), ...) name the same tensors at the same versions."""
    return len(a) == len(b) and all(x is y and vx == vy for (x, vx), (y, vy) in zip(a, b))


class STDR(CompactMask, Conditioner, Densifying, Reporting, Plugin):
    """State and rules of the plug-in. `cfg` is the `stdr` config node (StdrConfig)."""

    name = "stdr"

    # ----------------------------------------------------------------- registration
    @classmethod
    def from_config(cls, pcfg, cfg, schedule, train_times, device) -> "STDR":
        """Its phases from the schedule, its time knots from the training times."""
        knots = cls.knots_for(pcfg, train_times) if train_times is not None else None
        return cls(pcfg, schedule, knots, xyz_freqs=cfg.baseline.xyz_freqs, seed=cfg.seed,
                   init_opacity=cfg.model.init_opacity, device=device,
                   network_precision=str(getattr(cfg.baseline, "precision", "fp32")), baseline=str(cfg.baseline.name))

    @classmethod
    def stages(cls, pcfg, cfg, schedule) -> dict:
        """Mask warm-up, regularized phase and freeze (stdr.plugins.stdr.phases.add_stages)."""
        return add_stages(pcfg, schedule)

    def __init__(self, cfg, schedule, knots: Optional[Tensor], xyz_freqs: int, seed: int,
                 init_opacity: float = 0.1, device: torch.device | str = "cpu", network_precision: str = "fp32",
                 baseline: str = ""):
        """schedule: the run's stdr.schedule.Schedule (STDR's phases, already kept out of the
        baseline's switch windows); network_precision: the deformation network's arithmetic
        (baseline.precision, resolved), which stdr.field_precision=auto follows, and `baseline` its
        name (field_precision)."""
        if int(cfg.mask_bits) not in (8, 32):
            raise ValueError(f"stdr.mask_bits={cfg.mask_bits}: use 32 (float logits) or 8 (uint8 after the freeze)")
        self.mask_between = getattr(cfg, "mask_between", "linear")  # read once: opacity_factor runs every step
        if self.mask_between not in BETWEEN:
            raise ValueError(f"stdr.mask_between={self.mask_between!r}: use one of {BETWEEN}")
        self.cfg = cfg
        self.field_precision = field_precision(getattr(cfg, "field_precision", "auto"), network_precision, device,
                                               baseline)
        self.device = torch.device(device)  # of the separated field; the knots stay on the CPU (host-side lookups)
        self.iterations = int(schedule.iterations)
        phases = schedule.plugins[self.name]  # STDR.stages
        self.warmup_end, self.freeze_at = int(phases["warmup_end"]), int(phases["freeze_at"])
        self.freeze_moved: Optional[str] = phases["freeze_moved"]
        self.opacity_init, self.mask_init = resolve_init(cfg, init_opacity)
        self._cleaned = False
        self.cleaned_entries: Optional[int] = None  # set at the freeze
        self.xyz_freqs = xyz_freqs if cfg.field_pe_xyz else -1
        self.neighbours = NeighbourCache(cfg, seed, self.device)  # the spatial term's queries and their KNN
        self._params = None  # the model's parameter dict (init_gaussians / load_state_dict): for state_dict
        self._p_for: Optional[tuple] = None  # (mask tensor, its version) the softmax cache was built from
        self._p: Optional[Tensor] = None
        self.last_dynamic: Optional[Tensor] = None
        self._cond_cache: Optional[tuple] = None  # (key, (cond, d)) of the last conditioning outside training
        self.knots: Optional[Tensor] = None
        self.field: Optional[SeparatedField] = None
        if knots is not None:
            self._set_knots(knots)

    # ----------------------------------------------------------------- set-up
    @staticmethod
    def knots_for(cfg, train_times) -> Tensor:
        return knot_times(train_times, cfg.time_bins)

    def _set_knots(self, knots: Tensor) -> None:
        self.knots = knots.double().cpu()
        self.knot_values = tuple(self.knots.tolist())  # host floats: time lookups in a step read no tensor
        if self.cfg.separated_field:
            pe = 0 if self.xyz_freqs < 0 else positional_encoding_dim(3, self.xyz_freqs)
            self.field = SeparatedField(self.K + pe, self.cfg.field_width, self.cfg.temporal_dim,
                                        self.cfg.dropout, self.field_precision).to(self.device)

    @property
    def K(self) -> int:
        return int(self.knots.numel())

    @property
    def cond_dim(self) -> int:
        return self.cfg.temporal_dim + 1 if self.cfg.separated_field else 0

    def init_gaussians(self, params) -> None:
        """Add the mask logits [N, K] to the parameter dict (no-op with stdr.mask=false), and set
        the opacities to stdr.opacity_init when it is given."""
        self._params = params
        if self.cfg.mask:
            n = params["means"].shape[0]
            params[MASK_KEY] = torch.nn.Parameter(torch.full((n, self.K), self.mask_init,
                                                             device=params["means"].device))
            if self.opacity_init is not None:
                with torch.no_grad():
                    params["opacities"].fill_(logit(self.opacity_init))

    def param_groups(self) -> list[dict]:
        """The mask's rate (stdr.mask_lr), and the separated field: on the deformation network's
        schedule (stdr.field_lr_init=null), or log-linear from stdr.field_lr_init at the freeze
        (where it starts training) to stdr.field_lr_final at the end of the run."""
        mask = [{"key": MASK_KEY, "lr": float(self.cfg.mask_lr)}]
        if self.field is None:
            return mask
        g: dict[str, Any] = {"params": list(self.field.parameters()), "name": "stdr_field"}
        if self.cfg.field_lr_init is not None:
            final = self.cfg.field_lr_final
            g.update(lr_init=float(self.cfg.field_lr_init),
                     lr_final=float(self.cfg.field_lr_init if final is None else final),
                     lr_max_steps=max(self.iterations - self.freeze_at, 1), lr_delay=self.freeze_at)
        return [*mask, g]

    def modules(self) -> list[torch.nn.Module]:
        return [] if self.field is None else [self.field]

    def to(self, device) -> "STDR":
        self.device = torch.device(device)
        if self.field is not None:
            self.field.to(self.device)
        self.neighbours.to(self.device)
        self._p_for = None
        self._cond_cache = None
        return self

    def prune_factor(self, ctx: StepContext) -> Optional[Tensor]:
        """With stdr.prune_by_mask: the largest activated mask over time [N], so pruning looks at
        the largest opacity a Gaussian reaches."""
        params, step = ctx.params, ctx.step
        if not self.cfg.prune_by_mask or not self.has_mask(params) or not self.mask_modulates(step):
            return None
        return activated(params[MASK_KEY].detach()).amax(1)

    def phase(self, step: int) -> Phase:
        return phase_at(step, self.warmup_end, self.freeze_at)

    def has_mask(self, params) -> bool:
        return MASK_KEY in params

    # ----------------------------------------------------------------- per step
    def opacity_frozen(self, step: int) -> bool:
        """Whether opacity is held at `step`: in the warm-up, with stdr.freeze_opacity (the paper)."""
        return self.cfg.freeze_opacity and self.phase(step) == Phase.WARMUP

    def before_step(self, ctx: StepContext) -> None:
        """Opacity trains unless frozen in the warm-up; the mask trains until the freeze."""
        params, step = ctx.params, ctx.step
        ph = self.phase(step)
        if self.has_mask(params):
            if ph == Phase.FROZEN and not self._cleaned:
                self.cleanup(params)
            if ph == Phase.FROZEN and self.cfg.mask_bits == 8 and params[MASK_KEY].is_floating_point():
                self.store_mask_8bit(params)  # at the freeze; a run continued past it with the key: at once
            params["opacities"].requires_grad_(not self.opacity_frozen(step))
            params[MASK_KEY].requires_grad_(ph != Phase.FROZEN)

    def frozen_keys(self, params) -> set[str]:
        """The mask once stored in 8 bits (stdr.mask_bits=8, from the freeze on): fixed for good."""
        return {MASK_KEY} if self.has_mask(params) and not params[MASK_KEY].is_floating_point() else set()

    @torch.no_grad()
    def cleanup(self, params) -> int:
        """At the freeze: mask entries whose masked opacity sigmoid(o) * sigmoid(m) is below
        stdr.freeze_cleanup are switched off for good (logit -30). Such entries no longer get a
        gradient (the rasterizer skips alpha < 1/255) and would reappear as ghosts when opacity
        grows after the freeze. Returns the number of entries switched off."""
        self._cleaned = True
        thr = float(self.cfg.freeze_cleanup)
        if thr <= 0 or not self.has_mask(params):
            self.cleaned_entries = 0
            return 0
        m = params[MASK_KEY]
        eff = sigmoid(m) * sigmoid(params["opacities"])[:, None]
        off = eff < thr
        m.masked_fill_(off, -30.0)
        self._p_for = None  # the softmax cache was built from the old values
        self.cleaned_entries = int(off.sum())
        return self.cleaned_entries

    @torch.no_grad()
    def store_mask_8bit(self, params) -> None:
        """stdr.mask_bits=8, at the freeze (or, for a run continued past its freeze with the key, e.g.
        by `stdr-tool compact`, at its first step): the mask becomes uint8 q = round(255 sigmoid(m)) in the
        parameter dict (no gradient, no optimizer), a quarter of its float32 bytes in memory, in
        checkpoints and in model_mb; renders read q / 255 directly (mask.activated), the field's
        softmax reads logit(q / 255) (mask.logits_of). From here on the run trains with exactly what
        is stored, so resume and load_model are exact."""
        params[MASK_KEY] = torch.nn.Parameter(quantize(params[MASK_KEY]), requires_grad=False)
        self._p_for = None
        self._cond_cache = None

    @torch.no_grad()
    def reset_opacity(self, ctx: StepContext, value: float) -> bool:
        """The densification's opacity reset during the warm-up, where opacity is frozen: cap the
        masked opacity sigmoid(o) * sigmoid(m) at `value` through the mask instead (clamping the
        frozen opacity would hold every Gaussian under `value` until the warm-up ends). Returns
        False while opacity trains: the strategy then resets the opacities as usual."""
        params, step = ctx.params, ctx.step
        if not self.has_mask(params) or not self.opacity_frozen(step):
            return False
        m = params[MASK_KEY]
        o = sigmoid(params["opacities"])[:, None]
        cap = (value / o).clamp(max=1.0 - 1e-6)
        m.copy_(torch.minimum(m, torch.log(cap / (1.0 - cap))))
        self._p_for = None
        return True

    def mask_modulates(self, step: int) -> bool:
        return self.cfg.mask and (self.phase(step) != Phase.FROZEN or self.cfg.mask_after_freeze)

    def opacity_factor(self, ctx: StepContext) -> Optional[Tensor]:
        """Activated mask [N] at time ctx.t, or None when the mask does not modulate opacity now."""
        params, t, step = ctx.params, ctx.t, ctx.step
        if not self.has_mask(params) or not self.mask_modulates(step):
            return None
        return mask_at(params[MASK_KEY], t, self.knot_values, self.mask_between)

    def probabilities(self, params) -> Tensor:
        """p = softmax_t(m) [N, K], computed once per mask tensor and version (uniform without a mask)."""
        if not self.has_mask(params):
            n = params["means"].shape[0]
            return torch.full((n, self.K), 1.0 / self.K, device=params["means"].device)
        m = params[MASK_KEY]
        if self._p_for is None or self._p_for[0] is not m or self._p_for[1] != m._version:
            self._p = torch.softmax(logits_of(m.detach()), -1)
            self._p_for = (m, m._version)  # recomputed when the tensor is replaced or changed in place
        return self._p

    def conditioning(self, ctx: StepContext) -> tuple[Optional[Tensor], Optional[Tensor]]:
        """The hook: `conditioning_at(ctx.params, ctx.step)`."""
        return self.conditioning_at(ctx.params, ctx.step)

    def conditioning_at(self, params, step: int) -> tuple[Optional[Tensor], Optional[Tensor]]:
        """(cond [N, cond_dim] or None, delta scale [N, 1] or None) for the deformation network.

        Before the freeze the field is off and cond is zeros (the network's cond inputs start at
        zero weight, so switching the field on does not change the render).
        """
        if self.field is None:
            return None, None
        if COND_KEY in params:  # a compact file's derived form: the field's output itself
            cond = params[COND_KEY].detach().float()
            self.last_dynamic = d = cond[:, -1:]
            return cond, (d if self.cfg.scale_deltas_by_dynamic else None)
        n = params["means"].shape[0]
        if self.phase(step) != Phase.FROZEN:
            return torch.zeros(n, self.cond_dim, device=params["means"].device), None
        # outside training (eval mode, no autograd) the conditioning is the same for every frame:
        # computed once and reused until the mask, the means (with the xyz encoding) or a field
        # weight changes (tensor identity and in-place version)
        frozen = not self.field.training and not torch.is_grad_enabled()
        key = self._conditioning_key(params) if frozen else None
        if key is not None and self._cond_cache is not None and _same_key(self._cond_cache[0], key):
            cond, d = self._cond_cache[1]
            self.last_dynamic = d
            return cond, (d if self.cfg.scale_deltas_by_dynamic else None)
        x = self.probabilities(params)
        if self.xyz_freqs >= 0:
            x = torch.cat([x, positional_encoding(params["means"].detach(), self.xyz_freqs)], -1)
        z, d = self.field(x)
        self.last_dynamic = d.detach()
        cond = torch.cat([z, d], -1)
        self._cond_cache = (key, (cond, d)) if key is not None else None
        return cond, (d if self.cfg.scale_deltas_by_dynamic else None)

    def _conditioning_key(self, params) -> tuple:
        """What the conditioning is a function of: the mask (or the row count without one), the
        means with the xyz encoding, and the field's weights and BatchNorm statistics."""
        ts = [params[MASK_KEY] if self.has_mask(params) else params["means"]]
        if self.xyz_freqs >= 0:
            ts.append(params["means"])
        ts += list(self.field.parameters()) + list(self.field.buffers())
        return tuple((t, t._version) for t in ts)

    def regularizers(self, ctx: StepContext) -> dict[str, Tensor]:
        """Weighted L_temp and L_spatial while the phase is warm-up or regularized."""
        params, step = ctx.params, ctx.step
        if not self.has_mask(params) or self.phase(step) == Phase.FROZEN:
            return {}
        m = params[MASK_KEY]
        return regularizer_terms(self.cfg, m, lambda: self.neighbours.get(params["means"], m, step))

    # ----------------------------------------------------------------- state
    def state_dict(self) -> dict[str, Any]:
        mask = None if self._params is None else self._params.get(MASK_KEY)
        return {"knots": self.knots, "field": None if self.field is None else self.field.state_dict(),
                "field_precision": self.field_precision,
                **self.neighbours.state_dict(mask), "cleaned": self._cleaned, "cleaned_entries": self.cleaned_entries}

    def load_state_dict(self, s: dict[str, Any], params) -> None:
        if self.knots is None or not torch.equal(self.knots, s["knots"]):
            if self.knots is not None:
                raise ValueError(f"checkpoint has {s['knots'].numel()} STDR time knots, this run {self.K}")
            self._set_knots(s["knots"])
        if getattr(self.cfg, "field_precision", "auto") == "auto":
            # the arithmetic the state was trained with (fp32 before the key was recorded)
            self.field_precision = s.get("field_precision", "fp32")
            if self.field is not None:
                self.field.precision = self.field_precision
        if self.field is not None and s["field"] is not None:
            self.field.load_state_dict(s["field"])
        elif self.field is not None and COND_KEY not in params:
            raise ValueError("STDR state without the separated field's weights, and no stored field output "
                             f"({COND_KEY}) to read instead")
        self.neighbours.device = self.device
        self.neighbours.load_state_dict(s, params.get(MASK_KEY))
        self._params = params
        self._cleaned = bool(s.get("cleaned", False))
        self.cleaned_entries = s.get("cleaned_entries")
        self._cond_cache = None

    # ----------------------------------------------------------------- monitoring
    def log(self, tb, ctx: StepContext, images: bool, x: Optional[int] = None) -> None:
        """TensorBoard: the phase, mask statistics and, with images, histograms and the mask over
        time (stdr.plugins.stdr.monitor.log_to)."""
        log_to(tb, self, ctx.params, ctx.step, images, x)

    def stats(self, params) -> dict[str, Any]:
        """Numbers for metrics.json (stdr.plugins.stdr.monitor.stats_of)."""
        return stats_of(self, params)
