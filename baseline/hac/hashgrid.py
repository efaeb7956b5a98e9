"""HAC's binarized hash grid: one 3D multi-resolution grid plus xy / xz / yz planes (docs/method.md section 3).

One module of about 800 lines: the grid's layout arithmetic, its straight-through binarization,
the hash-bits term and the dispatch to the numba kernels are one component's parts, each
checked against the same layout.

Also a generic binary feature field that a feature provider can reuse as its own grid: every
size is a constructor argument, and several instances can live side by side.

Layout (defaults = HAC, 96 output dims, 1,766,272 binary values):
    3D grid   resolutions (18, 24, 33, 44, 59, 80, 108, 148, 201, 275, 376, 514), table 2^13
    2D planes resolutions (130, 258, 514, 1026), table 2^15, one grid per plane xy, xz, yz
    4 features per table row; output = [3D levels | xy levels | xz levels | yz levels], each
    level contributing its ``n_features`` values (level-major, as HAC's kernel writes them).

Rows of a level = ``ceil(min(2^log2, res^dim) / 8) * 8``. A level is *dense* when
``res^dim <= rows`` (index = x + y*res + z*res^2), else *hashed*: the uint32 XOR of
``coord_d * prime_d`` with primes (1, 2654435761, 805459861), modulo ``rows``.

Interpolation, exactly as HAC's CUDA kernel (``kernel_grid`` in its gridencoder):
    * positions are normalised by the anchor bounds to ``u`` in [0, 1]; a grid whose own input
      coordinates leave [0, 1] outputs zeros (HAC checks per sub-grid: a point outside the box
      in z still gets xy-plane features). ``oob="all"`` zeroes every grid instead;
    * ``pos = u * (res - 2) + 0.5``, ``g = floor(pos)``, ``f = pos - g``;
    * corners ``g`` and ``min(g + 1, res - 1)`` per axis with the usual multilinear weights;
    * a corner with any coordinate equal to 0 or ``res - 1`` is excluded, the remaining weights
      are renormalised by their sum ``wn`` (``wn == 0`` -> 1e-9, i.e. zero output).
    Consequence: only the interior lattice 1..res-2 ever stores features, u = 0 sits half way
    between the excluded corner 0 and corner 1, and u = 1 half way between res-2 and res-1.

Binarization (straight-through): forward ``clamp(p, -1, 1) >= 0 -> +1 else -1``, backward
passes the gradient where ``|p| <= 1``. Parameters are float, initialised U(-1e-4, 1e-4).

The same code computes float32 (training) and float64 features. The *exact* path
(:meth:`BinaryHashGrid.features_fixed`, used by the entropy coder) rounds the per-axis
interpolation weights to integers (units of 2^-15), so every weighted sum is a sum of integers
below 2^53, exact in any order; the rest are gathers and correctly rounded elementwise IEEE
operations (no transcendental functions). Its output is bit-reproducible across thread counts,
SIMD paths and chunkings (see :mod:`baseline.hac.exact`).

Index math runs in int32 on runs of consecutive levels of the same kind (dense; hashed with
power-of-two rows, where ``(coord * prime) mod rows`` is computed as ``coord * (prime mod rows)``);
very large hashed levels fall back to the uint32 hash in int64.
"""
from __future__ import annotations

import math
import os
import weakref
from typing import Dict, Optional, Sequence, Tuple

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

HAC_RESOLUTIONS_3D = (18, 24, 33, 44, 59, 80, 108, 148, 201, 275, 376, 514)
HAC_RESOLUTIONS_2D = (130, 258, 514, 1026)
HAC_LOG2_TABLE_3D = 13
HAC_LOG2_TABLE_2D = 15
HASH_PRIMES = (1, 2654435761, 805459861)
PLANES = {"xy": (0, 1), "xz": (0, 2), "yz": (1, 2)}
_MASK32 = 0xFFFFFFFF
# Fractional bits of the per-axis interpolation weights in the exact (coding) path.
WEIGHT_BITS = 15
# Fractional bits of the exact-path features (multiples of 2^-FEATURE_BITS).
FEATURE_BITS = 20


class STEBinary(torch.autograd.Function):
    """``clamp(x, -1, 1) >= 0 -> +1 else -1``; gradient passes where ``|x| <= 1``."""

    @staticmethod
    def forward(ctx, x):
        ctx.save_for_backward(x)
        # clamp(x, -1, 1) >= 0 is x >= 0 (NaN -> -1 either way); one fused op instead of four.
        return torch.where(x >= 0, 1.0, -1.0).to(x.dtype)

    @staticmethod
    def backward(ctx, grad):
        (x,) = ctx.saved_tensors
        return torch.where(x.abs() <= 1.0, grad, 0.0)


def binarize(x: torch.Tensor) -> torch.Tensor:
    return STEBinary.apply(x)


def level_rows(res: int, dim: int, log2_table: int) -> int:
    """Rows of one level: ``ceil(min(2^log2, res^dim) / 8) * 8``."""
    return int(math.ceil(min(2 ** log2_table, res ** dim) / 8) * 8)


def binary_entropy_bits(binary: torch.Tensor) -> torch.Tensor:
    """HAC's size estimate of a {-1, +1} tensor coded with one global Bernoulli p.

    ``p = n1 / n`` clamped to [1e-6, 1 - 1e-6]; ``bits = -n1 log2 p - n0 log2 (1 - p) + 32``
    (32 bits for p). Differentiable with respect to ``binary`` (through the STE it came from).
    """
    b = (binary.reshape(-1) + 1) / 2
    n = b.numel()
    return _bits_of_count(b.sum(), n)


