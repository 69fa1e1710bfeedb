"""STDR's config: the typed `stdr.*` keys (registered with the plug-in: stdr/plugins/stdr/__init__.py)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional


@dataclass
class StdrConfig:
    """The `stdr.*` keys (docs/stdr.md: what the paper says, what is chosen here, and why)."""

    enabled: bool = False
    # ablation switches
    mask: bool = True             # false: no mask (the field, if on, gets a uniform p)
    temporal_reg: bool = True
    spatial_reg: bool = True
    separated_field: bool = True
    # the mask
    time_bins: int = 0            # 0: one column per distinct training time; else K evenly spaced bins
    # the mask at a time between two columns (never a training time when time_bins=0): linear = the
    # activated columns interpolated linearly (this implementation's choice; the paper does not say);
    # nearest = the nearer column's; logit = the logits interpolated, then activated. A render-time
    # choice: stdr-eval's `stdr.mask_between=...` re-evaluates a trained run with another
    mask_between: str = "linear"
    mask_init: Optional[float] = 2.0  # initial logit; null: sigmoid(o) * sigmoid(m) = model.init_opacity
    opacity_init: Optional[float] = None  # opacity held during the warm-up; null: model.init_opacity
    mask_lr: float = 0.05         # Adam lr of the mask logits (that of opacity logits)
    mask_after_freeze: bool = False  # false: from the freeze on the mask feeds only the separated field (true: it keeps multiplying opacity)
    prune_by_mask: bool = True    # prune on sigmoid(o) * max_t mask, the opacity a Gaussian reaches
    freeze_cleanup: float = 0.0   # at the freeze, switch off mask entries with sigmoid(o) * mask below this
    # 32: the mask stays float32 logits; 8: at the freeze it becomes uint8 round(255 sigmoid(m)) in memory,
    # checkpoints and model_mb, and renders read it directly (docs/compactness.md)
    mask_bits: int = 32
    # phases: static_warmup = the baseline's static warm-up (baseline.warmup) and twice it;
    # fraction = warmup_fraction / freeze_fraction of optim.iterations. Explicit steps win.
    phase_rule: str = "static_warmup"
    warmup_fraction: float = 0.075  # the paper's 3000 / 40000
    freeze_fraction: float = 0.15   # the paper's 6000 / 40000
    warmup_end: Optional[int] = None
    freeze_at: Optional[int] = None
    # true: the paper's text, opacity frozen in the warm-up. false (default): opacity trains with
    # the mask; on the val split it gained +0.83 dB over true (research/notes/2026-11-24-stdr-measurements.md, fidelity study, candidate 5)
    freeze_opacity: bool = False
    # regularizers
    lambda_temp: float = 0.1      # x L_temp = sum (or mean) over i, t of (mask_t - mask_{t+1})^2
    temporal_reduction: str = "mean"  # sum: the paper's formula; mean: divided by N(K-1)
    lambda_spatial: float = 0.2   # x mean KL(p_i || p_j) over sampled Gaussians and their KNN
    knn_samples: int = 1000
    knn_candidates: int = 20000
    knn_k: int = 5
    knn_every: int = 100          # resample queries and recompute neighbours (and after densification)
    # separated deformation field
    field_width: int = 64
    temporal_dim: int = 16
    dropout: float = 0.1
    field_pe_xyz: bool = False    # also feed PE(x) (baseline.xyz_freqs) to the field
    # the field's arithmetic: fp32; bf16 = products in bfloat16 and its fast batch norm and dropout
    # (field.py); auto = the deformation network's (baseline.precision as the run resolved it: bf16
    # for deform on a CPU with bf16 matrix instructions), and bf16 beside the fp32 networks of the
    # baselines where that was verified (plugin.FIELD_BF16_BESIDE_FP32) on such a CPU. A resumed
    # run keeps the arithmetic it trained with
    field_precision: str = "auto"
    # the field's own lr schedule: null follows the deformation network's (baseline.lr_*); a value
    # starts at the freeze (where the field starts training) and decays log-linearly to
    # field_lr_final (null: constant) at the end of the run
    field_lr_init: Optional[float] = None
    field_lr_final: Optional[float] = None
    scale_deltas_by_dynamic: bool = False  # multiply the deformation deltas by the dynamic probability


#: ablation switches and options whose non-default value tags a +STDR table row
ABLATION_SWITCHES = ("mask", "temporal_reg", "spatial_reg", "separated_field")
NON_DEFAULT_OPTIONS = {"mask_after_freeze": (True, "mask after freeze"),
                       "scale_deltas_by_dynamic": (True, "deltas x dynamic"),
                       "mask_bits": (8, "8-bit mask")}


def row_tags(pcfg: dict) -> list[str]:
    """'w/o <switch>' for each ablation switch that is off, and the label of each option at its
    non-default value (e.g. 'deform+STDR w/o spatial_reg'); `pcfg` is a run's stdr node as a dict."""
    tags = [f"w/o {k}" for k in ABLATION_SWITCHES if pcfg.get(k) is False]
    return tags + [label for k, (val, label) in NON_DEFAULT_OPTIONS.items() if pcfg.get(k) == val]
