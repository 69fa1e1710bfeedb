"""Where each compiled form has been verified: the one table every `null` switch reads.

A key set to `null` (its default) takes the compiled form on a device listed here, and its torch
twin elsewhere; `true` insists, `false` refuses. The rule for adding a device
(docs/install.md, "When a compiled form becomes a default"):

* the CPU: its parity tests pass against the torch twin, and the suite trains with it;
* CUDA: on a GPU, (1) its parity tests pass (scripts/gpu_check.py's `kernels` stage), (2) the
  `train_keys` stage passes (the binning forced to disagree and short trainings through prunes,
  opacity resets, evaluations and a guard recovery, all under compute-sanitizer memcheck), and
  (3) a full `budget=gpu` run with it completes within `CUDA_RUN_TOLERANCE_DB` of the same run
  with the torch twin, both runs recorded under docs/measurements (`EVIDENCE`). Parity on fixed
  sizes is not enough: the speed keys passed it on an H100 and a 20k-step run with them still
  crashed (docs/notes/2026-11-27-gpu-crash.md).
"""
from __future__ import annotations

VERIFIED: dict[str, tuple[str, ...]] = {
    # the projection + SH kernels (stdr.render): CUDA on an H100 on 2026-11-26 (parity with the twin,
    # the float64 truth and the CPU extension at 1M Gaussians; training and resume of all four
    # baselines with STDR; memcheck clean; nine budget=cpu D-NeRF runs), before the full-run rule
    "render.compiled_projection": ("cpu", "cuda"),
    # the photometric loss in one pass (stdr.metrics.fused_loss)
    "optim.fused_loss": ("cpu",),
    # the guard's step check as one call (stdr.train.guard.resolve_compiled_check)
    "train.guard.compiled": ("cpu",),
    # the guard's step check without a host sync (stdr.train.guard.resolve_sync_free)
    "train.guard.sync_free": ("cpu",),
    # 4dgs's HexPlane sampling (stdr.baselines.hexplane.HexPlaneField.compiled_kind)
    "baseline.hexplane.compiled": ("cpu",),
}

#: what a CUDA entry rests on: the measurement folder (in docs/measurements) with its records
EVIDENCE: dict[str, str] = {
    "render.compiled_projection": "gpu_check_h100_staged",
}

#: the largest test-PSNR gap (dB) between a full budget=gpu run with a compiled form and the same
#: run with its torch twin for the form to become a CUDA default
CUDA_RUN_TOLERANCE_DB = 0.2


def verified_on(key: str) -> tuple[str, ...]:
    """The device types where `key`'s compiled form is verified (an unknown key is an error)."""
    try:
        return VERIFIED[key]
    except KeyError:
        raise KeyError(f"{key!r} has no entry in stdr.verified.VERIFIED; known: {', '.join(VERIFIED)}") from None
