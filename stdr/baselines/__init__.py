"""Deformation modules: one per baseline, all behind the interface in `base`, listed in one
registry (`registry.BASELINES`: name -> module and config dataclass)."""
from __future__ import annotations

from .base import BaselineConfig, Deformation, Deltas, apply_post_activation, apply_pre_activation
from .scgs import ControlNodeDeformation, ScgsBaselineConfig, ScgsConfig
from .deform import DeformConfig, DeformMLP
from .fourdgs import HexPlaneBaselineConfig, HexPlaneConfig, HexPlaneDeformation, hexplane_time_res
from .registry import BASELINES, BaselineSpec, build_deformation, get_baseline, register_baseline, unregister_baseline
from .spgs import SpgsBaselineConfig, SpgsConfig, SuperpointDeformation

__all__ = ["Deformation", "Deltas", "BaselineConfig", "DeformMLP", "ControlNodeDeformation", "SuperpointDeformation",
           "HexPlaneDeformation", "DeformConfig", "ScgsBaselineConfig", "ScgsConfig", "SpgsBaselineConfig",
           "SpgsConfig", "HexPlaneBaselineConfig", "HexPlaneConfig", "BASELINES", "BaselineSpec", "build_deformation",
           "get_baseline", "register_baseline", "unregister_baseline", "hexplane_time_res",
           "apply_post_activation", "apply_pre_activation"]
