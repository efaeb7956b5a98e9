"""Pure-PyTorch reference rasterizer: slow, readable, autograd for the gradients.

It is the ground truth the tests compare the other backends against, so it spells out the
conventions of :mod:`baseline.render.conventions` with plain tensor code:

* projection: vectorized over Gaussians; unsafe values (z of culled Gaussians, determinants,
  zero quaternions) are replaced *before* dividing, so no NaN reaches the gradients;
* compositing: per pixel, over the Gaussians in depth order, with masks for the skip rules
  (``power < 0``, ``alpha < 1/255``) and the stop rule (``T (1 - alpha) <= 1e-4``, that
  Gaussian excluded), and an exclusive cumulative product for the transmittance.

By default the image is composed tile by tile (16 x 16 pixels, each with the Gaussians whose
opacity-aware box touches the tile; a Python loop over tiles, never over Gaussians), and with
autograd enabled each tile runs under ``torch.utils.checkpoint`` so memory stays bounded by one
tile. ``dense=True`` instead evaluates every pixel against every projected Gaussian (in pixel
chunks), with no boxes or tiles at all; the tests use it to check that the boxes never drop
a contribution.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch
from torch import Tensor
from torch.utils.checkpoint import checkpoint

from .conventions import (ALPHA_MAX, ALPHA_MIN, CLIP_MARGIN, EPS2D, EXTEND_MAX, T_MIN,
                          TILE_SIZE, RenderOutput, check_inputs)


@dataclass
class Projection:
    """Projected Gaussians (all [N, ...]); zeros where culled.

    Attributes:
        means2d: [N, 2] pixel coordinates (differentiable).
        conics: [N, 3] (A, B, C) of the inverse 2D covariance (differentiable).
        depths: [N] camera-space z (not differentiable).
        radii_xy: [N, 2] int32 opacity-aware half extents along x and y; 0 = culled.
        rect: [N, 4] int64 tile rectangle (tx0, ty0, tx1, ty1), half-open.
        visible: [N] bool.
    """

    means2d: Tensor
    conics: Tensor
    depths: Tensor
    radii_xy: Tensor
    rect: Tensor
    visible: Tensor


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """[N, 4] wxyz quaternions (any norm; zero or non-finite -> identity) -> [N, 3, 3]."""
    qn2 = (quats * quats).sum(-1)
    ok = (qn2 > 0) & torch.isfinite(qn2)
    ident = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=quats.dtype, device=quats.device)
    q = torch.where(ok[:, None], quats, ident)
    q = q / q.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1).reshape(-1, 3, 3)


def ewa_cov2d(p_cam: Tensor, cov_cam: Tensor, camera, eps2d: float = EPS2D) -> Tensor:
    """EWA 2D covariance with gsplat's clamped Jacobian.

    Args:
        p_cam: [N, 3] camera-space centres with safe (positive) z.
        cov_cam: [N, 3, 3] camera-space covariances.
        camera: :class:`baseline.camera.Camera`. eps2d: diagonal dilation in pixels^2.
    Returns:
        [N, 2, 2] ``J cov_cam J^T + eps2d I``.
    """
    fx, fy, cx, cy = float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy)
    w, h = float(camera.width), float(camera.height)
    tan_x, tan_y = 0.5 * w / fx, 0.5 * h / fy
    lim_xp, lim_xn = (w - cx) / fx + CLIP_MARGIN * tan_x, cx / fx + CLIP_MARGIN * tan_x
    lim_yp, lim_yn = (h - cy) / fy + CLIP_MARGIN * tan_y, cy / fy + CLIP_MARGIN * tan_y
    x, y, z = p_cam.unbind(-1)
    u = (x / z).clamp(-lim_xn, lim_xp)
    v = (y / z).clamp(-lim_yn, lim_yp)
    zero = torch.zeros_like(z)
    J = torch.stack([fx / z, zero, -fx * u / z, zero, fy / z, -fy * v / z], -1).reshape(-1, 2, 3)
    eye = torch.eye(2, dtype=p_cam.dtype, device=p_cam.device)
    return J @ cov_cam @ J.transpose(1, 2) + eps2d * eye


def project_reference(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor,
                      camera) -> Projection:
    """Project N Gaussians (see conventions). Shapes: means [N,3], quats [N,4], scales [N,3],
    opacities [N] (only for the opacity-aware extent). Computes in ``means.dtype``."""
    dt, dev = means.dtype, means.device
    vm = camera.viewmat.to(dev, dt)
    R, t = vm[:3, :3], vm[:3, 3]
    p = means @ R.T + t
    z = p[:, 2]
    z_ok = (z > camera.near) & (z < camera.far)
    p_safe = torch.where(z_ok[:, None], p, torch.ones_like(p))  # safe z before any division
    x, y, zs = p_safe.unbind(-1)

    Rq = quat_to_rotmat(quats)
    M = Rq * scales[:, None, :]
    cov_world = M @ M.transpose(1, 2)
    cov_cam = R @ cov_world @ R.T
    cov2d = ewa_cov2d(p_safe, cov_cam, camera)
    a, b, c = cov2d[:, 0, 0], cov2d[:, 0, 1], cov2d[:, 1, 1]
    det = a * c - b * b
    ok = z_ok & torch.isfinite(cov2d).flatten(1).all(1) & (det > 0) & torch.isfinite(det)
    one = torch.ones_like(det)
    a_s, b_s, c_s = torch.where(ok, a, one), torch.where(ok, b, 0 * one), torch.where(ok, c, one)
    det_s = a_s * c_s - b_s * b_s
    conics = torch.stack([c_s / det_s, -b_s / det_s, a_s / det_s], -1)
    means2d = torch.stack([camera.fx * x / zs + camera.cx, camera.fy * y / zs + camera.cy], -1)

    with torch.no_grad():
        o = opacities.detach().to(dt)
        ok = ok & (o >= ALPHA_MIN)
        extend = torch.sqrt(2 * torch.log(o.clamp(min=ALPHA_MIN) / ALPHA_MIN)).clamp(max=EXTEND_MAX)
        rx = torch.ceil(extend * a_s.detach().sqrt())
        ry = torch.ceil(extend * c_s.detach().sqrt())
        mx, my = means2d.detach().unbind(-1)
        ok = ok & ((rx > 0) | (ry > 0))
        ok = ok & (mx + rx > 0) & (mx - rx < camera.width)
        ok = ok & (my + ry > 0) & (my - ry < camera.height)
        rx = torch.where(ok, rx.clamp(max=2.0 ** 30), 0 * rx)
        ry = torch.where(ok, ry.clamp(max=2.0 ** 30), 0 * ry)
        tiles_x = -(-camera.width // TILE_SIZE)
        tiles_y = -(-camera.height // TILE_SIZE)
        rect = torch.stack([
            torch.floor((mx - rx) / TILE_SIZE).clamp(0, tiles_x),
            torch.floor((my - ry) / TILE_SIZE).clamp(0, tiles_y),
            torch.ceil((mx + rx) / TILE_SIZE).clamp(0, tiles_x),
            torch.ceil((my + ry) / TILE_SIZE).clamp(0, tiles_y)], -1)
        rect = torch.where(ok[:, None], rect, torch.zeros_like(rect)).to(torch.int64)
        radii_xy = torch.stack([rx, ry], -1).to(torch.int32)
    zero2 = torch.zeros_like(means2d)
    return Projection(
        means2d=torch.where(ok[:, None], means2d, zero2),
        conics=torch.where(ok[:, None], conics, torch.zeros_like(conics)),
        depths=z.detach(), radii_xy=radii_xy, rect=rect, visible=ok)


def composite(pix: Tensor, means2d: Tensor, conics: Tensor, opacities: Tensor,
              colors: Tensor):
    """Front-to-back compositing of G depth-sorted Gaussians at P pixel centres.

    Args:
        pix: [P, 2] pixel centres. means2d [G, 2], conics [G, 3], opacities [G], colors [G, C]:
            the Gaussians, front to back.
    Returns:
        color [P, C] (without background) and final transmittance [P].
    """
    if means2d.shape[0] == 0:
        return (pix.new_zeros(pix.shape[0], colors.shape[1]) + 0 * colors.sum(),
                pix.new_ones(pix.shape[0]))
    d = means2d[None, :, :] - pix[:, None, :]  # [P, G, 2]
    dx, dy = d[..., 0], d[..., 1]
    A, B, C = conics[:, 0], conics[:, 1], conics[:, 2]
    power = 0.5 * (A * dx * dx + C * dy * dy) + B * dx * dy
    alpha = torch.clamp(opacities * torch.exp(-power), max=ALPHA_MAX)  # [P, G]
    valid = (power >= 0) & (alpha >= ALPHA_MIN)
    with torch.no_grad():
        # which Gaussians actually contribute: valid ones before the one that would push the
        # transmittance to <= 1e-4 (that one and everything behind it are excluded)
        a_v = torch.where(valid, alpha, torch.zeros_like(alpha))
        t_before = _exclusive_cumprod(1 - a_v)
        stops = valid & (t_before * (1 - a_v) <= T_MIN)
        stopped = torch.cumsum(stops.to(torch.int32), dim=1) > 0
        contrib = valid & ~stopped
    a = torch.where(contrib, alpha, torch.zeros_like(alpha))
    T = _exclusive_cumprod(1 - a)  # transmittance in front of each Gaussian
    weights = a * T
    color = weights @ colors
    t_final = T[:, -1] * (1 - a[:, -1])
    return color, t_final


def _exclusive_cumprod(x: Tensor) -> Tensor:
    """[P, G] -> [P, G] with out[:, j] = prod_{k<j} x[:, k]."""
    ones = torch.ones_like(x[:, :1])
    return torch.cumprod(torch.cat([ones, x[:, :-1]], dim=1), dim=1)


def _pixel_centres(x0, y0, x1, y1, dtype, device) -> Tensor:
    ys, xs = torch.meshgrid(torch.arange(y0, y1, dtype=dtype, device=device) + 0.5,
                            torch.arange(x0, x1, dtype=dtype, device=device) + 0.5, indexing="ij")
    return torch.stack([xs.reshape(-1), ys.reshape(-1)], -1)


def tile_lists(proj: Projection, camera):
    """Per-tile Gaussian lists in depth order (vectorized; no loop over Gaussians).

    Returns:
        ids [P] int64 (Gaussian of each tile pair, grouped by tile, front to back) and
        starts [n_tiles + 1] int64 (pairs of tile t are ids[starts[t]:starts[t+1]]).
    """
    tiles_x = -(-camera.width // TILE_SIZE)
    tiles_y = -(-camera.height // TILE_SIZE)
    dev = proj.rect.device
    vis = torch.nonzero(proj.visible).squeeze(1)
    order = vis[torch.sort(proj.depths[vis], stable=True).indices]
    r = proj.rect[order]
    w = (r[:, 2] - r[:, 0]).clamp(min=0)
    cnt = w * (r[:, 3] - r[:, 1]).clamp(min=0)
    g = order.repeat_interleave(cnt)
    first = torch.cumsum(cnt, 0) - cnt
    j = torch.arange(int(cnt.sum()), device=dev) - first.repeat_interleave(cnt)
    wr = w.repeat_interleave(cnt)
    tx = r[:, 0].repeat_interleave(cnt) + j % wr.clamp(min=1)
    ty = r[:, 1].repeat_interleave(cnt) + j // wr.clamp(min=1)
    tile = ty * tiles_x + tx
    perm = torch.sort(tile, stable=True).indices  # stable: keeps depth order inside a tile
    counts = torch.bincount(tile, minlength=tiles_x * tiles_y)
    starts = torch.cat([torch.zeros(1, dtype=torch.int64, device=dev), torch.cumsum(counts, 0)])
    return g[perm], starts


def rasterize_reference(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor,
                        colors: Tensor, camera, background: Optional[Tensor] = None, *,
                        dense: bool = False, chunk_pixels: int = 1024) -> RenderOutput:
    """Reference render (see :func:`baseline.render.rasterize` for the arguments).

    Args:
        means [N, 3], quats [N, 4], scales [N, 3], opacities [N], colors [N, C], camera,
        background [C] or None.
        dense: evaluate every pixel against every projected Gaussian (no tiles, no boxes).
        chunk_pixels: pixels per chunk in dense mode (memory ~ chunk_pixels x N).
    Returns:
        :class:`RenderOutput` (means2d retains its gradient). Computes in ``means.dtype``.
    """
    background = check_inputs(means, quats, scales, opacities, colors, camera, background)
    proj = project_reference(means, quats, scales, opacities, camera)
    means2d = proj.means2d
    if means2d.requires_grad:
        means2d.retain_grad()
    image, alpha = render_projected(proj, means2d, opacities, colors, background, camera,
                                    dense=dense, chunk_pixels=chunk_pixels)
    n = means.shape[0]
    radii = proj.radii_xy.max(dim=1).values.to(torch.int32) if n else \
        torch.zeros(0, dtype=torch.int32, device=means.device)
    return RenderOutput(image=image, alpha=alpha, means2d=means2d, radii=radii,
                        visible=radii > 0, depths=proj.depths, backend="reference",
                        extras={"projection": proj})


def render_projected(proj: Projection, means2d: Tensor, opacities: Tensor, colors: Tensor,
                     background: Tensor, camera, *, dense: bool = False,
                     chunk_pixels: int = 1024):
    """Composite already projected Gaussians.

    Args:
        proj: :func:`project_reference` output (its conics, depths, rects and visibility are
            used). means2d: [N, 2] the centres to use (normally ``proj.means2d``).
        opacities [N], colors [N, C], background [C], camera; dense, chunk_pixels: see
            :func:`rasterize_reference`.
    Returns:
        image [H, W, C] and alpha [H, W].
    """
    dt, dev = means2d.dtype, means2d.device
    H, W = camera.height, camera.width
    colors_c = colors.to(dt)
    opac = opacities.to(dt)
    use_ckpt = torch.is_grad_enabled() and any(
        t.requires_grad for t in (means2d, proj.conics, opacities, colors))

    def run(pix, ids):
        def f(m2d, con, op, col):
            return composite(pix, m2d, con, op, col)
        args = (means2d[ids], proj.conics[ids], opac[ids], colors_c[ids])
        if use_ckpt:
            return checkpoint(f, *args, use_reentrant=False)
        return f(*args)

    if dense:
        vis = torch.nonzero(proj.visible).squeeze(1)
        ids = vis[torch.sort(proj.depths[vis], stable=True).indices]
        pix_all = _pixel_centres(0, 0, W, H, dt, dev)
        cols, ts = [], []
        for s in range(0, pix_all.shape[0], chunk_pixels):
            col, t = run(pix_all[s:s + chunk_pixels], ids)
            cols.append(col)
            ts.append(t)
        color = torch.cat(cols).reshape(H, W, -1)
        t_final = torch.cat(ts).reshape(H, W)
    else:
        ids_all, starts = tile_lists(proj, camera)
        starts = starts.tolist()
        tiles_x = -(-W // TILE_SIZE)
        rows_c, rows_t = [], []
        for ty in range(-(-H // TILE_SIZE)):
            y0, y1 = ty * TILE_SIZE, min((ty + 1) * TILE_SIZE, H)
            cols, ts = [], []
            for tx in range(tiles_x):
                x0, x1 = tx * TILE_SIZE, min((tx + 1) * TILE_SIZE, W)
                tid = ty * tiles_x + tx
                ids = ids_all[starts[tid]:starts[tid + 1]]
                pix = _pixel_centres(x0, y0, x1, y1, dt, dev)
                if ids.numel() == 0:
                    col = torch.zeros(pix.shape[0], colors.shape[1], dtype=dt, device=dev)
                    t = torch.ones(pix.shape[0], dtype=dt, device=dev)
                else:
                    col, t = run(pix, ids)
                cols.append(col.reshape(y1 - y0, x1 - x0, -1))
                ts.append(t.reshape(y1 - y0, x1 - x0))
            rows_c.append(torch.cat(cols, dim=1))
            rows_t.append(torch.cat(ts, dim=1))
        color = torch.cat(rows_c, dim=0)
        t_final = torch.cat(rows_t, dim=0)
    image = color + t_final[..., None] * background.to(dt)
    alpha = 1 - t_final
    if use_ckpt and not image.requires_grad:
        # nothing was drawn: keep the outputs in the graph so backward() yields zero grads
        zero = 0 * (means2d.sum() + proj.conics.sum() + opac.sum() + colors_c.sum())
        image, alpha = image + zero, alpha + zero
    return image, alpha
