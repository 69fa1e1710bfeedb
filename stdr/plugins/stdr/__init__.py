"""STDR (spatio-temporal decoupling): the mask, its phases and regularizers, the separated field."""
from __future__ import annotations

from .. import register_plugin
from .settings import StdrConfig, row_tags
from .field import SeparatedField
from .mask import MASK_KEY, interp_weights, knot_times, mask_at, sample_neighbours, spatial_kl, temporal_entropy, temporal_loss
from .phases import Phase, phase_at, resolve_phases
from .plugin import STDR

# the separated field's output feeds the baseline's network: a baseline that takes conditioning
register_plugin("stdr", STDR, StdrConfig, label="+STDR", row_tags=row_tags,
                requires=lambda node: ("conditioning",) if node.separated_field else (), in_grids=True,
                removed_keys=("static_skip",))  # a render-time key that no longer exists (docs/stdr.md)

__all__ = ["MASK_KEY", "STDR", "StdrConfig", "Phase", "SeparatedField", "interp_weights", "knot_times", "mask_at",
           "phase_at", "resolve_phases", "sample_neighbours", "spatial_kl", "temporal_entropy",
           "temporal_loss"]
