"""Numba kernels of the CPU rasterizer (forward and backward).

One module of about 1,100 lines: the forward and backward kernels share the per-tile state
layout, its index constants and the work order, and must change together.

Everything here works on NumPy arrays; :mod:`baseline.render.cpu` wraps the kernels in
``torch.autograd.Function`` objects. The math follows gsplat's "classic" 3DGS rasterizer
(see :mod:`baseline.render.conventions`), with two CPU-specific choices:

* **Work order.** A tile (16 x 16 pixels) is one parallel task. Inside a tile the kernels loop
  over the tile's depth-sorted Gaussians and, per Gaussian, over the tile rows its
  opacity-aware box covers, 16 pixels at a time (looping per Gaussian over pixels rather than
  per pixel over Gaussians was ~4x faster in prototypes). The per-tile state lives in one flat
  float32 array indexed by constants + lane, the row loops have a constant trip count of 16
  and no branches, and each tile is a separate ``@njit`` function called from the ``prange``
  loop: together with ``error_model="numpy"`` (no ZeroDivisionError checks) that is what lets
  LLVM vectorize them (any of these missing made the kernels 3-10x slower). Rows whose pixels
  are all done are skipped, a tile stops when all its pixels are done, and the forward records
  per pair which tile rows it contributed to so the backward visits only those.
* **exp.** ``exp(-power)`` is evaluated as ``p(-power / 16) ** 16`` with a degree-7 Taylor
  polynomial ``p``; measured error on [0, 5.6] (where alpha >= 1/255 is possible): 2e-6
  relative, 8e-7 absolute, which keeps the forward within 1e-4 of the PyTorch reference.
  ``power`` is clamped to [0, 11] first (the approximation stays below 1/255 on [5.6, 11], so
  clamped values are rejected by the alpha threshold exactly as the exact ones would be).

Gradients of a (tile, Gaussian) pair go to a per-pair row of a buffer laid out Gaussian-major,
and one reduction kernel sums each Gaussian's rows in a fixed order: no atomics, bit-for-bit
deterministic for any thread count.

Array conventions (all C-contiguous):
    means2d  [N, 2] float32    pixel coordinates of the projected centres
    conics   [N, 3] float32    (A, B, C) of the inverse 2D covariance [[A, B], [B, C]]
    opac     [N]    float32
    colors   [N, K] float32    K channels
    radii    [N, 2] int32      opacity-aware half extents in pixels along x, y (0 = culled)
    rect     [N, 4] int32      tile rectangle tx0, ty0, tx1, ty1 (half-open)
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

# Constants, rounded to float32 where the float32 kernels use them (the reference uses the same
# values, see conventions.py).
_F0 = np.float32(0.0)
_F1 = np.float32(1.0)
_FHALF = np.float32(0.5)
_ALPHA_MIN = np.float32(1.0 / 255.0)
_ALPHA_MAX = np.float32(0.999)
_T_MIN = np.float32(1e-4)
_POWER_CLAMP = np.float32(11.0)
_INV16 = np.float32(1.0 / 16.0)
# Taylor coefficients of exp(y), degree 7.
_E2 = np.float32(1.0 / 2.0)
_E3 = np.float32(1.0 / 6.0)
_E4 = np.float32(1.0 / 24.0)
_E5 = np.float32(1.0 / 120.0)
_E6 = np.float32(1.0 / 720.0)
_E7 = np.float32(1.0 / 5040.0)

_TILE = 16
_RADIUS_CAP = 1 << 30  # radii are clamped here before the int32 conversion

# Fast-math flags that keep NaN/Inf semantics (the kernels never see NaN: culled Gaussians are
# never binned) but allow reassociation for vectorized reductions and FMA contraction.
_FM = {"reassoc", "contract", "arcp", "nsz"}


@njit(inline="always", fastmath=_FM, error_model="numpy")
def _exp_neg(power):
    """exp(-power) for float32 ``power`` (2e-6 relative error on [0, 5.6]; see module doc)."""
    p = min(max(power, _F0), _POWER_CLAMP)
    y = -p * _INV16
    e = _F1 + y * (_F1 + y * (_E2 + y * (_E3 + y * (_E4 + y * (_E5 + y * (_E6 + y * _E7))))))
    e = e * e
    e = e * e
    e = e * e
    return e * e


# --------------------------------------------------------------------------------------------
# Projection
# --------------------------------------------------------------------------------------------

@njit(parallel=True, cache=True)
def project_fwd(means, quats, scales, opac, viewmat, fx, fy, cx, cy, width, height, near, far,
                eps2d, alpha_min, extend_max, clip_margin, tiles_x, tiles_y,
                out_means2d, out_conics, out_depths, out_radii, out_rect):
    """EWA projection of N Gaussians (float64 throughout).

    Args:
        means [N, 3], quats [N, 4] (wxyz, any norm; zero -> identity), scales [N, 3],
        opac [N]: float64 inputs. viewmat [4, 4] float64 world-to-camera.
        fx, fy, cx, cy, width, height, near, far: camera. eps2d: diagonal dilation (0.3).
        alpha_min: 1/255. extend_max: 3.33 (max Mahalanobis extent of the box).
        clip_margin: 0.3, the Jacobian is evaluated at x/z, y/z clamped to the field of view
        enlarged by this fraction of the half-fov tangent on each side (gsplat's 1.3x).
        tiles_x, tiles_y: tile grid size.
    Outputs (written for every Gaussian; zeros where culled, except depths):
        out_means2d [N, 2], out_conics [N, 3], out_depths [N] (camera z), out_radii [N, 2]
        int32, out_rect [N, 4] int32 (tx0, ty0, tx1, ty1).
    """
    n = means.shape[0]
    tan_x = 0.5 * width / fx
    tan_y = 0.5 * height / fy
    lim_xp = (width - cx) / fx + clip_margin * tan_x
    lim_xn = cx / fx + clip_margin * tan_x
    lim_yp = (height - cy) / fy + clip_margin * tan_y
    lim_yn = cy / fy + clip_margin * tan_y
    r00 = viewmat[0, 0]; r01 = viewmat[0, 1]; r02 = viewmat[0, 2]; t0 = viewmat[0, 3]
    r10 = viewmat[1, 0]; r11 = viewmat[1, 1]; r12 = viewmat[1, 2]; t1 = viewmat[1, 3]
    r20 = viewmat[2, 0]; r21 = viewmat[2, 1]; r22 = viewmat[2, 2]; t2 = viewmat[2, 3]
    for i in prange(n):
        out_means2d[i, 0] = 0.0
        out_means2d[i, 1] = 0.0
        out_conics[i, 0] = 0.0
        out_conics[i, 1] = 0.0
        out_conics[i, 2] = 0.0
        out_radii[i, 0] = 0
        out_radii[i, 1] = 0
        out_rect[i, 0] = 0
        out_rect[i, 1] = 0
        out_rect[i, 2] = 0
        out_rect[i, 3] = 0
        px = means[i, 0]
        py = means[i, 1]
        pz = means[i, 2]
        x = r00 * px + r01 * py + r02 * pz + t0
        y = r10 * px + r11 * py + r12 * pz + t1
        z = r20 * px + r21 * py + r22 * pz + t2
        out_depths[i] = z
        if not (z > near and z < far):  # also rejects NaN
            continue
        # rotation of the Gaussian
        qw = quats[i, 0]
        qx = quats[i, 1]
        qy = quats[i, 2]
        qz = quats[i, 3]
        qn2 = qw * qw + qx * qx + qy * qy + qz * qz
        if qn2 > 0.0 and qn2 < np.inf:
            inv = 1.0 / math.sqrt(qn2)
            qw *= inv
            qx *= inv
            qy *= inv
            qz *= inv
        else:
            qw = 1.0
            qx = 0.0
            qy = 0.0
            qz = 0.0
        g00 = 1.0 - 2.0 * (qy * qy + qz * qz)
        g01 = 2.0 * (qx * qy - qw * qz)
        g02 = 2.0 * (qx * qz + qw * qy)
        g10 = 2.0 * (qx * qy + qw * qz)
        g11 = 1.0 - 2.0 * (qx * qx + qz * qz)
        g12 = 2.0 * (qy * qz - qw * qx)
        g20 = 2.0 * (qx * qz - qw * qy)
        g21 = 2.0 * (qy * qz + qw * qx)
        g22 = 1.0 - 2.0 * (qx * qx + qy * qy)
        sx = scales[i, 0]
        sy = scales[i, 1]
        sz = scales[i, 2]
        # M = R_g diag(s)
        m00 = g00 * sx; m01 = g01 * sy; m02 = g02 * sz
        m10 = g10 * sx; m11 = g11 * sy; m12 = g12 * sz
        m20 = g20 * sx; m21 = g21 * sy; m22 = g22 * sz
        # Jacobian of the perspective projection at the clamped direction
        rz = 1.0 / z
        u = min(lim_xp, max(-lim_xn, x * rz))
        v = min(lim_yp, max(-lim_yn, y * rz))
        j00 = fx * rz
        j02 = -fx * u * rz
        j11 = fy * rz
        j12 = -fy * v * rz
        # W = J R_view (2 x 3), then T = W M (2 x 3): cov2d = T T^T
        w00 = j00 * r00 + j02 * r20
        w01 = j00 * r01 + j02 * r21
        w02 = j00 * r02 + j02 * r22
        w10 = j11 * r10 + j12 * r20
        w11 = j11 * r11 + j12 * r21
        w12 = j11 * r12 + j12 * r22
        a0 = w00 * m00 + w01 * m10 + w02 * m20
        a1 = w00 * m01 + w01 * m11 + w02 * m21
        a2 = w00 * m02 + w01 * m12 + w02 * m22
        b0 = w10 * m00 + w11 * m10 + w12 * m20
        b1 = w10 * m01 + w11 * m11 + w12 * m21
        b2 = w10 * m02 + w11 * m12 + w12 * m22
        ca = a0 * a0 + a1 * a1 + a2 * a2 + eps2d
        cb = a0 * b0 + a1 * b1 + a2 * b2
        cc = b0 * b0 + b1 * b1 + b2 * b2 + eps2d
        det = ca * cc - cb * cb
        if not (det > 0.0 and det < np.inf and ca < np.inf and cc < np.inf):
            continue
        o = opac[i]
        if not (o >= alpha_min):
            continue
        extend = min(extend_max, math.sqrt(2.0 * math.log(o / alpha_min)))
        rx = math.ceil(extend * math.sqrt(ca))
        ry = math.ceil(extend * math.sqrt(cc))
        if rx <= 0.0 and ry <= 0.0:
            continue
        mx = fx * x * rz + cx
        my = fy * y * rz + cy
        if not (mx + rx > 0.0 and mx - rx < width and my + ry > 0.0 and my - ry < height):
            continue
        rx = min(rx, float(_RADIUS_CAP))
        ry = min(ry, float(_RADIUS_CAP))
        out_means2d[i, 0] = mx
        out_means2d[i, 1] = my
        idet = 1.0 / det
        out_conics[i, 0] = cc * idet
        out_conics[i, 1] = -cb * idet
        out_conics[i, 2] = ca * idet
        out_radii[i, 0] = np.int32(rx)
        out_radii[i, 1] = np.int32(ry)
        out_rect[i, 0] = np.int32(min(max(math.floor((mx - rx) / _TILE), 0.0), tiles_x))
        out_rect[i, 1] = np.int32(min(max(math.floor((my - ry) / _TILE), 0.0), tiles_y))
        out_rect[i, 2] = np.int32(min(max(math.ceil((mx + rx) / _TILE), 0.0), tiles_x))
        out_rect[i, 3] = np.int32(min(max(math.ceil((my + ry) / _TILE), 0.0), tiles_y))


@njit(parallel=True, cache=True)
def project_bwd(means, quats, scales, viewmat, fx, fy, cx, cy, width, height, clip_margin,
                radii, conics, v_means2d, v_conics, out_v_means, out_v_quats, out_v_scales):
    """Vector-Jacobian product of :func:`project_fwd` (float64).

    Exact gradient of the clamped-Jacobian projection (where x/z or y/z is clamped, the
    gradient of that term w.r.t. x or y is zero), unlike gsplat, whose backward ignores the
    clamp. Culled Gaussians (radii == 0) get zero gradients; zero quaternions get a zero
    quaternion gradient.

    Args:
        means, quats, scales, viewmat, camera: as :func:`project_fwd`.
        radii [N, 2] int32, conics [N, 3] float64: forward outputs.
        v_means2d [N, 2], v_conics [N, 3]: float64 output gradients.
    Outputs:
        out_v_means [N, 3], out_v_quats [N, 4], out_v_scales [N, 3] (float64, overwritten).
    """
    n = means.shape[0]
    tan_x = 0.5 * width / fx
    tan_y = 0.5 * height / fy
    lim_xp = (width - cx) / fx + clip_margin * tan_x
    lim_xn = cx / fx + clip_margin * tan_x
    lim_yp = (height - cy) / fy + clip_margin * tan_y
    lim_yn = cy / fy + clip_margin * tan_y
    r00 = viewmat[0, 0]; r01 = viewmat[0, 1]; r02 = viewmat[0, 2]; t0 = viewmat[0, 3]
    r10 = viewmat[1, 0]; r11 = viewmat[1, 1]; r12 = viewmat[1, 2]; t1 = viewmat[1, 3]
    r20 = viewmat[2, 0]; r21 = viewmat[2, 1]; r22 = viewmat[2, 2]; t2 = viewmat[2, 3]
    for i in prange(n):
        for k in range(3):
            out_v_means[i, k] = 0.0
            out_v_scales[i, k] = 0.0
        for k in range(4):
            out_v_quats[i, k] = 0.0
        if radii[i, 0] <= 0 and radii[i, 1] <= 0:
            continue
        px = means[i, 0]
        py = means[i, 1]
        pz = means[i, 2]
        x = r00 * px + r01 * py + r02 * pz + t0
        y = r10 * px + r11 * py + r12 * pz + t1
        z = r20 * px + r21 * py + r22 * pz + t2
        qw0 = quats[i, 0]
        qx0 = quats[i, 1]
        qy0 = quats[i, 2]
        qz0 = quats[i, 3]
        qn2 = qw0 * qw0 + qx0 * qx0 + qy0 * qy0 + qz0 * qz0
        q_ok = qn2 > 0.0 and qn2 < np.inf
        if q_ok:
            qnorm = math.sqrt(qn2)
            inv = 1.0 / qnorm
            qw = qw0 * inv
            qx = qx0 * inv
            qy = qy0 * inv
            qz = qz0 * inv
        else:
            qnorm = 1.0
            qw = 1.0
            qx = 0.0
            qy = 0.0
            qz = 0.0
        g00 = 1.0 - 2.0 * (qy * qy + qz * qz)
        g01 = 2.0 * (qx * qy - qw * qz)
        g02 = 2.0 * (qx * qz + qw * qy)
        g10 = 2.0 * (qx * qy + qw * qz)
        g11 = 1.0 - 2.0 * (qx * qx + qz * qz)
        g12 = 2.0 * (qy * qz - qw * qx)
        g20 = 2.0 * (qx * qz - qw * qy)
        g21 = 2.0 * (qy * qz + qw * qx)
        g22 = 1.0 - 2.0 * (qx * qx + qy * qy)
        sx = scales[i, 0]
        sy = scales[i, 1]
        sz = scales[i, 2]
        m00 = g00 * sx; m01 = g01 * sy; m02 = g02 * sz
        m10 = g10 * sx; m11 = g11 * sy; m12 = g12 * sz
        m20 = g20 * sx; m21 = g21 * sy; m22 = g22 * sz
        # world covariance S = M M^T (symmetric)
        s00 = m00 * m00 + m01 * m01 + m02 * m02
        s01 = m00 * m10 + m01 * m11 + m02 * m12
        s02 = m00 * m20 + m01 * m21 + m02 * m22
        s11 = m10 * m10 + m11 * m11 + m12 * m12
        s12 = m10 * m20 + m11 * m21 + m12 * m22
        s22 = m20 * m20 + m21 * m21 + m22 * m22
        rz = 1.0 / z
        xz = x * rz
        yz = y * rz
        u = min(lim_xp, max(-lim_xn, xz))
        v = min(lim_yp, max(-lim_yn, yz))
        u_free = xz >= -lim_xn and xz <= lim_xp
        v_free = yz >= -lim_yn and yz <= lim_yp
        j00 = fx * rz
        j02 = -fx * u * rz
        j11 = fy * rz
        j12 = -fy * v * rz
        w00 = j00 * r00 + j02 * r20
        w01 = j00 * r01 + j02 * r21
        w02 = j00 * r02 + j02 * r22
        w10 = j11 * r10 + j12 * r20
        w11 = j11 * r11 + j12 * r21
        w12 = j11 * r12 + j12 * r22
        # ---- conic -> cov2d: v_cov = -conic G conic, G = [[vA, vB/2], [vB/2, vC]]
        ia = conics[i, 0]
        ib = conics[i, 1]
        ic = conics[i, 2]
        ga = v_conics[i, 0]
        gb = 0.5 * v_conics[i, 1]
        gc = v_conics[i, 2]
        # X = conic @ G
        x00 = ia * ga + ib * gb
        x01 = ia * gb + ib * gc
        x10 = ib * ga + ic * gb
        x11 = ib * gb + ic * gc
        # V = -X @ conic (symmetric)
        v00 = -(x00 * ia + x01 * ib)
        v01 = -(x00 * ib + x01 * ic)
        v11 = -(x10 * ib + x11 * ic)
        # ---- cov2d = W S W^T:  v_W = 2 V W S,  v_S = W^T V W
        # WS = W @ S (2 x 3)
        ws00 = w00 * s00 + w01 * s01 + w02 * s02
        ws01 = w00 * s01 + w01 * s11 + w02 * s12
        ws02 = w00 * s02 + w01 * s12 + w02 * s22
        ws10 = w10 * s00 + w11 * s01 + w12 * s02
        ws11 = w10 * s01 + w11 * s11 + w12 * s12
        ws12 = w10 * s02 + w11 * s12 + w12 * s22
        vw00 = 2.0 * (v00 * ws00 + v01 * ws10)
        vw01 = 2.0 * (v00 * ws01 + v01 * ws11)
        vw02 = 2.0 * (v00 * ws02 + v01 * ws12)
        vw10 = 2.0 * (v01 * ws00 + v11 * ws10)
        vw11 = 2.0 * (v01 * ws01 + v11 * ws11)
        vw12 = 2.0 * (v01 * ws02 + v11 * ws12)
        # VW = V @ W (2 x 3); v_S = W^T VW (3 x 3, symmetric)
        vv00 = v00 * w00 + v01 * w10
        vv01 = v00 * w01 + v01 * w11
        vv02 = v00 * w02 + v01 * w12
        vv10 = v01 * w00 + v11 * w10
        vv11 = v01 * w01 + v11 * w11
        vv12 = v01 * w02 + v11 * w12
        vs00 = w00 * vv00 + w10 * vv10
        vs01 = w00 * vv01 + w10 * vv11
        vs02 = w00 * vv02 + w10 * vv12
        vs11 = w01 * vv01 + w11 * vv11
        vs12 = w01 * vv02 + w11 * vv12
        vs22 = w02 * vv02 + w12 * vv12
        # ---- W = J R: v_J = v_W R^T (only the 4 non-zero entries of J matter)
        vj00 = vw00 * r00 + vw01 * r01 + vw02 * r02
        vj02 = vw00 * r20 + vw01 * r21 + vw02 * r22
        vj11 = vw10 * r10 + vw11 * r11 + vw12 * r12
        vj12 = vw10 * r20 + vw11 * r21 + vw12 * r22
        # ---- camera-space mean gradient
        gmx = v_means2d[i, 0]
        gmy = v_means2d[i, 1]
        rz2 = rz * rz
        vx = fx * rz * gmx
        vy = fy * rz * gmy
        vz = -(fx * x * gmx + fy * y * gmy) * rz2
        vz += -fx * rz2 * vj00 - fy * rz2 * vj11
        # J02 = -fx u / z with u = x / z unless clamped
        if u_free:
            vx += -fx * rz2 * vj02
            vz += 2.0 * fx * x * rz2 * rz * vj02
        else:
            vz += fx * u * rz2 * vj02
        if v_free:
            vy += -fy * rz2 * vj12
            vz += 2.0 * fy * y * rz2 * rz * vj12
        else:
            vz += fy * v * rz2 * vj12
        out_v_means[i, 0] = r00 * vx + r10 * vy + r20 * vz
        out_v_means[i, 1] = r01 * vx + r11 * vy + r21 * vz
        out_v_means[i, 2] = r02 * vx + r12 * vy + r22 * vz
        # ---- S = M M^T: v_M = 2 v_S M
        vm00 = 2.0 * (vs00 * m00 + vs01 * m10 + vs02 * m20)
        vm01 = 2.0 * (vs00 * m01 + vs01 * m11 + vs02 * m21)
        vm02 = 2.0 * (vs00 * m02 + vs01 * m12 + vs02 * m22)
        vm10 = 2.0 * (vs01 * m00 + vs11 * m10 + vs12 * m20)
        vm11 = 2.0 * (vs01 * m01 + vs11 * m11 + vs12 * m21)
        vm12 = 2.0 * (vs01 * m02 + vs11 * m12 + vs12 * m22)
        vm20 = 2.0 * (vs02 * m00 + vs12 * m10 + vs22 * m20)
        vm21 = 2.0 * (vs02 * m01 + vs12 * m11 + vs22 * m21)
        vm22 = 2.0 * (vs02 * m02 + vs12 * m12 + vs22 * m22)
        out_v_scales[i, 0] = vm00 * g00 + vm10 * g10 + vm20 * g20
        out_v_scales[i, 1] = vm01 * g01 + vm11 * g11 + vm21 * g21
        out_v_scales[i, 2] = vm02 * g02 + vm12 * g12 + vm22 * g22
        if not q_ok:
            continue
        # v_R = v_M diag(s)
        a00 = vm00 * sx; a01 = vm01 * sy; a02 = vm02 * sz
        a10 = vm10 * sx; a11 = vm11 * sy; a12 = vm12 * sz
        a20 = vm20 * sx; a21 = vm21 * sy; a22 = vm22 * sz
        # d R / d(w, x, y, z) contracted with v_R
        vqw = 2.0 * (-qz * a01 + qy * a02 + qz * a10 - qx * a12 - qy * a20 + qx * a21)
        vqx = 2.0 * (qy * a01 + qz * a02 + qy * a10 - 2.0 * qx * a11 - qw * a12
                     + qz * a20 + qw * a21 - 2.0 * qx * a22)
        vqy = 2.0 * (-2.0 * qy * a00 + qx * a01 + qw * a02 + qx * a10 + qz * a12
                     - qw * a20 + qz * a21 - 2.0 * qy * a22)
        vqz = 2.0 * (-2.0 * qz * a00 - qw * a01 + qx * a02 + qw * a10 - 2.0 * qz * a11
                     + qy * a12 + qx * a20 + qy * a21)
        # normalization q / |q|
        dot = qw * vqw + qx * vqx + qy * vqy + qz * vqz
        invn = 1.0 / qnorm
        out_v_quats[i, 0] = (vqw - qw * dot) * invn
        out_v_quats[i, 1] = (vqx - qx * dot) * invn
        out_v_quats[i, 2] = (vqy - qy * dot) * invn
        out_v_quats[i, 3] = (vqz - qz * dot) * invn


# --------------------------------------------------------------------------------------------
# Tile binning
# --------------------------------------------------------------------------------------------

@njit(cache=True)
def depth_order(depths, ids):
    """``ids`` sorted by ``depths[ids]``, front to back, stable (ties keep the order of ids).

    LSD radix sort on the float64 bit patterns (mapped to order-preserving unsigned keys),
    four 16-bit digits, skipping digits all keys share. O(M), far quicker than a comparison
    sort for the 1e4-1e6 visible Gaussians of a view.

    Args:
        depths [N] float64 (no NaN), ids [M] int64 (increasing).
    Returns:
        [M] int64.
    """
    m = ids.shape[0]
    keys = np.empty(m, np.uint64)
    sign = np.uint64(1) << np.uint64(63)
    for j in range(m):
        z = depths[ids[j]] + 0.0  # -0.0 -> +0.0 (they compare equal)
        b = np.uint64(np.int64(np.float64(z).view(np.int64)))
        keys[j] = ~b if b & sign else b | sign
    cur_ids = ids.copy()
    cur_keys = keys
    tmp_ids = np.empty(m, np.int64)
    tmp_keys = np.empty(m, np.uint64)
    count = np.empty(1 << 16, np.int64)
    mask = np.uint64(0xFFFF)
    for d in range(4):
        shift = np.uint64(16 * d)
        count[:] = 0
        for j in range(m):
            count[np.int64((cur_keys[j] >> shift) & mask)] += 1
        if m == 0 or count[np.int64((cur_keys[0] >> shift) & mask)] == m:
            continue  # every key has this digit
        run = 0
        for c in range(1 << 16):
            n_c = count[c]
            count[c] = run
            run += n_c
        for j in range(m):
            c = np.int64((cur_keys[j] >> shift) & mask)
            dst = count[c]
            count[c] = dst + 1
            tmp_ids[dst] = cur_ids[j]
            tmp_keys[dst] = cur_keys[j]
        cur_ids, tmp_ids = tmp_ids, cur_ids
        cur_keys, tmp_keys = tmp_keys, cur_keys
    return cur_ids


@njit(parallel=True, cache=True)
def bin_pairs(order, rect, tiles_x, n_tiles, n_chunks):
    """Lists of (tile, Gaussian) pairs, each tile's list in front-to-back order.

    A parallel, stable counting sort: ``order`` (visible Gaussians sorted by depth) is split
    into ``n_chunks`` contiguous chunks; each chunk counts its pairs per tile, a prefix sum gives
    every (chunk, tile) its write position, and each chunk scatters its pairs. Because chunks
    are written in order, every tile's list stays in depth order.

    Args:
        order [M] int64: Gaussian ids with non-empty rect, sorted front to back.
        rect [N, 4] int32: tile rectangles (tx0, ty0, tx1, ty1).
        tiles_x, n_tiles: tile grid width and tile count. n_chunks: parallel chunks.
    Returns:
        tile_start [n_tiles + 1] int64: pairs of tile t are tile_start[t]:tile_start[t+1].
        pair_gauss [P] int32: the Gaussian of each pair.
        pair_slot [P] int64: row of the pair in the Gaussian-major gradient buffer.
        gauss_start [N + 1] int64: Gaussian g owns buffer rows gauss_start[g]:gauss_start[g+1].
    """
    n = rect.shape[0]
    m = order.shape[0]
    gauss_start = np.zeros(n + 1, np.int64)
    for g in range(n):
        cnt = (rect[g, 2] - rect[g, 0]) * (rect[g, 3] - rect[g, 1])
        if cnt < 0:
            cnt = 0
        gauss_start[g + 1] = gauss_start[g] + cnt
    n_pairs = gauss_start[n]
    chunk = (m + n_chunks - 1) // n_chunks
    counts = np.zeros((n_chunks, n_tiles), np.int64)
    for c in prange(n_chunks):
        for j in range(c * chunk, min(m, (c + 1) * chunk)):
            g = order[j]
            for ty in range(rect[g, 1], rect[g, 3]):
                for tx in range(rect[g, 0], rect[g, 2]):
                    counts[c, ty * tiles_x + tx] += 1
    tile_start = np.zeros(n_tiles + 1, np.int64)
    cursor = np.empty((n_chunks, n_tiles), np.int64)
    run = 0
    for t in range(n_tiles):
        tile_start[t] = run
        for c in range(n_chunks):
            cursor[c, t] = run
            run += counts[c, t]
    tile_start[n_tiles] = run
    pair_gauss = np.empty(n_pairs, np.int32)
    pair_slot = np.empty(n_pairs, np.int64)
    for c in prange(n_chunks):
        for j in range(c * chunk, min(m, (c + 1) * chunk)):
            g = order[j]
            s = gauss_start[g]
            for ty in range(rect[g, 1], rect[g, 3]):
                for tx in range(rect[g, 0], rect[g, 2]):
                    t = ty * tiles_x + tx
                    p = cursor[c, t]
                    cursor[c, t] = p + 1
                    pair_gauss[p] = g
                    pair_slot[p] = s
                    s += 1
    return tile_start, pair_gauss, pair_slot, gauss_start


# --------------------------------------------------------------------------------------------
# Rasterization
# --------------------------------------------------------------------------------------------

@njit(inline="always")
def _row_span(my, ry, y0, y1):
    """Rows [gy0, gy1) of a tile (rows y0..y1) inside a Gaussian's box (centre my, half
    height ry); pixel row y has its centre at y + 0.5."""
    gy0 = max(y0, np.int64(math.ceil(my - ry - _FHALF)))
    gy1 = min(y1, np.int64(math.floor(my + ry - _FHALF)) + 1)
    return gy0, gy1


@njit(parallel=True, cache=True, fastmath=_FM, error_model="numpy")
def raster_fwd(means2d, conics, opac, colors, background, radii, tile_start, pair_gauss,
               width, height, tiles_x, out_image, out_T, out_last, out_rows):
    """Front-to-back alpha compositing, one tile per parallel task.

    Per tile, the state of its 16 x 16 pixels (padded at the image border; padding pixels
    start "done") lives in one flat float32 array ``S`` (transmittance, done flag, last
    contributor as a tile-local index, colour accumulators): with a single array and constant
    offsets LLVM needs no aliasing checks and vectorizes the row loops. For each Gaussian of
    the tile (front to back), the tile rows inside its box are updated 16 pixels at a time;
    rows whose pixels are all done are skipped, and the tile stops when every pixel is done.
    Whole tile rows are evaluated, as in the reference; pixels outside the box have
    alpha < 1/255 and are rejected by the compositing rule. C = 3 has a fused path.

    Args:
        means2d [N, 2], conics [N, 3], opac [N], colors [N, K], background [K]: float32.
        radii [N, 2] int32. tile_start, pair_gauss: from :func:`bin_pairs` (at most 2^24
        pairs per tile: tile-local indices are stored as float32).
        width, height, tiles_x: image and tile grid size.
    Outputs:
        out_image [H, W, K] float32: sum_i c_i a_i T_i + T_final * background.
        out_T [H, W] float32: final transmittance (alpha = 1 - T).
        out_last [H, W] int64: pair index of the last contributing Gaussian (-1 if none).
        out_rows [P] int32 (zeroed by the caller): bit r set when the pair's Gaussian
            contributed to a pixel of tile row r (lets the backward skip the other rows).
    """
    n_tiles = tile_start.shape[0] - 1
    for t in prange(n_tiles):
        if colors.shape[1] == 3:
            _fwd_tile3(t, means2d, conics, opac, colors, background, radii, tile_start,
                       pair_gauss, width, height, tiles_x, out_image, out_T, out_last, out_rows)
        else:
            _fwd_tile_any(t, means2d, conics, opac, colors, background, radii, tile_start,
                          pair_gauss, width, height, tiles_x, out_image, out_T, out_last,
                          out_rows)


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _fwd_tile3(t, means2d, conics, opac, colors, background, radii, tile_start, pair_gauss,
               width, height, tiles_x, out_image, out_T, out_last, out_rows):
    """One tile of :func:`raster_fwd` for C = 3.

    A separate function because inside a prange body numba passes the state offsets as
    runtime values and LLVM no longer vectorizes the row loops; for the same reason the
    channel count is a literal here and the generic-C code lives in :func:`_fwd_tile_any`.
    Per-row bookkeeping uses boolean any/all reductions (cheap mask tests) rather than float
    sums (horizontal adds after every row)."""
    n_ch = 3  # a literal: the state offsets below must be compile-time constants
    npix = _TILE * _TILE
    o_T = 0  # transmittance
    o_D = npix  # done flag (1.0 once the pixel stopped; padding starts done)
    o_L = 2 * npix  # last contributor, tile-local index as float32 (-1: none)
    o_A = 3 * npix  # colour accumulators, channel-major
    o_W = (3 + n_ch) * npix  # weights of the current row (generic path)
    ty = t // tiles_x
    tx = t - ty * tiles_x
    x0 = tx * _TILE
    y0 = ty * _TILE
    x1 = min(x0 + _TILE, width)
    y1 = min(y0 + _TILE, height)
    k0 = tile_start[t]
    S = np.zeros(o_W + _TILE, np.float32)
    for i in range(npix):
        S[o_T + i] = _F1
        S[o_L + i] = np.float32(-1.0)
        r = i // _TILE
        if y0 + r >= height or x0 + (i - r * _TILE) >= width:
            S[o_D + i] = _F1
    for k in range(k0, tile_start[t + 1]):
        g = pair_gauss[k]
        mx = means2d[g, 0]
        my = means2d[g, 1]
        ca = conics[g, 0]
        cb = conics[g, 1]
        cc = conics[g, 2]
        o = opac[g]
        kf = np.float32(k - k0)
        dx0 = mx - (np.float32(x0) + _FHALF)
        gy0, gy1 = _row_span(my, np.float32(radii[g, 1]), y0, y1)
        rmask = 0
        stopped = False
        c0 = colors[g, 0]
        c1 = colors[g, 1]
        c2 = colors[g, 2]
        for py in range(gy0, gy1):
            r = py - y0
            off = r * _TILE
            R = S[off:]  # one view, constant offsets + j >= 0: no wraparound, vectorizes
            all_done = True
            for j in range(_TILE):
                all_done &= R[o_D + j] != _F0
            if all_done:
                continue
            dy = my - (np.float32(py) + _FHALF)
            half_c_dy2 = _FHALF * cc * dy * dy
            b_dy = cb * dy
            any_contrib = False
            any_stop = False
            for j in range(_TILE):
                dx = dx0 - np.float32(j)
                power = _FHALF * ca * dx * dx + half_c_dy2 + b_dy * dx
                alpha = min(_ALPHA_MAX, o * _exp_neg(power))
                ti = R[o_T + j]
                nt = ti * (_F1 - alpha)
                ok = (power >= _F0) & (alpha >= _ALPHA_MIN) & (R[o_D + j] == _F0)
                stop = ok & (nt <= _T_MIN)
                contrib = ok & (nt > _T_MIN)
                w = alpha * ti if contrib else _F0
                R[o_A + j] += w * c0
                R[o_A + npix + j] += w * c1
                R[o_A + 2 * npix + j] += w * c2
                R[o_T + j] = nt if contrib else ti
                R[o_L + j] = kf if contrib else R[o_L + j]
                R[o_D + j] = _F1 if stop else R[o_D + j]
                any_contrib |= contrib
                any_stop |= stop
            if any_contrib:
                rmask |= 1 << r
            stopped |= any_stop
        out_rows[k] = rmask
        if stopped:  # rare (once per pixel): is the whole tile done?
            all_done = True
            for i in range(npix):
                all_done &= S[o_D + i] != _F0
            if all_done:
                break
    for py in range(y0, y1):
        for px in range(x0, x1):
            i = (py - y0) * _TILE + px - x0
            ti = S[o_T + i]
            for ch in range(n_ch):
                out_image[py, px, ch] = S[o_A + ch * npix + i] + ti * background[ch]
            out_T[py, px] = ti
            lf = S[o_L + i]
            out_last[py, px] = k0 + np.int64(lf) if lf >= _F0 else -1


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _fwd_tile_any(t, means2d, conics, opac, colors, background, radii, tile_start, pair_gauss,
                  width, height, tiles_x, out_image, out_T, out_last, out_rows):
    """One tile of :func:`raster_fwd` for any channel count (weights of a row go through a
    scratch row, then one pass per channel; see :func:`_fwd_tile3`)."""
    n_ch = colors.shape[1]
    npix = _TILE * _TILE
    o_T = 0  # transmittance
    o_D = npix  # done flag (1.0 once the pixel stopped; padding starts done)
    o_L = 2 * npix  # last contributor, tile-local index as float32 (-1: none)
    o_A = 3 * npix  # colour accumulators, channel-major
    o_W = (3 + n_ch) * npix  # weights of the current row (generic path)
    ty = t // tiles_x
    tx = t - ty * tiles_x
    x0 = tx * _TILE
    y0 = ty * _TILE
    x1 = min(x0 + _TILE, width)
    y1 = min(y0 + _TILE, height)
    k0 = tile_start[t]
    S = np.zeros(o_W + _TILE, np.float32)
    for i in range(npix):
        S[o_T + i] = _F1
        S[o_L + i] = np.float32(-1.0)
        r = i // _TILE
        if y0 + r >= height or x0 + (i - r * _TILE) >= width:
            S[o_D + i] = _F1
    for k in range(k0, tile_start[t + 1]):
        g = pair_gauss[k]
        mx = means2d[g, 0]
        my = means2d[g, 1]
        ca = conics[g, 0]
        cb = conics[g, 1]
        cc = conics[g, 2]
        o = opac[g]
        kf = np.float32(k - k0)
        dx0 = mx - (np.float32(x0) + _FHALF)
        gy0, gy1 = _row_span(my, np.float32(radii[g, 1]), y0, y1)
        rmask = 0
        stopped = False
        for py in range(gy0, gy1):
            r = py - y0
            off = r * _TILE
            R = S[off:]  # one view, constant offsets + j >= 0: no wraparound, vectorizes
            all_done = True
            for j in range(_TILE):
                all_done &= R[o_D + j] != _F0
            if all_done:
                continue
            dy = my - (np.float32(py) + _FHALF)
            half_c_dy2 = _FHALF * cc * dy * dy
            b_dy = cb * dy
            any_contrib = False
            any_stop = False
            for j in range(_TILE):
                dx = dx0 - np.float32(j)
                power = _FHALF * ca * dx * dx + half_c_dy2 + b_dy * dx
                alpha = min(_ALPHA_MAX, o * _exp_neg(power))
                ti = R[o_T + j]
                nt = ti * (_F1 - alpha)
                ok = (power >= _F0) & (alpha >= _ALPHA_MIN) & (R[o_D + j] == _F0)
                stop = ok & (nt <= _T_MIN)
                contrib = ok & (nt > _T_MIN)
                S[o_W + j] = alpha * ti if contrib else _F0
                R[o_T + j] = nt if contrib else ti
                R[o_L + j] = kf if contrib else R[o_L + j]
                R[o_D + j] = _F1 if stop else R[o_D + j]
                any_contrib |= contrib
                any_stop |= stop
            for ch in range(n_ch):
                col = colors[g, ch]
                a_v = S[o_A + ch * npix + off:]
                for j in range(_TILE):
                    a_v[j] += S[o_W + j] * col
            if any_contrib:
                rmask |= 1 << r
            stopped |= any_stop
        out_rows[k] = rmask
        if stopped:  # rare (once per pixel): is the whole tile done?
            all_done = True
            for i in range(npix):
                all_done &= S[o_D + i] != _F0
            if all_done:
                break
    for py in range(y0, y1):
        for px in range(x0, x1):
            i = (py - y0) * _TILE + px - x0
            ti = S[o_T + i]
            for ch in range(n_ch):
                out_image[py, px, ch] = S[o_A + ch * npix + i] + ti * background[ch]
            out_T[py, px] = ti
            lf = S[o_L + i]
            out_last[py, px] = k0 + np.int64(lf) if lf >= _F0 else -1


@njit(parallel=True, cache=True, fastmath=_FM, error_model="numpy")
def raster_bwd(means2d, conics, opac, colors, background, radii, tile_start, pair_gauss,
               pair_slot, pair_rows, width, height, tiles_x, T_final, last, v_image, v_alpha,
               out_pair):
    """Backward of :func:`raster_fwd`, one tile per parallel task.

    Each pixel walks back from its last contributor, recovering the transmittance in front of
    each Gaussian by division (T_prev = T / (1 - alpha); alpha <= 0.999 keeps it stable) and
    the colour accumulated behind it. Same flat per-tile state and 16-wide rows as the
    forward; only the rows where the pair contributed in the forward (``pair_rows``) are
    visited; C = 3 has a fused single-pass row loop.

    Args:
        as :func:`raster_fwd`, plus pair_slot [P] int64, pair_rows [P] int32, T_final [H, W],
        last [H, W] int64 (forward outputs), v_image [H, W, K], v_alpha [H, W] float32
        (output gradients).
    Outputs:
        out_pair [P, 6 + K] float32, row pair_slot[k] of pair k: d/d(mean2d x, y),
        d/d(conic A, B, C), d/d opacity, d/d colour (K). Rows of pairs no pixel reaches are left
        untouched (pass a zeroed buffer).
    """
    n_tiles = tile_start.shape[0] - 1
    for t in prange(n_tiles):
        if colors.shape[1] == 3:
            _bwd_tile3(t, means2d, conics, opac, colors, background, radii, tile_start,
                       pair_gauss, pair_slot, pair_rows, width, height, tiles_x, T_final, last,
                       v_image, v_alpha, out_pair)
        else:
            _bwd_tile_any(t, means2d, conics, opac, colors, background, radii, tile_start,
                          pair_gauss, pair_slot, pair_rows, width, height, tiles_x, T_final,
                          last, v_image, v_alpha, out_pair)


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _bwd_tile3(t, means2d, conics, opac, colors, background, radii, tile_start, pair_gauss,
              pair_slot, pair_rows, width, height, tiles_x, T_final, last, v_image, v_alpha,
              out_pair):
    """One tile of :func:`raster_bwd` for C = 3 (fused single-pass rows).

    A separate function for vectorization (see :func:`_fwd_tile3`; the generic-C code in the
    same function also stopped LLVM from vectorizing this loop). The gradient sums of a pair
    are kept per lane (``G``, 16 partial sums per quantity) and reduced once per pair:
    horizontal reductions after every row made the row loop twice as slow."""
    n_ch = 3  # a literal: the state offsets below must be compile-time constants
    npix = _TILE * _TILE
    o_T = 0
    o_L = npix  # last contributor, tile-local index as float32 (-1: none)
    o_E = 2 * npix  # T_final * (v_alpha - <background, v_image>)
    o_V = 3 * npix  # v_image, channel-major
    o_B = (3 + n_ch) * npix  # colour accumulated behind, channel-major
    o_R = (3 + 2 * n_ch) * npix  # row scratch (generic path): ok, fac, ra, t, s1, s2, vis
    k0 = tile_start[t]
    if tile_start[t + 1] == k0:
        return
    ty = t // tiles_x
    tx = t - ty * tiles_x
    x0 = tx * _TILE
    y0 = ty * _TILE
    x1 = min(x0 + _TILE, width)
    y1 = min(y0 + _TILE, height)
    S = np.zeros(o_R + 7 * _TILE, np.float32)
    # lane-wise gradient sums of the current pair: mean2d x, y, conic A, B, C, opacity, colours
    n_g = 6 + n_ch
    G = np.zeros(n_g * _TILE, np.float32)
    for i in range(npix):
        S[o_T + i] = _F1
        S[o_L + i] = np.float32(-1.0)
    k_max = k0 - 1
    for py in range(y0, y1):
        r = py - y0
        for px in range(x0, x1):
            i = r * _TILE + px - x0
            tf = T_final[py, px]
            S[o_T + i] = tf
            lk = last[py, px]
            if lk >= k0:
                S[o_L + i] = np.float32(lk - k0)
            k_max = max(k_max, lk)
            bdot = _F0
            for ch in range(n_ch):
                gv = v_image[py, px, ch]
                S[o_V + ch * npix + i] = gv
                bdot += background[ch] * gv
            S[o_E + i] = tf * (v_alpha[py, px] - bdot)
    for k in range(k_max, k0 - 1, -1):
        rmask = pair_rows[k]
        if rmask == 0:
            continue
        g = pair_gauss[k]
        mx = means2d[g, 0]
        my = means2d[g, 1]
        ca = conics[g, 0]
        cb = conics[g, 1]
        cc = conics[g, 2]
        o = opac[g]
        kf = np.float32(k - k0)
        dx0 = mx - (np.float32(x0) + _FHALF)
        c0 = colors[g, 0]
        c1 = colors[g, 1]
        c2 = colors[g, 2]
        gy0, gy1 = _row_span(my, np.float32(radii[g, 1]), y0, y1)
        for q in range(n_g * _TILE):
            G[q] = _F0
        for py in range(gy0, gy1):
            r = py - y0
            if (rmask >> r) & 1 == 0:
                continue
            dy = my - (np.float32(py) + _FHALF)
            off = r * _TILE
            R = S[off:]  # one view, constant offsets + j >= 0: no wraparound, vectorizes
            half_c_dy2 = _FHALF * cc * dy * dy
            b_dy = cb * dy
            for j in range(_TILE):
                dx = dx0 - np.float32(j)
                power = _FHALF * ca * dx * dx + half_c_dy2 + b_dy * dx
                vis = _exp_neg(power)
                alpha = min(_ALPHA_MAX, o * vis)
                ok = (power >= _F0) & (alpha >= _ALPHA_MIN) & (kf <= R[o_L + j])
                ra = _F1 / (_F1 - alpha)
                t_old = R[o_T + j]
                tn = t_old * ra if ok else t_old
                R[o_T + j] = tn
                fac = alpha * tn if ok else _F0
                g0 = R[o_V + j]
                g1 = R[o_V + npix + j]
                g2 = R[o_V + 2 * npix + j]
                b0 = R[o_B + j]
                b1 = R[o_B + npix + j]
                b2 = R[o_B + 2 * npix + j]
                s1 = c0 * g0 + c1 * g1 + c2 * g2
                s2 = b0 * g0 + b1 * g1 + b2 * g2
                R[o_B + j] = b0 + c0 * fac
                R[o_B + npix + j] = b1 + c1 * fac
                R[o_B + 2 * npix + j] = b2 + c2 * fac
                # the 0.999 clamp blocks gradients to opacity and the Gaussian's shape
                on = ok & (o * vis <= _ALPHA_MAX)
                v_al = (tn * s1 - ra * s2 + ra * R[o_E + j]) if on else _F0
                v_sig = -o * vis * v_al
                G[j] += v_sig * (ca * dx + cb * dy)
                G[_TILE + j] += v_sig * (cb * dx + cc * dy)
                G[2 * _TILE + j] += _FHALF * dx * dx * v_sig
                G[3 * _TILE + j] += dx * dy * v_sig
                G[4 * _TILE + j] += _FHALF * dy * dy * v_sig
                G[5 * _TILE + j] += vis * v_al
                G[6 * _TILE + j] += fac * g0
                G[7 * _TILE + j] += fac * g1
                G[8 * _TILE + j] += fac * g2
        row = pair_slot[k]
        for q in range(n_g):
            acc = _F0
            for j in range(_TILE):
                acc += G[q * _TILE + j]
            out_pair[row, q] = acc


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _bwd_tile_any(t, means2d, conics, opac, colors, background, radii, tile_start, pair_gauss,
              pair_slot, pair_rows, width, height, tiles_x, T_final, last, v_image, v_alpha,
              out_pair):
    """One tile of :func:`raster_bwd` for any C (three passes per row through scratch rows;
    see :func:`_bwd_tile3`)."""
    n_ch = colors.shape[1]
    npix = _TILE * _TILE
    o_T = 0
    o_L = npix  # last contributor, tile-local index as float32 (-1: none)
    o_E = 2 * npix  # T_final * (v_alpha - <background, v_image>)
    o_V = 3 * npix  # v_image, channel-major
    o_B = (3 + n_ch) * npix  # colour accumulated behind, channel-major
    o_R = (3 + 2 * n_ch) * npix  # row scratch (generic path): ok, fac, ra, t, s1, s2, vis
    k0 = tile_start[t]
    if tile_start[t + 1] == k0:
        return
    ty = t // tiles_x
    tx = t - ty * tiles_x
    x0 = tx * _TILE
    y0 = ty * _TILE
    x1 = min(x0 + _TILE, width)
    y1 = min(y0 + _TILE, height)
    S = np.zeros(o_R + 7 * _TILE, np.float32)
    # lane-wise gradient sums of the current pair: mean2d x, y, conic A, B, C, opacity, colours
    n_g = 6 + n_ch
    G = np.zeros(n_g * _TILE, np.float32)
    for i in range(npix):
        S[o_T + i] = _F1
        S[o_L + i] = np.float32(-1.0)
    k_max = k0 - 1
    for py in range(y0, y1):
        r = py - y0
        for px in range(x0, x1):
            i = r * _TILE + px - x0
            tf = T_final[py, px]
            S[o_T + i] = tf
            lk = last[py, px]
            if lk >= k0:
                S[o_L + i] = np.float32(lk - k0)
            k_max = max(k_max, lk)
            bdot = _F0
            for ch in range(n_ch):
                gv = v_image[py, px, ch]
                S[o_V + ch * npix + i] = gv
                bdot += background[ch] * gv
            S[o_E + i] = tf * (v_alpha[py, px] - bdot)
    for k in range(k_max, k0 - 1, -1):
        rmask = pair_rows[k]
        if rmask == 0:
            continue
        g = pair_gauss[k]
        mx = means2d[g, 0]
        my = means2d[g, 1]
        ca = conics[g, 0]
        cb = conics[g, 1]
        cc = conics[g, 2]
        o = opac[g]
        kf = np.float32(k - k0)
        dx0 = mx - (np.float32(x0) + _FHALF)
        gy0, gy1 = _row_span(my, np.float32(radii[g, 1]), y0, y1)
        for q in range(n_g * _TILE):
            G[q] = _F0
        for py in range(gy0, gy1):
            r = py - y0
            if (rmask >> r) & 1 == 0:
                continue
            dy = my - (np.float32(py) + _FHALF)
            off = r * _TILE
            R = S[off:]  # one view, constant offsets + j >= 0: no wraparound, vectorizes
            half_c_dy2 = _FHALF * cc * dy * dy
            b_dy = cb * dy
            for j in range(_TILE):
                dx = dx0 - np.float32(j)
                power = _FHALF * ca * dx * dx + half_c_dy2 + b_dy * dx
                vis = _exp_neg(power)
                alpha = min(_ALPHA_MAX, o * vis)
                ok = (power >= _F0) & (alpha >= _ALPHA_MIN) & (kf <= R[o_L + j])
                ra = _F1 / (_F1 - alpha)
                t_old = R[o_T + j]
                tn = t_old * ra if ok else t_old
                R[o_T + j] = tn
                S[o_R + j] = _F1 if ok & (o * vis <= _ALPHA_MAX) else _F0
                S[o_R + _TILE + j] = alpha * tn if ok else _F0
                S[o_R + 2 * _TILE + j] = ra
                S[o_R + 3 * _TILE + j] = tn
                S[o_R + 4 * _TILE + j] = _F0
                S[o_R + 5 * _TILE + j] = _F0
                S[o_R + 6 * _TILE + j] = vis
            for ch in range(n_ch):
                col = colors[g, ch]
                v_v = S[o_V + ch * npix + off:]
                b_v = S[o_B + ch * npix + off:]
                g_v = G[(6 + ch) * _TILE:]
                for j in range(_TILE):
                    gv = v_v[j]
                    fac = S[o_R + _TILE + j]
                    S[o_R + 4 * _TILE + j] += col * gv
                    S[o_R + 5 * _TILE + j] += b_v[j] * gv
                    g_v[j] += fac * gv
                    b_v[j] += col * fac
            for j in range(_TILE):
                dx = dx0 - np.float32(j)
                ra = S[o_R + 2 * _TILE + j]
                v_al = S[o_R + j] * (S[o_R + 3 * _TILE + j] * S[o_R + 4 * _TILE + j]
                                     - ra * S[o_R + 5 * _TILE + j] + ra * R[o_E + j])
                vis = S[o_R + 6 * _TILE + j]
                v_sig = -o * vis * v_al
                G[j] += v_sig * (ca * dx + cb * dy)
                G[_TILE + j] += v_sig * (cb * dx + cc * dy)
                G[2 * _TILE + j] += _FHALF * dx * dx * v_sig
                G[3 * _TILE + j] += dx * dy * v_sig
                G[4 * _TILE + j] += _FHALF * dy * dy * v_sig
                G[5 * _TILE + j] += vis * v_al
        row = pair_slot[k]
        for q in range(n_g):
            acc = _F0
            for j in range(_TILE):
                acc += G[q * _TILE + j]
            out_pair[row, q] = acc


@njit(parallel=True, cache=True)
def reduce_pairs(pair_buf, gauss_start, out_v_means2d, out_v_conics, out_v_opac, out_v_colors):
    """Sum each Gaussian's pair rows (Gaussian-major, fixed order: deterministic).

    Args:
        pair_buf [P, 6 + K] float32, gauss_start [N + 1] int64.
    Outputs (overwritten): out_v_means2d [N, 2], out_v_conics [N, 3], out_v_opac [N],
        out_v_colors [N, K], float32.
    """
    n = gauss_start.shape[0] - 1
    n_ch = out_v_colors.shape[1]
    for g in prange(n):
        a0 = 0.0
        a1 = 0.0
        a2 = 0.0
        a3 = 0.0
        a4 = 0.0
        a5 = 0.0
        for ch in range(n_ch):
            out_v_colors[g, ch] = 0.0
        for r in range(gauss_start[g], gauss_start[g + 1]):
            a0 += pair_buf[r, 0]
            a1 += pair_buf[r, 1]
            a2 += pair_buf[r, 2]
            a3 += pair_buf[r, 3]
            a4 += pair_buf[r, 4]
            a5 += pair_buf[r, 5]
            for ch in range(n_ch):
                out_v_colors[g, ch] += pair_buf[r, 6 + ch]
        out_v_means2d[g, 0] = a0
        out_v_means2d[g, 1] = a1
        out_v_conics[g, 0] = a2
        out_v_conics[g, 1] = a3
        out_v_conics[g, 2] = a4
        out_v_opac[g] = a5
