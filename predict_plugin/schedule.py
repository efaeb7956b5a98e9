"""Prediction-tailored progressive training: the downsampling schedule (paper eq. 6).

    delta_t = d_e + 0.5 (d_s - d_e) (1 + cos(pi t / T)),   t in [0, T]; full resolution after T.

``linear`` interpolates d_s -> d_e over the same span; ``none`` keeps d_s fixed until the
residual branch starts and then jumps to full resolution (the paper's "Non" row of Table 6).
"""
from __future__ import annotations

import math


def downsample_scale(t: int, schedule: str, d_s: float, d_e: float, T: int,
                     stage2_from: int = 0) -> float:
    """Scale factor of the training view at iteration ``t`` (all in this run's iterations)."""
    if schedule == "cosine":
        if t >= T:
            return d_e
        return d_e + 0.5 * (d_s - d_e) * (1.0 + math.cos(math.pi * t / T))
    if schedule == "linear":
        if t >= T:
            return d_e
        return d_s + (d_e - d_s) * t / T
    if schedule == "none":
        return d_s if t < stage2_from else d_e
    raise ValueError(f"unknown progressive schedule '{schedule}' (cosine, linear, none)")