def _bits_of_count(n1: torch.Tensor, n: int) -> torch.Tensor:
    """The scalar part of :func:`binary_entropy_bits` (``n1``: the count of ones, float)."""
    n0 = n - n1
    p = (n1 / max(n, 1)).clamp(1e-6, 1 - 1e-6)
    return -n1 * torch.log2(p) - n0 * torch.log2(1 - p) + 32


# Below this many entries a float32 sum of 0/1 values is exact in any order, so a count gives
# the same n1 as the sum of the binarized tables.
_EXACT_COUNT = 1 << 24


class _TableBits(torch.autograd.Function):
    """``binary_entropy_bits(cat(binarize(t) for t in tables))`` without materializing the
    binarized tables, their concatenation or the elementwise chain (and its backward) over every
    entry: the bits depend on the tables only through the count of ones, so the forward counts
    (``x >= 0``) and the backward gives every entry ``d bits / d n1 / 2`` where the STE passes
    (``|x| <= 1``). Bit for bit the values and gradients of the unfused form (the scalar part is
    the same ops, differentiated by autograd; ``tests/test_hac_hashgrid.py``)."""

    @staticmethod
    def forward(ctx, *tables):
        n = sum(t.numel() for t in tables)
        count = sum(_count_nonneg(t) for t in tables)
        n1 = torch.tensor(float(count), dtype=tables[0].dtype, device=tables[0].device)
        ctx.save_for_backward(*tables)
        ctx.n1, ctx.n = n1, n
        return _bits_of_count(n1, n)

    @staticmethod
    def backward(ctx, grad):
        with torch.enable_grad():
            n1 = ctx.n1.detach().requires_grad_(True)
            (g_n1,) = torch.autograd.grad(_bits_of_count(n1, ctx.n), n1, grad)
        g = g_n1 / 2
        return tuple(_ste_fill(t, g) for t in ctx.saved_tensors)


def _count_nonneg(t: torch.Tensor) -> int:
    """``int((t >= 0).sum())``; one numba pass over a float32 CPU table."""
    if _BACKEND != "torch" and t.device.type == "cpu" and t.dtype == torch.float32 and t.ndim == 2:
        K, cpu = _grid_kernels()
        with cpu._RUN_LOCK:
            cpu._apply_threads()
            return int(K.count_nonneg(t.detach().contiguous().numpy()))
    return int((t >= 0).sum())


