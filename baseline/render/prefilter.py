"""Visible-anchor prefilter (docs/method.md section 2).

Each anchor is projected as a Gaussian with identity rotation and the given scales (the
first three of exp(scaling)). An anchor is visible when

* its camera-space z is > ``camera.near`` (0.2 by default, ``data.near``: Scaffold-GS and HAC
  cull anchors and Gaussians at the same depth),
* its EWA 2D covariance, *after* the 0.3 px^2 diagonal dilation, has det > 0 (true in exact
  arithmetic: the dilation makes it positive definite; what this rejects in practice is
  non-finite values, and scales so large, ~1e38, that ``a c - b^2`` cancels to <= 0), and
* its 3-sigma box overlaps the image: with ``r = ceil(3 sqrt(lambda_max))`` pixels
  (``lambda_max`` the larger eigenvalue of the dilated 2D covariance, as the original 3DGS
  rasterizer's ``markVisible``), the square ``[mx - r, mx + r] x [my - r, my + r]`` must
  overlap ``[0, W] x [0, H]`` (strictly, on pixel coordinates rather than 16-pixel tiles).

The projection uses the same clamped Jacobian as the rasterizer. Computed in float64 without
gradients: two small matrix products in torch, then the test itself, as torch operations on
other devices and as one numba loop over the anchors on the CPU (the same operations in the
same order, so the same decisions).
"""
from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from .conventions import CLIP_MARGIN, EPS2D

Z_MIN = 0.2  # the default near plane (baseline.camera.Camera.near)


@torch.no_grad()
def prefilter_anchors(xyz: Tensor, scales: Tensor, camera, z_min: float | None = None) -> Tensor:
    """Which anchors can touch the image.

    Args:
        xyz: [N, 3] anchor positions (world).
        scales: [N, 3] positive scales (activated) of the anchor-sized Gaussian.
        camera: :class:`baseline.camera.Camera`.
        z_min: camera-space depth threshold; None: ``camera.near`` (0.2 by default).
    Returns:
        [N] bool visibility mask, on xyz's device.
    """
    if xyz.dim() != 2 or xyz.shape[-1] != 3 or scales.shape != xyz.shape:
        raise ValueError(f"xyz and scales must both be [N, 3], got {tuple(xyz.shape)} and "
                         f"{tuple(scales.shape)}")
    p, cov, terms = _camera_space(xyz, scales, camera, z_min)
    if p.device.type == "cpu":
        # One fused pass instead of ~60 torch ops over [N] float64 arrays (about 4x faster at
        # truck's 165k anchors: docs/RESULTS.md, "Speed (CPU)"): the same IEEE operations in
        # the same order, with no FMA contraction, so the same decisions bit for bit (tests
        # compare it with the torch form on hostile inputs).
        out = np.empty(p.shape[0], dtype=np.bool_)
        _visible_kernel(p.numpy(), cov.numpy(), *terms, out)
        return torch.from_numpy(out)
    return _visible_torch(p, cov, *terms)


def _camera_space(xyz: Tensor, scales: Tensor, camera, z_min: float | None):
    """float64 camera-space centres ``p`` [N,3], the six distinct entries of the camera-space
    covariances ``cov`` [N,6], and the camera's scalars for the visibility test (near, fx, fy,
    cx, cy, width, height, and the Jacobian's clamp of x/z and y/z: lo, hi, lo, hi)."""
    dt = torch.float64
    x = xyz.to(dt)
    vm = camera.viewmat.to(x.device, dt)
    R, t = vm[:3, :3], vm[:3, 3]
    p = (x @ R.T + t).contiguous()
    # Written out element by element rather than as [N,3,3] / [N,2,3] batched products (which
    # torch runs as N tiny matrix products: ~40 ms for 165k anchors on one core, most of a
    # decoded frame's prefilter). cov_cam = R diag(s^2) R^T, as its six distinct entries from
    # one [N,3] x [3,6] product; then J cov_cam J^T (+ eps2d I) with gsplat's clamped Jacobian
    # J = [[fx/z, 0, -fx u/z], [0, fy/z, -fy v/z]], exactly ewa_cov2d's (tests compare them).
    s2 = scales.to(dt) ** 2
    ii, jj = (0, 0, 0, 1, 1, 2), (0, 1, 2, 1, 2, 2)
    A = torch.stack([R[list(ii), k] * R[list(jj), k] for k in range(3)])   # [3,6]
    cov = (s2 @ A).contiguous()
    fx, fy, cx, cy = float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy)
    w, h = float(camera.width), float(camera.height)
    tan_x, tan_y = 0.5 * w / fx, 0.5 * h / fy
    near = float(camera.near) if z_min is None else float(z_min)
    return p, cov, (near, fx, fy, cx, cy, w, h,
                    -(cx / fx + CLIP_MARGIN * tan_x), (w - cx) / fx + CLIP_MARGIN * tan_x,
                    -(cy / fy + CLIP_MARGIN * tan_y), (h - cy) / fy + CLIP_MARGIN * tan_y)


