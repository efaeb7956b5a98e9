"""Where a training step's time goes: named stages, off unless a bench turns them on.

The training code marks its stages with ``with stage("name"):`` (forward work, the optimizer,
hooks) and, for the backward pass, tensors whose gradient arrival ends a stage with
``backward_mark(tensor, "name")``: autograd computes gradients in reverse order of creation,
so the time from the start of ``backward()`` to the first gradient of the rendered image is the
losses' backward, from there to the rasterizer's inputs the rasterizer's, and so on.

Without an active :class:`StageTimer` both are a check of one global and nothing else. With one,
``pgs bench train`` reads per step ``{stage: seconds}``; stages may nest (a parent's time includes
its children's).
"""
from __future__ import annotations

import time
from contextlib import contextmanager
from typing import Optional

_ACTIVE: Optional["StageTimer"] = None
_CLOCK = time.perf_counter


def now() -> float:
    """The stage clock's reading (seconds)."""
    return _CLOCK()


@contextmanager
def clock(fn):
    """Time stages with ``fn`` (e.g. ``time.process_time``) inside the block."""
    global _CLOCK
    prev, _CLOCK = _CLOCK, fn
    try:
        yield
    finally:
        _CLOCK = prev


class StageTimer:
    def __init__(self):
        self.times: dict[str, float] = {}
        self._bwd_start: Optional[float] = None
        self._bwd_marks: list[tuple[float, str]] = []

    def add(self, name: str, dt: float) -> None:
        self.times[name] = self.times.get(name, 0.0) + dt

    def backward_started(self) -> None:
        self._bwd_start = _CLOCK()
        self._bwd_marks = []

    def backward_finished(self) -> None:
        """Split the backward pass at the recorded gradient arrivals: each mark's stage runs from
        the previous mark (or the start) to it; the rest after the last mark is 'rest bwd'."""
        end = _CLOCK()
        if self._bwd_start is None:
            return
        prev = self._bwd_start
        seen = set()
        for t, name in sorted(self._bwd_marks):
            if name in seen:
                continue
            seen.add(name)
            self.add(name, max(0.0, t - prev))
            prev = max(prev, t)
        self.add("rest bwd", max(0.0, end - prev))
        self.add("backward", end - self._bwd_start)
        self._bwd_start = None

    def mark(self, name: str) -> None:
        self._bwd_marks.append((_CLOCK(), name))


def active() -> Optional[StageTimer]:
    return _ACTIVE


@contextmanager
def timing(timer: StageTimer):
    """Activate ``timer`` for the block (one at a time)."""
    global _ACTIVE
    prev, _ACTIVE = _ACTIVE, timer
    try:
        yield timer
    finally:
        _ACTIVE = prev


@contextmanager
def stage(name: str):
    t = _ACTIVE
    if t is None:
        yield
        return
    t0 = _CLOCK()
    try:
        yield
    finally:
        t.add(name, _CLOCK() - t0)


def backward_mark(tensor, name: str) -> None:
    """When timing, record the moment ``tensor``'s gradient is computed as the end of ``name``
    (its first arrival counts)."""
    t = _ACTIVE
    if t is None or tensor is None or not getattr(tensor, "requires_grad", False):
        return

    def hook(grad):
        t.mark(name)
        return None

    tensor.register_hook(hook)
