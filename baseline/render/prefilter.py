"""Visible-anchor prefilter (SPEC section 2).

Each anchor is projected as a Gaussian with identity rotation and the given scales (the
first three of exp(scaling)). An anchor is visible when

* its camera-space z is > 0.2 (a fixed threshold, as Scaffold-GS; independent of camera.near),
* its EWA 2D covariance, *after* the 0.3 px^2 diagonal dilation, has det > 0 (always true for
  finite inputs: the dilation makes it positive definite; what this rejects in practice is
  non-finite values), and
* its 3-sigma box overlaps the image: with ``r = ceil(3 sqrt(lambda_max))`` pixels
  (``lambda_max`` the larger eigenvalue of the dilated 2D covariance, as the original 3DGS
  rasterizer's ``markVisible``), the square ``[mx - r, mx + r] x [my - r, my + r]`` must
  overlap ``[0, W] x [0, H]`` (strictly, on pixel coordinates rather than 16-pixel tiles).

The projection uses the same clamped Jacobian as the rasterizer. Computed in float64 without
gradients.
"""
from __future__ import annotations

import torch
from torch import Tensor

from .reference import ewa_cov2d

Z_MIN = 0.2


@torch.no_grad()
def prefilter_anchors(xyz: Tensor, scales: Tensor, camera, z_min: float = Z_MIN) -> Tensor:
    """Which anchors can touch the image.

    Args:
        xyz: [N, 3] anchor positions (world).
        scales: [N, 3] positive scales (activated) of the anchor-sized Gaussian.
        camera: :class:`baseline.camera.Camera`.
        z_min: camera-space depth threshold (0.2).
    Returns:
        [N] bool visibility mask, on xyz's device.
    """
    if xyz.dim() != 2 or xyz.shape[-1] != 3 or scales.shape != xyz.shape:
        raise ValueError(f"xyz and scales must both be [N, 3], got {tuple(xyz.shape)} and "
                         f"{tuple(scales.shape)}")
    dt = torch.float64
    x = xyz.to(dt)
    vm = camera.viewmat.to(x.device, dt)
    R, t = vm[:3, :3], vm[:3, 3]
    p = x @ R.T + t
    z = p[:, 2]
    z_ok = z > z_min
    p_safe = torch.where(z_ok[:, None], p, torch.ones_like(p))
    s2 = scales.to(dt) ** 2
    cov_cam = (R[None] * s2[:, None, :]) @ R.T  # R diag(s^2) R^T
    cov2d = ewa_cov2d(p_safe, cov_cam, camera)
    a, b, c = cov2d[:, 0, 0], cov2d[:, 0, 1], cov2d[:, 1, 1]
    det = a * c - b * b
    finite = torch.isfinite(cov2d).flatten(1).all(1) & torch.isfinite(det)
    ok = z_ok & finite & (det > 0)
    mid = 0.5 * (a + c)
    lam_max = mid + torch.sqrt(torch.clamp(mid * mid - det, min=0.1))
    r = torch.ceil(3.0 * torch.sqrt(torch.where(ok, lam_max, torch.ones_like(lam_max))))
    mx = camera.fx * p_safe[:, 0] / p_safe[:, 2] + camera.cx
    my = camera.fy * p_safe[:, 1] / p_safe[:, 2] + camera.cy
    overlap = (mx + r > 0) & (mx - r < camera.width) & (my + r > 0) & (my - r < camera.height)
    return ok & overlap
