"""The `device` config key: where a run's tensors live."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Optional

import torch


def resolve_device(name: str) -> torch.device:
    """`auto` = the current CUDA device when torch sees one, else the CPU; otherwise a torch
    device name (`cpu`, `cuda`, `cuda:1`). Asking for CUDA where torch has none is an error that
    says why, never a silent fall back to the CPU."""
    name = str(name).strip()
    if name == "auto":
        return torch.device("cuda", torch.cuda.current_device()) if torch.cuda.is_available() else torch.device("cpu")
    try:
        dev = torch.device(name)
    except RuntimeError as e:
        raise ValueError(f"device={name!r} is not a torch device name ({e}); use auto, cpu, cuda or cuda:<index>") \
            from None
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            why = ("this torch is a CPU-only build" if torch.version.cuda is None
                   else f"torch (CUDA {torch.version.cuda}) sees no GPU: check the driver and CUDA_VISIBLE_DEVICES")
            raise ValueError(f"device={name}: {why}. Use device=cpu or device=auto; README 'Training on a GPU' says "
                             "how to install a CUDA build of torch")
        index = torch.cuda.current_device() if dev.index is None else dev.index
        if index >= torch.cuda.device_count():
            raise ValueError(f"device={name}: only {torch.cuda.device_count()} CUDA device(s) visible")
        return torch.device("cuda", index)
    if dev.type != "cpu":
        raise ValueError(f"device={name}: only cpu and cuda are supported (the rasterizer has no {dev.type} backend)")
    return dev


#: the CPU flags (Linux /proc/cpuinfo names) of matrix instructions that multiply in bfloat16
BF16_CPU_FLAGS = ("avx512_bf16", "amx_bf16")


def cpu_bf16_flags(cpuinfo: str | Path = "/proc/cpuinfo") -> tuple[str, ...]:
    """Which of BF16_CPU_FLAGS this CPU has (AVX512-BF16: AMD Zen 4 and later, Intel Cooper Lake and
    Sapphire Rapids; AMX-BF16: Intel Sapphire Rapids and later). Empty where the CPU has neither,
    or where /proc/cpuinfo cannot be read (not Linux): torch then emulates bfloat16 products, and
    they run slower than fp32."""
    try:
        text = Path(cpuinfo).read_text(errors="replace")
    except OSError:
        return ()
    flags: set[str] = set()
    for line in text.splitlines():
        if line.startswith("flags"):
            flags.update(line.partition(":")[2].split())
    return tuple(f for f in BF16_CPU_FLAGS if f in flags)


def emulated_bf16_note(key: str) -> str:
    """The one line for an explicit `key=bf16` on a CPU without bf16 matrix instructions."""
    return (f"{key}=bf16 on a CPU without AVX512-BF16 or AMX: bfloat16 products are emulated here and run "
            "slower than fp32")


def synchronize(device: torch.device) -> None:
    """Wait for queued kernels on `device` (for timings); a no-op on the CPU."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def process_memory_mb(device: torch.device) -> Optional[float]:
    """The training's memory now, in MiB: on CUDA the peak torch allocated on `device` since the
    run reset it (Trainer.train); elsewhere the process's resident set (Linux /proc/self/statm),
    which also holds what earlier runs of the same process (an in-process multirun) left behind.
    None where neither can be read."""
    if device.type == "cuda":
        return torch.cuda.max_memory_allocated(device) / 2**20
    try:
        pages = int(Path("/proc/self/statm").read_text().split()[1])  # [1]: resident pages
        return pages * os.sysconf("SC_PAGE_SIZE") / 2**20
    except (OSError, ValueError, IndexError, AttributeError):
        return None


MEMORY_CONVENTION = {"cuda": "torch.cuda.max_memory_allocated since the run began",
                     "cpu": "resident set of the process (/proc/self/statm), sampled every train.log_every steps"}


def available_bytes(device: torch.device) -> Optional[int]:
    """Memory a run on `device` can still take: a CUDA device's free memory, else the host's
    MemAvailable (/proc/meminfo); None where it cannot be read."""
    if device.type == "cuda":
        try:
            return int(torch.cuda.mem_get_info(device)[0])
        except (RuntimeError, AssertionError):
            return None
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None