def _visible_torch(p: Tensor, cov: Tensor, near: float, fx: float, fy: float, cx: float,
                   cy: float, w: float, h: float, lox: float, hix: float, loy: float,
                   hiy: float) -> Tensor:
    """The visibility test of :func:`prefilter_anchors` from camera-space centres ``p`` [N,3]
    and covariance entries ``cov`` [N,6] (float64) as torch ops: any device."""
    z_ok = p[:, 2] > near
    p_safe = torch.where(z_ok[:, None], p, torch.ones_like(p))
    c00, c01, c02, c11, c12, c22 = cov.unbind(-1)
    px, py, pz = p_safe.unbind(-1)
    u = (px / pz).clamp(lox, hix)
    v = (py / pz).clamp(loy, hiy)
    j1, j3 = fx / pz, -fx * u / pz
    k2, k3 = fy / pz, -fy * v / pz
    a = j1 * j1 * c00 + 2 * j1 * j3 * c02 + j3 * j3 * c22 + EPS2D
    b = j1 * k2 * c01 + j1 * k3 * c02 + j3 * k2 * c12 + j3 * k3 * c22
    c = k2 * k2 * c11 + 2 * k2 * k3 * c12 + k3 * k3 * c22 + EPS2D
    det = a * c - b * b
    finite = torch.isfinite(a) & torch.isfinite(b) & torch.isfinite(c) & torch.isfinite(det)
    ok = z_ok & finite & (det > 0)
    mid = 0.5 * (a + c)
    lam_max = mid + torch.sqrt(torch.clamp(mid * mid - det, min=0.1))
    r = torch.ceil(3.0 * torch.sqrt(torch.where(ok, lam_max, torch.ones_like(lam_max))))
    mx = fx * px / pz + cx
    my = fy * py / pz + cy
    overlap = (mx + r > 0) & (mx - r < w) & (my + r > 0) & (my - r < h)
    return ok & overlap


_compiled_loop = None


def _visible_kernel(p, cov, near, fx, fy, cx, cy, w, h, lox, hix, loy, hiy, out) -> None:
    """:func:`_visible_loop` compiled by numba, which is imported and compiles it (or loads it
    from its disk cache) on the first call, as the rasterizer's kernels are: importing the
    package does not import numba."""
    global _compiled_loop
    if _compiled_loop is None:
        from numba import njit

        _compiled_loop = njit(cache=True, error_model="numpy")(_visible_loop)
    _compiled_loop(p, cov, near, fx, fy, cx, cy, w, h, lox, hix, loy, hiy, out)


def _visible_loop(p, cov, near, fx, fy, cx, cy, w, h, lox, hix, loy, hiy, out):
    """:func:`_visible_torch` point by point (NumPy float64 arrays, ``out`` [N] bool). Each
    line is the torch form's expression in its order; comparisons are written so that NaN
    passes through the clamps as torch.clamp passes it."""
    for i in range(p.shape[0]):
        z_ok = p[i, 2] > near
        px, py, pz = (p[i, 0], p[i, 1], p[i, 2]) if z_ok else (1.0, 1.0, 1.0)
        c00, c01, c02, c11, c12, c22 = cov[i, 0], cov[i, 1], cov[i, 2], cov[i, 3], cov[i, 4], cov[i, 5]
        u = px / pz
        u = lox if u < lox else (hix if u > hix else u)
        v = py / pz
        v = loy if v < loy else (hiy if v > hiy else v)
        # torch evaluates ``scalar / tensor`` as ``tensor.reciprocal() * scalar``
        j1, j3 = (1.0 / pz) * fx, -fx * u / pz
        k2, k3 = (1.0 / pz) * fy, -fy * v / pz
        a = j1 * j1 * c00 + 2 * j1 * j3 * c02 + j3 * j3 * c22 + EPS2D
        b = j1 * k2 * c01 + j1 * k3 * c02 + j3 * k2 * c12 + j3 * k3 * c22
        c = k2 * k2 * c11 + 2 * k2 * k3 * c12 + k3 * k3 * c22 + EPS2D
        det = a * c - b * b
        ok = (z_ok and np.isfinite(a) and np.isfinite(b) and np.isfinite(c) and np.isfinite(det)
              and det > 0)
        mid = 0.5 * (a + c)
        q = mid * mid - det
        q = 0.1 if q < 0.1 else q
        lam_max = mid + np.sqrt(q)
        r = np.ceil(3.0 * np.sqrt(lam_max if ok else 1.0))
        mx = fx * px / pz + cx
        my = fy * py / pz + cy
        out[i] = ok and (mx + r > 0) and (mx - r < w) and (my + r > 0) and (my - r < h)


@torch.no_grad()
def prefilter_anchors_matrix_form(xyz: Tensor, scales: Tensor, camera,
                                  z_min: float | None = None) -> Tensor:
    """Reference form of :func:`prefilter_anchors`: the same test written with [N,3,3]
    camera-space covariances and the rasterizer's shared :func:`ewa_cov2d` (batched 2x3 / 3x3
    products). Tests check that the two decide alike; ``pgs bench frame`` times both."""
    from .reference import ewa_cov2d

    dt = torch.float64
    vm = camera.viewmat.to(xyz.device, dt)
    R, t = vm[:3, :3], vm[:3, 3]
    p = xyz.to(dt) @ R.T + t
    z_ok = p[:, 2] > (float(camera.near) if z_min is None else z_min)
    p_safe = torch.where(z_ok[:, None], p, torch.ones_like(p))
    cov_cam = (R[None] * (scales.to(dt) ** 2)[:, None, :]) @ R.T
    cov2d = ewa_cov2d(p_safe, cov_cam, camera)
    a, b, c = cov2d[:, 0, 0], cov2d[:, 0, 1], cov2d[:, 1, 1]
    det = a * c - b * b
    ok = z_ok & torch.isfinite(cov2d).flatten(1).all(1) & torch.isfinite(det) & (det > 0)
    mid = 0.5 * (a + c)
    lam = mid + torch.sqrt(torch.clamp(mid * mid - det, min=0.1))
    r = torch.ceil(3.0 * torch.sqrt(torch.where(ok, lam, torch.ones_like(lam))))
    mx = camera.fx * p_safe[:, 0] / p_safe[:, 2] + camera.cx
    my = camera.fy * p_safe[:, 1] / p_safe[:, 2] + camera.cy
    return ok & (mx + r > 0) & (mx - r < camera.width) & (my + r > 0) & (my - r < camera.height)
