"""Conventions shared by every rasterizer backend, and the :class:`RenderOutput` they return.

The backends follow gsplat's "classic" 3DGS rasterizer (``rasterization(...,
rasterize_mode="classic", eps2d=0.3)``) so that CPU and CUDA renders agree:

Projection (per Gaussian, camera with world-to-camera ``viewmat``, OpenCV axes):
    * ``p = R @ mean + t``; Gaussians with ``z <= near`` or ``z >= far`` are culled.
    * ``Sigma = R_q diag(s)^2 R_q^T`` with ``R_q`` from the *normalized* wxyz quaternion; a zero
      (or non-finite) quaternion is treated as the identity rotation (gradient zero).
    * EWA: ``cov2d = J R Sigma R^T J^T + 0.3 I`` with the perspective Jacobian
      ``J = [[fx/z, 0, -fx u/z], [0, fy/z, -fy v/z]]`` evaluated at ``u = x/z, v = y/z``
      clamped to the field of view enlarged by 30 % of the half-fov tangent on each side
      (gsplat's ``1.3 x`` limits: ``-(cx/fx + 0.3 tan_x) <= u <= (W-cx)/fx + 0.3 tan_x``,
      ``tan_x = W / (2 fx)``). No antialiasing compensation.
    * ``det(cov2d) <= 0`` culls; ``conic = cov2d^-1`` stored as (A, B, C) = (inv00, inv01, inv11).
    * ``means2d = (fx x/z + cx, fy y/z + cy)`` in pixels; pixel (x, y) has its centre at
      (x + 0.5, y + 0.5).
    * Extent (gsplat >= 1.5, "opacity-aware"): Gaussians with opacity < 1/255 are culled;
      ``extend = min(3.33, sqrt(2 ln(255 o)))``, ``radius_x = ceil(extend sqrt(cov2d_xx))``,
      ``radius_y = ceil(extend sqrt(cov2d_yy))``. This axis-aligned box contains every pixel
      centre where ``o exp(-power) >= 1/255``, so the tile binning never drops a pixel the
      compositing rule would keep (the reference backend checks this against a dense render).
      Gaussians whose box misses the image are culled. The reported ``radii`` [N] is
      ``max(radius_x, radius_y)`` (0 = culled).

Compositing (per pixel, Gaussians sorted front to back by camera z, ties by index):
    * ``power = 0.5 (A dx^2 + C dy^2) + B dx dy`` with ``(dx, dy) = means2d - pixel centre``;
    * ``alpha = min(0.999, o exp(-power))``; skip if ``power < 0`` or ``alpha < 1/255``;
    * stop the pixel when ``T (1 - alpha) <= 1e-4``; that Gaussian does *not* contribute;
    * ``image = sum_i c_i alpha_i T_i + T_final * background``, ``alpha_out = 1 - T_final``.

Tiles are 16 x 16 pixels.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np
import torch
from torch import Tensor

TILE_SIZE = 16
EPS2D = 0.3
CLIP_MARGIN = 0.3  # Jacobian clamp: 1.3 x the fov tangent limits
EXTEND_MAX = 3.33
# Thresholds as float32 values, so that the float32 CPU kernels and the (float64) reference
# compare against the very same numbers.
ALPHA_MIN = float(np.float32(1.0 / 255.0))
ALPHA_MAX = float(np.float32(0.999))
T_MIN = float(np.float32(1e-4))


@dataclass
class RenderOutput:
    """What :func:`baseline.render.rasterize` returns.

    Attributes:
        image: [H, W, C] rendered colours, ``sum_i c_i a_i T_i + T_final * background``.
        alpha: [H, W] accumulated opacity ``1 - T_final``.
        means2d: [N, 2] projected centres in *pixel* coordinates. After ``loss.backward()``
            its ``.grad`` holds dLoss/d(means2d) in pixel units (the densification code converts
            to NDC units itself by multiplying by (W/2, H/2)). Zero rows for culled Gaussians.
        radii: [N] int32 screen-space extent in pixels, ``max(radius_x, radius_y)``; 0 = culled.
        visible: [N] bool, ``radii > 0``.
        depths: [N] camera-space z of every Gaussian (not differentiable), or None.
        backend: name of the backend that rendered.
    """

    image: Tensor
    alpha: Tensor
    means2d: Tensor
    radii: Tensor
    visible: Tensor
    depths: Optional[Tensor] = None
    backend: str = ""
    extras: dict = field(default_factory=dict)


def check_inputs(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor,
                 colors: Tensor, camera, background: Optional[Tensor]) -> Tensor:
    """Validate shapes; returns the background [C] (zeros when None), on the colors' device."""
    if means.dim() != 2 or means.shape[-1] != 3:
        raise ValueError(f"means must be [N, 3], got {tuple(means.shape)}")
    n = means.shape[0]
    if quats.shape != (n, 4):
        raise ValueError(f"quats must be [N, 4] (wxyz) with N={n}, got {tuple(quats.shape)}")
    if scales.shape != (n, 3):
        raise ValueError(f"scales must be [N, 3] with N={n}, got {tuple(scales.shape)}")
    if opacities.shape != (n,):
        raise ValueError(f"opacities must be [N] with N={n}, got {tuple(opacities.shape)}")
    if colors.dim() != 2 or colors.shape[0] != n or colors.shape[1] < 1:
        raise ValueError(f"colors must be [N, C] with N={n}, C>=1, got {tuple(colors.shape)}")
    if int(camera.width) < 1 or int(camera.height) < 1:
        raise ValueError(f"camera size must be at least 1x1, got {camera.width}x{camera.height}")
    c = colors.shape[1]
    if background is None:
        background = torch.zeros(c, dtype=colors.dtype, device=colors.device)
    else:
        background = torch.as_tensor(background, dtype=colors.dtype, device=colors.device)
        if background.shape != (c,):
            raise ValueError(f"background must be [C] with C={c}, got {tuple(background.shape)}")
    return background