def _ste_fill(t: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """``torch.where(t.abs() <= 1.0, g, 0.0)`` (``g`` a scalar tensor); one numba pass over a
    float32 CPU table."""
    if (_BACKEND != "torch" and t.device.type == "cpu" and t.dtype == torch.float32
            and t.ndim == 2 and g.dtype == torch.float32):
        K, cpu = _grid_kernels()
        out = np.empty(tuple(t.shape), dtype=np.float32)
        with cpu._RUN_LOCK:
            cpu._apply_threads()
            K.ste_fill(t.detach().contiguous().numpy(), np.float32(g.item()), out)
        return torch.from_numpy(out)
    return torch.where(t.abs() <= 1.0, g, 0.0)


def table_bits(tables) -> torch.Tensor:
    """:func:`binary_entropy_bits` of the binarized ``tables`` (float parameters), fused."""
    tables = list(tables)
    if sum(t.numel() for t in tables) > _EXACT_COUNT:     # a float32 sum may round: unfused
        return binary_entropy_bits(torch.cat([binarize(t).reshape(-1) for t in tables]))
    return _TableBits.apply(*tables)


class GridLevels(nn.Module):
    """One multi-resolution grid of dimension ``dim`` (a 3D grid or a 2D plane).

    Parameters: ``params`` [total_rows, n_features] (float; binarised in :meth:`forward`).
    """

    def __init__(self, dim: int, resolutions: Sequence[int], log2_table: int, n_features: int,
                 init_range: float = 1e-4):
        super().__init__()
        if dim not in (2, 3):
            raise ValueError(f"grid dimension must be 2 or 3, got {dim}")
        resolutions = tuple(int(r) for r in resolutions)
        if any(r < 2 for r in resolutions):
            raise ValueError(f"grid resolutions must be >= 2, got {resolutions}")
        self.dim = dim
        self.resolutions = resolutions
        self.log2_table = int(log2_table)
        self.n_features = int(n_features)
        rows = [level_rows(r, dim, log2_table) for r in resolutions]
        offsets = np.concatenate([[0], np.cumsum(rows)]).astype(np.int64)
        self.rows = tuple(rows)
        self.register_buffer("_res", torch.tensor(resolutions, dtype=torch.int64), persistent=False)
        self.register_buffer("_rows", torch.tensor(rows, dtype=torch.int64), persistent=False)
        self.register_buffer("_offsets", torch.from_numpy(offsets[:-1].copy()), persistent=False)
        strides = torch.tensor([[r ** d for d in range(dim)] for r in resolutions], dtype=torch.int64)
        self.register_buffer("_strides", strides, persistent=False)
        # Runs of consecutive levels sharing an index kind: "dense"; "hash32" (power-of-two rows,
        # small enough that (coord * (prime mod rows)) fits int32: (a ^ b) mod 2^k equals
        # (a mod 2^k) ^ (b mod 2^k)); "hash64" (the general uint32 hash, then modulo rows).
        kinds = []
        for r, t in zip(resolutions, rows):
            if r ** dim <= t:
                kinds.append("dense")
            elif t & (t - 1) == 0 and r * t < 2 ** 31:
                kinds.append("hash32")
            else:
                kinds.append("hash64")
        self._runs = []
        for i, k in enumerate(kinds):
            if self._runs and self._runs[-1][2] == k:
                self._runs[-1][1] = i + 1
            else:
                self._runs.append([i, i + 1, k])
        self._runs = [tuple(r) for r in self._runs]
        pmod = torch.tensor([[HASH_PRIMES[d] % t for d in range(dim)] for t in rows], dtype=torch.int64)
        self.register_buffer("_pmod", pmod, persistent=False)
        self._index_dtype = torch.int32 if int(offsets[-1]) < 2 ** 31 else torch.int64
        self.params = nn.Parameter(torch.empty(int(offsets[-1]), self.n_features))
        self.init_range = float(init_range)
        self.reset_parameters()

    def reset_parameters(self, shared: bool = False) -> None:
        """U(-init_range, init_range); ``shared``: every entry at +init_range (one code)."""
        with torch.no_grad():
            if shared:
                self.params.fill_(self.init_range)
            else:
                self.params.uniform_(-self.init_range, self.init_range)

    @property
    def n_levels(self) -> int:
        return len(self.resolutions)

    @property
    def output_dim(self) -> int:
        return self.n_levels * self.n_features

    def _corner_product(self, pair: torch.Tensor, combine) -> torch.Tensor:
        """Combine per-axis candidates [dim, 2, n, L] into per-corner values [2^dim, n, L].

        Corner ``c`` uses candidate ``(c >> d) & 1`` on axis d (HAC's order; axis 0 fastest).
        Values are combined in axis order (``combine(axis_d, acc)``), by broadcasting over the
        contiguous point/level dims (fast inner loops).
        """
        acc = pair[0]
        for d in range(1, self.dim):
            acc = combine(pair[d][:, None], acc[None, :]).flatten(0, 1)
        return acc

    def corner_indices(self, u: torch.Tensor, exact: bool = False):
        """Table row indices and weights of every corner: (idx [n, L, C], w [n, L, C]).

        ``u`` [n, dim] inside [0, 1]; ``C = 2^dim`` corners in HAC's order (bit d of the corner
        number selects the upper neighbour ``min(g + 1, res - 1)`` along axis d). A corner with a
        coordinate equal to 0 or ``res - 1`` gets weight 0. Corner weights are the product of
        the axis weights in axis order (as HAC's kernel).

        ``exact``: per-axis weights are integers in units of 2^-WEIGHT_BITS (upper
        ``round(f * 2^15)``, lower ``2^15 -`` that), so corner weights are integers < 2^45 and
        every sum of them, in any order, is exact in float64.
        """
        res = self._res
        ut = u.T.contiguous()  # [dim, n]
        pos = ut[:, :, None] * (res.to(u.dtype) - 2) + 0.5  # [dim, n, L]
        g = torch.floor(pos)
        f = pos - g
        g = g.to(torch.int32)  # in [0, res - 1] for u in [0, 1]
        hi_cap = (res - 1).to(torch.int32)
        gp = torch.stack([g, torch.minimum(g + 1, hi_cap)], dim=1)  # [dim, 2, n, L]
        if exact:
            w1 = torch.round(f * float(1 << WEIGHT_BITS))
            wp = torch.stack([float(1 << WEIGHT_BITS) - w1, w1], dim=1)
        else:
            wp = torch.stack([1 - f, f], dim=1)
        wp = wp * ((gp > 0) & (gp < hi_cap)).to(wp.dtype)
        w = self._corner_product(wp, torch.mul)  # [C, n, L]
        idx = None
        for a, b, kind in self._runs:
            gl = gp[..., a:b]
            if kind == "dense":
                part = self._corner_product(gl * self._strides[a:b].T.to(torch.int32)[:, None, None, :], torch.add)
            elif kind == "hash32":
                mask = (self._rows[a:b] - 1).to(torch.int32)
                terms = (gl * self._pmod[a:b].T.to(torch.int32)[:, None, None, :]) & mask
                part = self._corner_product(terms, torch.bitwise_xor)
            else:
                primes = torch.tensor(HASH_PRIMES[:self.dim], dtype=torch.int64, device=gl.device)
                terms = (gl.to(torch.int64) * primes[:, None, None, None]) & _MASK32
                part = torch.remainder(self._corner_product(terms, torch.bitwise_xor), self._rows[a:b])
            if len(self._runs) == 1:
                idx = part.to(self._index_dtype)
            else:
                if idx is None:
                    idx = torch.empty(w.shape, dtype=self._index_dtype, device=w.device)
                idx[..., a:b] = part
        idx += self._offsets.to(self._index_dtype)
        return idx.permute(1, 2, 0), w.permute(1, 2, 0)

    def encode(self, u: torch.Tensor, table: torch.Tensor, exact: bool = False,
               signs: bool = False) -> torch.Tensor:
        """Interpolated features [n, L * n_features] of normalised points ``u`` [n, dim].

        ``table`` is the (binarised) parameter table [total_rows, n_features] in ``u``'s dtype;
        with ``signs`` the float parameters, binarised here (straight-through, as
        :func:`binarize`; the numba kernels do it as they read and mask the gradient in their
        backward, so no binarised table is written).
        ``exact`` (float64 only): integer corner weights (see :meth:`corner_indices`), so the
        weighted sums are exact and order-free; the one rounding left is the final division by
        the weight sum, a correctly rounded elementwise operation.
        """
        if not exact and _use_kernels(u, table):
            return _GridKernel.apply(table, u.contiguous(), self, signs)
        if signs:
            table = binarize(table).to(u.dtype)
        if exact and _use_exact_kernel(u, table):
            return _grid_exact_kernel(self, u, table)
        n = u.shape[0]
        inside = ((u >= 0) & (u <= 1)).all(dim=-1)  # NaN counts as outside
        u = torch.where(inside[:, None], u, torch.full_like(u, 0.5))
        idx, w = self.corner_indices(u, exact=exact)  # [n, L, C]
        L, C = idx.shape[1], idx.shape[2]
        idx = idx.reshape(-1, C)
        w = w.reshape(-1, C)  # (copies [C, n, L] into bag-major order)
        if table.requires_grad and torch.is_grad_enabled():
            acc = _WeightedGather.apply(table, idx, w)                     # [n*L, F]
        else:
            acc = F.embedding_bag(idx, table, per_sample_weights=w, mode="sum")  # [n*L, F]
        wn = w.sum(dim=-1).reshape(-1, 1)
        if exact:
            out = acc / torch.where(wn == 0, torch.ones_like(wn), wn)
        else:
            wn = torch.where(wn == 0, torch.full_like(wn, 1e-9), wn)
            out = acc * (1.0 / wn)
        # where, not a product: outside points get +0 (a product gives -0 for negative values),
        # as the fused kernels write
        return torch.where(inside[:, None], out.reshape(n, L * acc.shape[1]), 0.0)


_BACKEND = os.environ.get("PGS_GRID_BACKEND", "auto")


def set_grid_backend(name: str) -> None:
    """Float-path backend of every grid: ``auto`` (numba kernels on the CPU when usable),
    ``numba`` (same; an error where they cannot run) or ``torch`` (plain PyTorch ops)."""
    global _BACKEND
    if name not in ("auto", "numba", "torch"):
        raise ValueError(f"grid backend must be auto, numba or torch, got {name!r}")
    _BACKEND = name


def get_grid_backend() -> str:
    return _BACKEND


def _use_kernels(u: torch.Tensor, table: torch.Tensor) -> bool:
    if _BACKEND == "torch":
        return False
    ok = (u.device.type == "cpu" and table.device.type == "cpu" and u.dtype == torch.float32
          and table.dtype == torch.float32 and not (u.requires_grad and torch.is_grad_enabled()))
    if _BACKEND == "numba" and not ok:
        raise ValueError("grid backend 'numba' needs float32 CPU inputs without a position "
                         "gradient; use 'auto' or 'torch'")
    return ok


def _use_exact_kernel(u: torch.Tensor, table: torch.Tensor) -> bool:
    """The exact path's numba kernel: same bits as the PyTorch float64 path (tested), ~10x
    faster; under the same backend switch as the float kernels."""
    if _BACKEND == "torch":
        return False
    return (u.device.type == "cpu" and table.device.type == "cpu" and u.dtype == torch.float64
            and table.dtype == torch.float64)


def _grid_exact_kernel(g: "GridLevels", u: torch.Tensor, table: torch.Tensor) -> torch.Tensor:
    K, cpu = _grid_kernels()
    un = u.detach().contiguous().numpy()
    out = np.empty((un.shape[0], g.n_levels * table.shape[1]), dtype=np.float64)
    with cpu._RUN_LOCK:
        cpu._apply_threads()
        tab = table.detach().to(torch.int8).contiguous().numpy()   # entries are +-1
        K.grid_fwd_exact(un, tab, *_kernel_meta(g), out)
    return torch.from_numpy(out)


def _kernel_meta(g: "GridLevels"):
    meta = getattr(g, "_kmeta", None)
    if meta is None:
        res = np.asarray(g.resolutions, dtype=np.int64)
        rows = np.asarray(g.rows, dtype=np.int64)
        offsets = np.concatenate([[0], np.cumsum(rows)[:-1]]).astype(np.int64)
        hashed = np.asarray([r ** g.dim > t for r, t in zip(g.resolutions, g.rows)], dtype=np.uint8)
        strides = np.asarray([[r ** d for d in range(g.dim)] for r in g.resolutions], dtype=np.int64)
        meta = g._kmeta = (res, rows, offsets, hashed, strides)
    return meta


def _float_meta(g: "GridLevels"):
    """The float kernels' level description: ``hashed`` replaced by the level kinds."""
    meta = getattr(g, "_kmeta_float", None)
    if meta is None:
        from . import _grid_kernels as K

        res, rows, offsets, hashed, strides = _kernel_meta(g)
        meta = g._kmeta_float = (res, rows, offsets, K.level_kinds(rows, hashed), strides)
    return meta


def _grid_kernels():
    """The numba grid kernels, sharing the CPU rasterizer's thread settings and launch lock."""
    from baseline.render import cpu as _cpu

    _cpu.configure_numba()
    from . import _grid_kernels as K
    return K, _cpu


class _GridKernel(torch.autograd.Function):
    """Fused interpolation of one :class:`GridLevels` (numba); gradient to the table only.

    ``signs``: ``table`` holds the float parameters, read as their binarization, and the
    gradient is the straight-through one (zero where ``|table| > 1``): :class:`STEBinary` and
    this function in one, the same values and gradients."""

    @staticmethod
    def forward(ctx, table, u, grid, signs=False):
        K, cpu = _grid_kernels()
        meta = _float_meta(grid)
        un = u.detach().numpy()
        tn = table.detach().contiguous().numpy()
        out = np.empty((un.shape[0], grid.n_levels * tn.shape[1]), dtype=np.float32)
        with cpu._RUN_LOCK:
            cpu._apply_threads()
            K.grid_fwd(un, tn, *meta, out, signs)
        ctx.save_for_backward(u, table if signs else None)
        ctx.grid = grid
        ctx.signs = signs
        ctx.table_shape = tuple(table.shape)
        return torch.from_numpy(out)

    @staticmethod
    def backward(ctx, gout):
        if not ctx.needs_input_grad[0]:
            return None, None, None, None
        u, table = ctx.saved_tensors
        K, cpu = _grid_kernels()
        gt = np.zeros(ctx.table_shape, dtype=np.float32)
        with cpu._RUN_LOCK:
            nt = cpu._apply_threads()
            K.grid_bwd(u.numpy(), gout.detach().to(torch.float32).contiguous().numpy(),
                       *_float_meta(ctx.grid), gt, nt)
            if ctx.signs:
                K.ste_mask(table.detach().contiguous().numpy(), gt)
        return torch.from_numpy(gt), None, None, None


class _WeightedGather(torch.autograd.Function):
    """``out[b] = sum_c w[b, c] * table[idx[b, c]]`` with a scatter-add backward.

    The forward is ``embedding_bag`` (fast). Its own dense backward sorts the indices and was
    measured 6x slower than one ``index_add_`` here (170 ms vs 30 ms for 360k bags of 8 on 2
    cores), which made the context/SFP grids the largest cost of a training step.
    """

    @staticmethod
    def forward(ctx, table, idx, w):
        ctx.save_for_backward(idx, w)
        ctx.rows = table.shape[0]
        return F.embedding_bag(idx, table, per_sample_weights=w, mode="sum")

    @staticmethod
    def backward(ctx, g):
        idx, w = ctx.saved_tensors
        src = (w[..., None].to(g.dtype) * g[:, None, :]).reshape(-1, g.shape[-1])
        gt = torch.zeros(ctx.rows, g.shape[-1], dtype=g.dtype, device=g.device)
        gt.index_add_(0, idx.reshape(-1).long(), src)
        return gt, None, None


def contract_unit(u: torch.Tensor) -> torch.Tensor:
    """Scene contraction of box-normalised positions ``u`` [N, 3] (the box is [0, 1]^3) into
    [0, 1)^3: the box maps linearly onto the middle half [1/4, 3/4]^3 and the space outside it
    into the outer quarters, by the L-infinity contraction used by MERF and nerfstudio's
    ``SceneContraction``: with v = 2u - 1 and n = max|v_i|, v -> (2 - 1/n) v / n where n > 1.
    Every operation is a correctly rounded IEEE one, so float64 inputs give reproducible bits."""
    v = 2.0 * u - 1.0
    n = v.abs().amax(dim=-1, keepdim=True)
    big = n > 1.0
    n = torch.where(big, n, torch.ones_like(n))
    v = torch.where(big, v * ((2.0 - 1.0 / n) / n), v)
    return (v + 2.0) / 4.0


class BinaryHashGrid(nn.Module):
    """HAC's mixed 3D grid + 2D planes with binarised entries; a generic binary feature field.

    Args:
        resolutions_3d, log2_table_3d: the 3D grid (empty resolutions -> no 3D grid).
        resolutions_2d, log2_table_2d: the planes (empty -> no planes).
        n_features: features per table row.
        planes: which 2D planes, from ("xy", "xz", "yz").
        init_range: parameters start U(-init_range, init_range).
        oob: "per_grid" (HAC: each grid zeroes when its own input coordinates leave [0, 1]) or
            "all" (any coordinate outside zeroes every grid).
        chunk: points per vectorised chunk (memory bound).

    Buffers ``xyz_min``/``xyz_max`` [3] (float32) hold the normalisation bounds (:meth:`set_bounds`).
    ``contract`` (attribute, set by the owner from its config; default False): the bounds fill
    the middle half of the unit cube and the space outside them is contracted into the rest
    (:func:`contract_unit`).
    ``forward(xyz [N, 3]) -> [N, output_dim]`` in ``xyz``'s floating dtype.
    """

    def __init__(self,
                 resolutions_3d: Sequence[int] = HAC_RESOLUTIONS_3D,
                 log2_table_3d: int = HAC_LOG2_TABLE_3D,
                 resolutions_2d: Sequence[int] = HAC_RESOLUTIONS_2D,
                 log2_table_2d: int = HAC_LOG2_TABLE_2D,
                 n_features: int = 4,
                 planes: Sequence[str] = ("xy", "xz", "yz"),
                 init_range: float = 1e-4,
                 oob: str = "per_grid",
                 chunk: int = 65536):
        super().__init__()
        self.contract = False
        if oob not in ("per_grid", "all"):
            raise ValueError(f"oob must be 'per_grid' or 'all', got {oob!r}")
        for p in planes:
            if p not in PLANES:
                raise ValueError(f"unknown plane {p!r}; choose from {sorted(PLANES)}")
        self.config = dict(resolutions_3d=tuple(int(r) for r in resolutions_3d),
                           log2_table_3d=int(log2_table_3d),
                           resolutions_2d=tuple(int(r) for r in resolutions_2d),
                           log2_table_2d=int(log2_table_2d), n_features=int(n_features),
                           planes=tuple(planes), init_range=float(init_range), oob=oob)
        self.oob = oob
        self.chunk = int(chunk)
        self.grids = nn.ModuleDict()
        self._axes: Dict[str, Tuple[int, ...]] = {}
        if len(resolutions_3d):
            self.grids["xyz"] = GridLevels(3, resolutions_3d, log2_table_3d, n_features, init_range)
            self._axes["xyz"] = (0, 1, 2)
        if len(resolutions_2d):
            for p in planes:
                self.grids[p] = GridLevels(2, resolutions_2d, log2_table_2d, n_features, init_range)
                self._axes[p] = PLANES[p]
        if not len(self.grids):
            raise ValueError("the grid needs at least one 3D level or one plane level")
        self.register_buffer("xyz_min", torch.zeros(3))
        self.register_buffer("xyz_max", torch.ones(3))

    def __getstate__(self):
        """Pickling and deep copies leave out :meth:`shared_query`'s entry (a weak reference
        and a tensor of the last step's graph)."""
        state = dict(super().__getstate__())
        state.pop("_memo", None)
        return state

    # ----------------------------------------------------------------- sizes
    @property
    def output_dim(self) -> int:
        return sum(g.output_dim for g in self.grids.values())

    @property
    def n_binary(self) -> int:
        """Number of binary values stored (table entries)."""
        return sum(g.params.numel() for g in self.grids.values())

    def reset_parameters(self, shared: bool = False) -> None:
        """Random entries (HAC's start), or with ``shared`` every entry at +init_range: every
        point then reads the same binarized code until the entries move."""
        for g in self.grids.values():
            g.reset_parameters(shared=shared)

    # ---------------------------------------------------------------- bounds
    def set_bounds(self, xyz_min, xyz_max) -> None:
        """Set the normalisation box (stored as float32; the bitstream keeps these values)."""
        lo = torch.as_tensor(xyz_min, dtype=torch.float32).reshape(3)
        hi = torch.as_tensor(xyz_max, dtype=torch.float32).reshape(3)
        if not (torch.isfinite(lo).all() and torch.isfinite(hi).all()) or (hi <= lo).any():
            raise ValueError(f"invalid grid bounds min={lo.tolist()} max={hi.tolist()}")
        self.xyz_min.copy_(lo.to(self.xyz_min.device))
        self.xyz_max.copy_(hi.to(self.xyz_max.device))

    def normalize(self, xyz: torch.Tensor) -> torch.Tensor:
        lo = self.xyz_min.to(device=xyz.device, dtype=xyz.dtype)
        hi = self.xyz_max.to(device=xyz.device, dtype=xyz.dtype)
        u = (xyz - lo) / (hi - lo)
        return contract_unit(u) if self.contract else u

    # --------------------------------------------------------------- tables
    def binary_tables(self) -> Dict[str, torch.Tensor]:
        """Binarised tables (STE), name -> [rows, n_features] in {-1, +1}."""
        return {k: binarize(g.params) for k, g in self.grids.items()}

    def hash_bits(self) -> torch.Tensor:
        """Estimated size in bits of the binarised tables (differentiable via the STE)."""
        return table_bits(g.params for g in self.grids.values())

    def binary_values(self) -> np.ndarray:
        """All binary entries as uint8 {0, 1} in the canonical order (grid order, row-major)."""
        with torch.no_grad():
            bits = [(g.params.detach().clamp(-1, 1) >= 0).reshape(-1).cpu() for g in self.grids.values()]
        return torch.cat(bits).numpy().astype(np.uint8)

    def load_binary_values(self, bits) -> None:
        """Set the tables from {0, 1} entries (as decoded): parameters become exactly +-1."""
        bits = np.asarray(bits).reshape(-1)
        if bits.size != self.n_binary:
            raise ValueError(f"expected {self.n_binary} binary values, got {bits.size}")
        off = 0
        with torch.no_grad():
            for g in self.grids.values():
                n = g.params.numel()
                b = torch.from_numpy(bits[off:off + n].astype(np.float32)).reshape(g.params.shape)
                g.params.copy_((b * 2 - 1).to(g.params.device))
                off += n

    @torch.no_grad()
    def used_values(self, xyz: torch.Tensor) -> np.ndarray:
        """bool [n_binary] (canonical order): the entries some point of ``xyz`` [N, 3] reads.

        An entry is used when it is a corner with a nonzero weight for some point, on the float
        path (float32 normalisation, as rendering queries) or the exact coding path (float64);
        the union of both. Every other entry can take any value without changing a feature at
        these points (its weight is 0 on both paths), so a codec that knows the points can skip it.
        (Another device's float32 could put a point that sits within an ulp of a cell boundary
        in the neighbouring cell; the corner that changes then has a weight of about that ulp.)
        """
        x = xyz.detach().cpu()
        lo64, hi64 = self.xyz_min.detach().cpu().double(), self.xyz_max.detach().cpu().double()
        u64 = (x.double() - lo64) / (hi64 - lo64)
        paths = [(self.normalize(x.float().to(self.xyz_min.device)).cpu(), False),
                 (contract_unit(u64) if self.contract else u64, True)]
        out = []
        for k, g in self.grids.items():
            n_rows = g.params.shape[0]
            rows = torch.zeros(n_rows + 1, dtype=torch.bool)    # the last slot: weight-0 corners
            for u, exact in paths:
                uc = u[:, list(self._axes[k])]
                inside = ((uc >= 0) & (uc <= 1)).all(dim=-1)
                if self.oob == "all":
                    inside &= ((u >= 0) & (u <= 1)).all(dim=-1)
                ui, step = uc[inside], self.chunk or 65536
                for s in range(0, ui.shape[0], step):
                    idx, w = g.corner_indices(ui[s:s + step], exact=exact)
                    rows[torch.where(w > 0, idx.long(), n_rows).reshape(-1)] = True
            out.append(np.repeat(rows[:n_rows].numpy(), g.params.shape[1]))
        return np.concatenate(out) if out else np.zeros(0, dtype=bool)

    def encode_bits(self, used: Optional[np.ndarray] = None) -> bytes:
        """The binarised tables, Bernoulli range coded with one global p (~1 bit per entry).

        ``used`` (bool [n_binary], :meth:`used_values` of the points the decoder will know):
        code those entries only."""
        from baseline.codec.rangecoder import encode_bernoulli

        vals = self.binary_values()
        return encode_bernoulli(vals if used is None else vals[used])

    def decode_bits(self, blob: bytes, used: Optional[np.ndarray] = None) -> None:
        """Inverse of :meth:`encode_bits` (with the same ``used``); skipped entries become +1."""
        from baseline.codec.rangecoder import decode_bernoulli

        if used is None:
            self.load_binary_values(decode_bernoulli(blob, expected_n=self.n_binary))
            return
        used = np.asarray(used, dtype=bool)
        if used.size != self.n_binary:
            raise ValueError(f"used mask of {used.size} entries for {self.n_binary}")
        full = np.ones(self.n_binary, dtype=np.uint8)
        full[used] = decode_bernoulli(blob, expected_n=int(used.sum()))
        self.load_binary_values(full)

    # ---------------------------------------------------------------- query
    def forward(self, xyz: torch.Tensor, normalized: bool = False, exact: bool = False) -> torch.Tensor:
        """Features [N, output_dim] of world positions ``xyz`` [N, 3] (or normalised ones).

        ``exact``: the bit-reproducible coding path (float64 on the CPU, integer interpolation
        weights, output rounded to multiples of 2^-FEATURE_BITS); see :meth:`features_fixed`.
        """
        if exact:
            return self.features_fixed(xyz, normalized=normalized) * (2.0 ** -FEATURE_BITS)
        if xyz.ndim != 2 or xyz.shape[1] != 3:
            raise ValueError(f"positions must be [N, 3], got {tuple(xyz.shape)}")
        if not xyz.is_floating_point():
            xyz = xyz.float()
        u = xyz if normalized else self.normalize(xyz)
        if _use_kernels(u, next(iter(self.grids.values())).params):
            # the kernels binarize as they read: the parameters go in as they are
            return self._query(u, {k: g.params for k, g in self.grids.items()}, exact=False,
                               signs=True)
        tables = {k: t.to(u.dtype) for k, t in self.binary_tables().items()}
        return self._query(u, tables, exact=False)

    def shared_query(self, xyz: torch.Tensor) -> torch.Tensor:
        """``self(xyz)``, computed once for one position tensor: two users of one grid that
        query the same positions in one step (a feature provider and an entropy context
        reading the provider's grid, ``entropy.context = "provider"``) share the pass and its
        backward. The result is reused only for the very same ``xyz`` object, unmodified
        (its version), while no table has changed (the optimizer's in-place step bumps their
        versions; a load that swaps a table's storage moves its address); otherwise it is
        computed anew. Holds one entry, and only with gradients on (a training step): a pass
        without them (evaluation, a decoded model's feature cache) is neither kept nor reused."""
        if not torch.is_grad_enabled():
            return self(xyz)
        key = (xyz._version,
               tuple((g.params._version, g.params.data_ptr()) for g in self.grids.values()))
        memo = getattr(self, "_memo", None)
        if memo is not None and memo[0]() is xyz and memo[1] == key:
            return memo[2]
        out = self(xyz)
        self._memo = (weakref.ref(xyz), key, out)
        return out

    @torch.no_grad()
    def features_fixed(self, xyz: torch.Tensor, normalized: bool = False) -> torch.Tensor:
        """Bit-reproducible features as integers (float64 tensor) in units of 2^-FEATURE_BITS.

        Runs in float64 on the CPU whatever the module's device. Every step is either a gather,
        a correctly rounded elementwise IEEE operation in a fixed order, or a sum of integers
        below 2^53 (exact in any order), so the result does not depend on the thread count,
        SIMD width or BLAS: encoder and decoder get identical bits.
        """
        if xyz.ndim != 2 or xyz.shape[1] != 3:
            raise ValueError(f"positions must be [N, 3], got {tuple(xyz.shape)}")
        x = xyz.detach().to(device="cpu", dtype=torch.float64)
        if normalized:
            u = x
        else:
            lo = self.xyz_min.detach().to(device="cpu", dtype=torch.float64)
            hi = self.xyz_max.detach().to(device="cpu", dtype=torch.float64)
            u = (x - lo) / (hi - lo)
            u = contract_unit(u) if self.contract else u
        tables = {k: t.detach().to(device="cpu", dtype=torch.float64)
                  for k, t in self.binary_tables().items()}
        out = self._query(u, tables, exact=True)
        return torch.round(out * float(1 << FEATURE_BITS))

    def _query(self, u: torch.Tensor, tables: Dict[str, torch.Tensor], exact: bool,
               signs: bool = False) -> torch.Tensor:
        outs = []
        # The numba kernels need no temporaries per corner: one call for all points.
        t0 = next(iter(tables.values()))
        fused = _use_exact_kernel(u, t0) if exact else _use_kernels(u, t0)
        step = max(u.shape[0], 1) if fused else self.chunk
        for s in range(0, max(u.shape[0], 1), step):
            uc = u[s:s + step]
            parts = [g.encode(uc[:, list(self._axes[k])], tables[k], exact=exact, signs=signs)
                     for k, g in self.grids.items()]
            out = torch.cat(parts, dim=-1)
            if self.oob == "all":
                inside = ((uc >= 0) & (uc <= 1)).all(dim=-1)
                out = out * inside[:, None].to(out.dtype)
            outs.append(out)
        return torch.cat(outs, dim=0) if len(outs) > 1 else outs[0]

    def extra_repr(self) -> str:
        c = self.config
        return (f"3d={c['resolutions_3d']} 2^{c['log2_table_3d']}, 2d={c['resolutions_2d']} "
                f"2^{c['log2_table_2d']} {c['planes']}, F={c['n_features']}, out={self.output_dim}, "
                f"binary={self.n_binary}")


def warm_kernels() -> None:
    """Compile (or load from numba's disk cache) every grid kernel a training and a decode use:
    the float32 interpolation forward/backward and the float64 exact path, for 3D levels and
    planes, on a tiny grid. Called by ``pgs warmup`` (the set-up of ``run.sh``) so that a first
    training does not pay the compile."""
    if _BACKEND == "torch":
        return
    g = BinaryHashGrid(resolutions_3d=(4, 16), log2_table_3d=6, resolutions_2d=(4, 16),
                       log2_table_2d=6)
    x = torch.rand(64, 3, generator=torch.Generator().manual_seed(0))
    (g(x).sum() + g.hash_bits()).backward()
    g(x, exact=True)


def auto_grid_layout(n_anchors: int, bounds=None, voxel_size: Optional[float] = None, *,
                     resolutions_3d: Sequence[int] = HAC_RESOLUTIONS_3D,
                     resolutions_2d: Sequence[int] = HAC_RESOLUTIONS_2D,
                     max_log2_table_3d: int = HAC_LOG2_TABLE_3D,
                     max_log2_table_2d: int = HAC_LOG2_TABLE_2D,
                     rows_per_anchor: float = 4.0, cells_per_anchor_axis: float = 2.0,
                     min_log2_table: int = 6, min_levels: int = 1) -> dict:
    """Constructor arguments of :class:`BinaryHashGrid` sized for a scene with ``n_anchors``.

    The rule (documented choice; HAC itself always uses the full layout):

    * Table size: an anchor touches at most 8 (3D) or 4 (2D) rows per level, and a table row that
      no anchor touches is dead weight in the bitstream. The table is the next power of two of
      ``rows_per_anchor * n_anchors`` (default 4x), clamped to [2^min_log2_table, HAC's size].
    * Levels: anchors sample surfaces, so along one axis there are about ``sqrt(n_anchors)``
      distinct anchor positions. A level whose interior cell count ``res - 2`` exceeds
      ``cells_per_anchor_axis * sqrt(n_anchors)`` cannot be resolved by the anchors and is
      dropped. With ``bounds`` ([2, 3] min/max) and ``voxel_size`` a level is also dropped when
      its cell ``extent / (res - 2)`` is finer than the voxel size (nothing lives below it).
      The coarsest ``min_levels`` levels of each grid are always kept.

    For an average Mip-NeRF360 scene (~500k anchors) this returns exactly HAC's layout.
    """
    n = max(int(n_anchors), 1)
    log2 = int(math.ceil(math.log2(max(rows_per_anchor * n, 2))))
    log2_3d = int(min(max(log2, min_log2_table), max_log2_table_3d))
    log2_2d = int(min(max(log2, min_log2_table), max_log2_table_2d))
    max_cells = cells_per_anchor_axis * math.sqrt(n)
    if bounds is not None and voxel_size is not None and voxel_size > 0:
        b = np.asarray(bounds, dtype=np.float64).reshape(2, 3)
        extent = float((b[1] - b[0]).max())
        max_cells = min(max_cells, extent / float(voxel_size))

    def keep(resolutions):
        res = sorted(int(r) for r in resolutions)
        kept = [r for r in res if (r - 2) <= max_cells]
        if len(kept) < min(min_levels, len(res)):
            kept = res[:min(min_levels, len(res))]
        return tuple(kept)

    return dict(resolutions_3d=keep(resolutions_3d), log2_table_3d=log2_3d,
                resolutions_2d=keep(resolutions_2d), log2_table_2d=log2_2d)
