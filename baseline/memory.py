"""Allocation failures as named errors.

PyTorch reports a failed CPU allocation as a ``RuntimeError`` ("DefaultCPUAllocator: can't
allocate memory: you tried to allocate N bytes"), a CUDA one as ``torch.OutOfMemoryError`` (a
``RuntimeError``), NumPy as a ``MemoryError`` naming the size, and Python as a bare
``MemoryError``. :func:`allocating` turns each, raised inside its block, into one
:class:`AllocationError` line: what was being allocated, the size of the allocation that failed
(where the library reports it), the plan and its budget where the caller has them, and what
this process may use (its address-space limit, the memory the machine has available, or the
GPU's free memory). Any other error passes through unchanged, so "internal error" stays
reserved for bugs.
"""
from __future__ import annotations

import re
from collections.abc import Iterator
from contextlib import contextmanager

_ALLOC_MARKERS = ("can't allocate memory", "out of memory", "not enough memory",
                  "cannot allocate memory", "failed to allocate", "bad_alloc")
_SIZE = re.compile(r"(?:tried to allocate|unable to allocate)\s+([0-9.]+\s*(?:bytes|[kmgtp]i?b))",
                   re.IGNORECASE)
_UNITS = {"bytes": 1, "b": 1, "kb": 1e3, "mb": 1e6, "gb": 1e9, "tb": 1e12, "pb": 1e15,
          "kib": 2 ** 10, "mib": 2 ** 20, "gib": 2 ** 30, "tib": 2 ** 40, "pib": 2 ** 50}


class AllocationError(MemoryError):
    """An allocation failed; the message names what, its size and the budget."""


def is_allocation_failure(e: BaseException) -> bool:
    """A ``MemoryError``, or a ``RuntimeError`` a library raised for a failed allocation."""
    if isinstance(e, MemoryError):
        return True
    return isinstance(e, RuntimeError) and any(m in str(e).lower() for m in _ALLOC_MARKERS)


def failed_size(e: BaseException) -> int | None:
    """Bytes of the failed allocation, when the message reports them."""
    m = _SIZE.search(str(e))
    if not m:
        return None
    num, unit = re.match(r"([0-9.]+)\s*(\S+)", m.group(1)).groups()
    try:
        return int(float(num) * _UNITS[unit.lower()])
    except (KeyError, ValueError):
        return None


def mib(n: float) -> str:
    return f"{n / 2 ** 20:,.0f} MiB"


def process_limit(device: str = "cpu") -> str:
    """What this process may allocate, in words: the GPU's free memory, or the address-space
    limit and the machine's available memory."""
    if device.startswith("cuda"):
        try:
            import torch

            free, total = torch.cuda.mem_get_info(torch.device(device))
            return f"{mib(free)} free of the GPU's {mib(total)}"
        except Exception:                            # noqa: BLE001 - a description only
            return "the GPU's memory"
    parts = []
    try:
        import resource

        soft, _ = resource.getrlimit(resource.RLIMIT_AS)
        if soft != resource.RLIM_INFINITY:
            parts.append(f"an address-space limit of {mib(soft)}")
    except (ImportError, OSError, ValueError):
        pass
    try:
        with open("/proc/meminfo", encoding="ascii") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    parts.append(f"{mib(int(line.split()[1]) * 1024)} available on this machine")
                    break
    except (OSError, ValueError, IndexError):
        pass
    return " and ".join(parts) or "this machine's memory"


def describe(what: str, e: BaseException, planned: int | None = None,
             budget: int | None = None, budget_name: str = "",
             device: str = "cpu") -> str:
    size = failed_size(e)
    head = f"out of memory {what}: " + (f"an allocation of {mib(size)} failed"
                                        if size is not None else "an allocation failed")
    plan = ""
    if planned is not None:
        plan = f"; about {mib(planned)} planned"
        if budget is not None:
            plan += f" within the {mib(budget)} budget" + (f" ({budget_name})" if budget_name else "")
    return f"{head}{plan}; this process has {process_limit(device)}"


@contextmanager
def allocating(what: str, *, planned: int | None = None, budget: int | None = None,
               budget_name: str = "", device: str = "cpu") -> Iterator[None]:
    """Raise an allocation failure inside the block as one :class:`AllocationError` naming
    ``what`` ("decoding F.pgs (N anchors)"), the failed size, ``planned`` bytes against
    ``budget`` (named ``budget_name``, e.g. the variable that raises it) and the process's
    limit. Other errors pass through."""
    try:
        yield
    except AllocationError:
        raise
    except (MemoryError, RuntimeError) as e:
        if not is_allocation_failure(e):
            raise
        raise AllocationError(describe(what, e, planned, budget, budget_name, device)) from None
