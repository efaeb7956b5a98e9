"""Where tensors live: the run's device (``train.device``) and random draws that follow it.

Training runs on one device: the CPU (numba rasterizer and hash-grid kernels) or a CUDA GPU
(gsplat rasterizer, PyTorch hash grid). The codec always runs on the CPU: its probabilities come
from a float64 path that must give the same bits on the encoder's and the decoder's machine, so
a file written after GPU training decodes exactly anywhere.
"""
from __future__ import annotations

from typing import Optional

import torch


class DeviceError(ValueError):
    """A device that cannot be used here (the message says why and what to do instead)."""


def resolve_device(name: str = "auto") -> torch.device:
    """``auto`` -> ``cuda`` when this PyTorch sees a GPU, else ``cpu``; ``cpu``, ``cuda``,
    ``cuda:N`` as given, checked against what is there (a clear error, not a crash later)."""
    if name in ("", "auto"):
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(name)
    except RuntimeError:
        raise DeviceError(f"unknown device '{name}': use auto, cpu, cuda or cuda:N") from None
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise DeviceError(
                f"device '{name}' was asked for, but this PyTorch ({torch.__version__}, CUDA "
                f"{torch.version.cuda}) sees no CUDA GPU: install a CUDA build of torch, or use "
                f"--set train.device=cpu")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise DeviceError(f"device '{name}': only {torch.cuda.device_count()} CUDA GPU(s) here")
    elif dev.type != "cpu":
        raise DeviceError(f"device '{name}': only cpu and cuda are supported")
    return dev


def device_name(dev: torch.device) -> str:
    """A human-readable name for reports: the GPU's model, or ``cpu``."""
    if dev.type == "cuda":
        return f"{dev} ({torch.cuda.get_device_name(dev)})"
    return "cpu"


def machine_name(dev: torch.device) -> str:
    """The machine a run's time was taken on, for its record: the GPU's model on CUDA; on the
    CPU the processor's model and its logical CPU count, e.g. ``AMD EPYC 7B13 (2 CPUs)``.

    Two runs' times compare only when this is the same (it cannot tell two hosts of one model
    apart, nor their load: stall time covers the part of that a run can see).
    """
    import os
    import platform

    if dev.type == "cuda":
        return torch.cuda.get_device_name(dev)
    model = ""
    try:        # Linux: the model string; platform.processor() there is only "x86_64"
        for line in open("/proc/cpuinfo", encoding="utf-8", errors="replace"):
            if line.lower().startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    model = " ".join(model.split()) or platform.processor() or platform.machine() or "cpu"
    return f"{model} ({os.cpu_count()} CPUs)"


def make_generator(seed: int, device: torch.device) -> torch.Generator:
    """A generator on ``device`` (draws then happen where the tensors are, no transfer)."""
    return torch.Generator(device=device).manual_seed(seed)


def uniform(shape, generator: Optional[torch.Generator], device: torch.device | str,
            dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """U[0, 1) draws of ``shape`` on ``device``, from ``generator`` (None: the global one).

    Drawn on the generator's own device, moved only when that differs from ``device``, so CPU
    runs draw exactly what they drew before device support existed.
    """
    device = torch.device(device)
    if generator is None:
        return torch.rand(shape, device=device, dtype=dtype)
    g_dev = generator.device
    if g_dev.type == device.type and (g_dev.index or 0) == (device.index or 0):
        return torch.rand(shape, generator=generator, device=device, dtype=dtype)
    return torch.rand(shape, generator=generator, device=g_dev, dtype=dtype).to(device)


_ALLOCATOR_TUNED = False


def keep_freed_memory() -> bool:
    """Let glibc's allocator keep the memory a training step frees for the next step.

    A step allocates and frees the same large tensors (gradients, activations of ~100k
    anchors) every iteration. glibc returns blocks above its mmap threshold to the kernel when
    they are freed, so the next step maps and faults them in again: on a truck training that
    was measured at 50 ms of system time per step (of ~900), 7 ms with these settings. Blocks
    up to 32 MiB (glibc's largest mmap threshold) then come from the heap, and the heap is not
    trimmed below 1 GiB of free space. Values and results are unchanged: only where memory
    comes from. A no-op where the C library is not glibc; once per process."""
    global _ALLOCATOR_TUNED
    if _ALLOCATOR_TUNED:
        return True
    import ctypes
    import ctypes.util

    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    M_TRIM_THRESHOLD, M_TOP_PAD, M_MMAP_THRESHOLD = -1, -2, -3
    ok = (mallopt(M_MMAP_THRESHOLD, 32 << 20) == 1 and mallopt(M_TRIM_THRESHOLD, 1 << 30) == 1
          and mallopt(M_TOP_PAD, 256 << 20) == 1)
    _ALLOCATOR_TUNED = ok
    return ok


def code_version() -> str:
    """The code a run's time was taken with, for its record: the git commit of the checkout
    the ``baseline`` package is imported from (12 hex digits, ``+modified`` when its tracked
    files differ from that commit), else ``pgs VERSION`` (an installed wheel).

    Two runs' times compare only when this is the same: a same-numbers speed-up changes no
    result, so only this tells which code a training time measures.
    """
    import subprocess
    from pathlib import Path

    import baseline

    root = Path(baseline.__file__).resolve().parent.parent
    try:
        def git(*args):
            return subprocess.run(["git", "-C", str(root), *args], capture_output=True,
                                  text=True, timeout=20, check=True).stdout.strip()

        if Path(git("rev-parse", "--show-toplevel")).resolve() != root:
            raise ValueError("the package is not at the top of a checkout")
        commit = git("rev-parse", "--short=12", "HEAD")
        modified = git("status", "--porcelain", "--untracked-files=no")
        return commit + ("+modified" if modified else "")
    except (OSError, ValueError, subprocess.SubprocessError):
        return f"pgs {baseline.__version__}"

