"""Where each compiled form has been verified: the one table every `null` switch reads.

A key set to `null` (its default) takes the compiled form on a device listed here, and its torch
twin elsewhere; `true` insists, `false` refuses. The rule for adding a device
(docs/install.md, "When a compiled form becomes a default"):

* the CPU: its parity tests pass against the torch twin, and the suite trains with it;
* CUDA: on a GPU, (1) its parity tests pass (scripts/gpu_check.py's `kernels` stage), (2) the
  `binning_memcheck`, `train_keys` and `memcheck_keys` stages pass (the binning forced to disagree
  under compute-sanitizer memcheck; short trainings through prunes, opacity resets, evaluations
  and a guard recovery against the torch forms; one such run under memcheck), and (3) full
  `budget=gpu` runs with it complete for every seed of `CUDA_RUN_SEEDS`, their mean test PSNR
  within `CUDA_RUN_TOLERANCE_DB` of the same runs with the torch twin (`cuda_run_verdict`), all
  recorded under research/measurements (`EVIDENCE`). Parity on fixed sizes is not enough: the speed
  keys passed it on an H100 and a 20k-step run with them still crashed
  (research/notes/2026-11-27-gpu-crash.md).
"""
from __future__ import annotations

VERIFIED: dict[str, tuple[str, ...]] = {
    # the projection + SH kernels (stdr.render): CUDA on an H100 (parity with the twin,
    # the float64 truth and the CPU extension at 1M Gaussians; training and resume of all four
    # baselines with STDR; memcheck clean; nine budget=cpu D-NeRF runs), before the full-run rule
    "render.compiled_projection": ("cpu", "cuda"),
    # the photometric loss in one pass (stdr.metrics.fused_loss)
    "optim.fused_loss": ("cpu",),
    # the guard's step check as one call (stdr.train.guard.resolve_compiled_check)
    "train.guard.compiled": ("cpu",),
    # the guard's step check without a host sync (stdr.train.guard.resolve_sync_free)
    "train.guard.sync_free": ("cpu",),
    # 4dgs's HexPlane sampling (stdr.baselines.fourdgs.HexPlaneField.compiled_kind)
    "baseline.hexplane.compiled": ("cpu",),
    # the search behind baseline.<name>.knn=direct (stdr.knn.knn_direct): the kernel and its twin
    # give the same bits, so it is a speed choice only. CUDA has no kernel: it runs the twin
    "baseline.knn_compiled": ("cpu",),
}

#: what a CUDA entry rests on: the measurement folder (in research/measurements) with its records
EVIDENCE: dict[str, str] = {
    "render.compiled_projection": "gpu_check_h100_staged",
}

#: the largest test-PSNR gap (dB) between full budget=gpu runs with a compiled form and the same
#: runs with its torch twin, as means over CUDA_RUN_SEEDS, for the form to become a CUDA default
CUDA_RUN_TOLERANCE_DB = 0.2
#: the seeds of those runs: one pair cannot tell a form's cost from the GPU's run-to-run spread
#: (atomic adds), so the rule reads the mean of three (research/measurements/gpu_check_h200_keys)
CUDA_RUN_SEEDS = (0, 1, 2)


def cuda_run_verdict(compiled: dict[int, float], twin: dict[int, float]) -> dict:
    """Rule (3) on test PSNRs by seed: {"gap_db": mean(compiled) - mean(twin) over CUDA_RUN_SEEDS,
    "per_seed": {seed: gap}, "missing": seeds without both runs, "passes": no seed missing and
    |gap| <= CUDA_RUN_TOLERANCE_DB}. gap_db is None while a seed is missing."""
    missing = [s for s in CUDA_RUN_SEEDS if s not in compiled or s not in twin]
    per_seed = {s: compiled[s] - twin[s] for s in CUDA_RUN_SEEDS if s in compiled and s in twin}
    gap = None if missing else sum(per_seed.values()) / len(per_seed)
    return {"gap_db": gap, "per_seed": per_seed, "missing": missing,
            "passes": gap is not None and abs(gap) <= CUDA_RUN_TOLERANCE_DB}


def verified_on(key: str) -> tuple[str, ...]:
    """The device types where `key`'s compiled form is verified (an unknown key is an error)."""
    try:
        return VERIFIED[key]
    except KeyError:
        raise KeyError(f"{key!r} has no entry in stdr.verified.VERIFIED; known: {', '.join(VERIFIED)}") from None
