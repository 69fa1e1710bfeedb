"""Deformation modules: one per baseline, all behind the interface in `base`."""
from __future__ import annotations

from .base import Deformation, Deltas, apply_post_activation, apply_pre_activation
from .deform3dgs import DeformMLP

REGISTRY = {"deform": DeformMLP}


def build_deformation(name: str, **kwargs) -> Deformation:
    if name not in REGISTRY:
        raise ValueError(f"baseline.name={name!r} is not one of {sorted(REGISTRY)}")
    return REGISTRY[name](**kwargs)


__all__ = ["Deformation", "Deltas", "DeformMLP", "REGISTRY", "build_deformation",
           "apply_post_activation", "apply_pre_activation"]
