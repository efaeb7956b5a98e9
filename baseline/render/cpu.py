"""Compiled CPU backend: numba kernels wrapped as two ``torch.autograd.Function`` objects.

``_Project`` (means, quats, scales -> means2d, conics, ...) and ``_Rasterize`` (means2d, conics,
opacities, colors, background -> image, alpha) are separate so that ``means2d`` is a real node
of the autograd graph: ``means2d.retain_grad()`` then gives dLoss/d(means2d) in pixels, as in
gsplat. Kernels live in :mod:`baseline.render._kernels` (forward and backward of projection,
tile binning, compositing, per-pair gradient reduction); this module only converts tensors.

Threads: the kernels use ``numba.set_num_threads(n)`` before every call, with ``n`` from
:func:`set_num_threads` or else ``torch.get_num_threads()`` (capped by numba's pool size,
``NUMBA_NUM_THREADS``). First use compiles the kernels (15-30 s); the machine code is
cached on disk by numba (``cache=True``, in ``__pycache__`` next to the module or under
``NUMBA_CACHE_DIR``) and the wait is announced with one line on stderr.

Cold and warm processes run the same machine code: a cold cache is filled by a child process,
and this process then loads the kernels from the cache. (Compiled in-process, the fast-math
tile kernels came out with a different summation order than the same kernels loaded from the
cache: backward gradients differed by ~1e-7 relative, and a 1k-iteration training with a cold
cache ended elsewhere than with a warm one.) Where the cache cannot be written the kernels are
compiled in-process, with a warning.

Threading layer: unless the user chose one (``NUMBA_THREADING_LAYER`` or
``numba.config.THREADING_LAYER``), numba's ``workqueue`` layer is selected before the first
parallel launch (training starts numba's default instead: see :func:`configure_numba`).
GNU OpenMP (numba's default here) keeps its workers spinning after each kernel; on a busy
2-core machine that was measured to slow the small PyTorch conversions between the kernels
~50x (about 50 ms per 50k-Gaussian forward), and it is not fork-safe (data-loader workers).
``workqueue`` is not safe for concurrent calls from several Python threads, so kernel launches
here are serialized by a lock.
Tiles differ a lot in cost, so the raster kernels are scheduled dynamically in small chunks
(``numba.parallel_chunksize``).
"""
from __future__ import annotations

import logging
import os
import sys
import threading
import time
from typing import Optional

import numpy as np
import torch
from torch import Tensor

from .conventions import (ALPHA_MIN, CLIP_MARGIN, EPS2D, EXTEND_MAX, TILE_SIZE, RenderOutput,
                          check_inputs)

log = logging.getLogger(__name__)

_K = None
_K_LOCK = threading.Lock()
_RUN_LOCK = threading.RLock()  # serializes kernel launches (workqueue layer is not threadsafe)
_TILE_CHUNK = 2  # tiles handed to a thread at a time
_THREADS: Optional[int] = None
COMPILE_MESSAGE = "compiling CPU rasterizer kernels (first use, cached afterwards)..."


def set_num_threads(n: Optional[int]) -> None:
    """Threads used by the CPU kernels; ``None`` follows ``torch.get_num_threads()``."""
    global _THREADS
    if n is not None and int(n) < 1:
        raise ValueError(f"thread count must be >= 1, got {n}")
    _THREADS = None if n is None else int(n)


def get_num_threads() -> int:
    """Threads the CPU kernels will use (after capping by numba's thread pool size)."""
    import numba

    n = _THREADS if _THREADS is not None else torch.get_num_threads()
    return max(1, min(int(n), int(numba.config.NUMBA_NUM_THREADS)))


def _apply_threads() -> int:
    import numba

    configure_numba()
    n = get_num_threads()
    numba.set_num_threads(n)
    return n


def _cache_is_warm(dispatcher) -> bool:
    try:
        return os.path.exists(dispatcher._cache._cache_file._index_path)
    except Exception:  # private numba API: be conservative and announce
        return False


def kernels():
    """The kernel module, compiled (or loaded from numba's disk cache) on first use."""
    global _K
    if _K is not None:
        return _K
    with _K_LOCK:
        if _K is not None:
            return _K
        configure_numba()
        from . import _kernels as K

        fns = (K.project_fwd, K.project_bwd, K.bin_pairs, K.raster_fwd, K.raster_bwd,
               K.reduce_pairs, K.depth_order, K._fwd_tile3, K._fwd_tile_any, K._bwd_tile3,
               K._bwd_tile_any)
        cold = not all(_cache_is_warm(f) for f in fns)
        if cold:
            print(COMPILE_MESSAGE, file=sys.stderr, flush=True)
            log.info(COMPILE_MESSAGE)
            if os.environ.get(_CHILD_ENV) != "1" and _compile_in_child():
                cold = not all(_cache_is_warm(f) for f in fns)
            if cold and os.environ.get(_CHILD_ENV) != "1":
                print("warning: the numba cache cannot be written: CPU rasterizer kernels "
                      "compiled in this process (results may differ from a cached run's in "
                      "the last float bits)", file=sys.stderr, flush=True)
        t0 = time.perf_counter()
        _warmup(K)
        dt = time.perf_counter() - t0
        if cold:
            log.info("CPU rasterizer kernels compiled in %.1f s", dt)
        elif dt > 3.0:  # a stale cache (changed source, other CPU) was recompiled
            print(f"CPU rasterizer kernels recompiled ({dt:.0f} s, cached afterwards)",
                  file=sys.stderr, flush=True)
        _K = K
        return _K


_CHILD_ENV = "PGS_NUMBA_COMPILE_CHILD"


def _compile_in_child() -> bool:
    """Compile the kernels into numba's disk cache in a child process (same interpreter,
    environment and cache location). True when the child succeeded.

    The child runs in the folder this ``baseline`` package was imported from: ``python -c``
    puts its working directory first on ``sys.path``, so from another checkout's folder it
    would compile (and cache) that checkout's kernels instead of these."""
    import subprocess
    from pathlib import Path

    env = dict(os.environ, **{_CHILD_ENV: "1"})
    code = "from baseline.render.cpu import kernels; kernels()"
    root = Path(__file__).resolve().parents[2]
    try:
        r = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                           text=True, timeout=1800, cwd=root)
    except (OSError, subprocess.SubprocessError) as e:
        log.warning("compiling the CPU kernels in a child process failed: %s", e)
        return False
    if r.returncode != 0:
        log.warning("compiling the CPU kernels in a child process failed: %s", r.stderr[-2000:])
    return r.returncode == 0


_NUMBA_STARTED = False


def configure_numba(layer: str = "workqueue") -> None:
    """Select numba's threading layer (unless the user chose one) and start its thread pool,
    keeping torch's thread count. Only the first call in a process has an effect.

    ``layer``: ``"workqueue"`` (the renderer's choice, see the module docstring) or
    ``"default"`` (numba's own order: GNU OpenMP here, tbb not being installed).
    :func:`baseline.train.trainer.set_threads` asks for ``"default"``, so a ``pgs train``
    process trains with OpenMP, as before; ``pgs compare`` renders before it trains, so its
    trainings have used ``workqueue``. Measured on 2 cores: one training at 2 threads, OpenMP
    faster (truck ``-r 4`` first 500 iterations 0.195 vs 0.220 s/it; synthetic scene 0.086 vs
    0.107); two 1-thread trainings side by side, ``workqueue`` faster (synthetic 0.103-0.105 vs
    0.113-0.124 s/it). ``NUMBA_THREADING_LAYER`` picks one for any process.

    Starting the OpenMP layer resets the calling thread's OpenMP thread count to
    ``NUMBA_NUM_THREADS`` (numba and torch share one ``libgomp``): before this restored it,
    ``train.threads = 1`` ran torch and the kernels on 2 threads, and two such trainings side
    by side ran 4 spinning threads on 2 cores (3.2 s/it on truck's first iterations instead of
    0.23).
    """
    global _NUMBA_STARTED
    if _NUMBA_STARTED:
        return
    import numba

    if ("NUMBA_THREADING_LAYER" not in os.environ and numba.config.THREADING_LAYER == "default"
            and layer != "default"):
        numba.config.THREADING_LAYER = layer  # no-op once numba has launched threads
    n = torch.get_num_threads()
    numba.get_num_threads()  # launches the pool
    if torch.get_num_threads() != n:
        torch.set_num_threads(n)
    _NUMBA_STARTED = True


def _warmup(K) -> None:
    """Run every kernel once on a tiny scene with the exact argument types used later."""
    n = 3
    means = np.array([[0.0, 0.0, 2.0], [0.1, 0.0, 3.0], [5.0, 5.0, -1.0]])
    quats = np.array([[1.0, 0.0, 0.0, 0.0]] * n)
    scales = np.full((n, 3), 0.1)
    opac = np.full(n, 0.5)
    colors = np.ones((n, 3), np.float32)
    cam = _CamParams(np.eye(4), 8.0, 8.0, 4.0, 4.0, 8, 8, 0.01, 1e10)
    proj = _project_np(K, means, quats, scales, opac, cam)
    st = _raster_fwd_np(K, proj, opac.astype(np.float32), colors, np.zeros(3, np.float32), cam)
    _raster_bwd_np(K, proj, opac.astype(np.float32), colors, np.zeros(3, np.float32), cam, st,
                   np.ones((8, 8, 3), np.float32), np.ones((8, 8), np.float32))
    _project_bwd_np(K, means, quats, scales, cam, proj, np.ones((n, 2)), np.ones((n, 3)))


class _CamParams:
    """Camera as plain numbers for the kernels."""

    __slots__ = ("viewmat", "fx", "fy", "cx", "cy", "width", "height", "near", "far",
                 "tiles_x", "tiles_y")

    def __init__(self, viewmat, fx, fy, cx, cy, width, height, near, far):
        self.viewmat = np.ascontiguousarray(viewmat, dtype=np.float64)
        self.fx, self.fy, self.cx, self.cy = float(fx), float(fy), float(cx), float(cy)
        self.width, self.height = int(width), int(height)
        self.near, self.far = float(near), float(far)
        self.tiles_x = (self.width + TILE_SIZE - 1) // TILE_SIZE
        self.tiles_y = (self.height + TILE_SIZE - 1) // TILE_SIZE

    @classmethod
    def from_camera(cls, camera) -> "_CamParams":
        vm = camera.viewmat.detach().to("cpu", torch.float64).numpy()
        return cls(vm, camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height,
                   camera.near, camera.far)


class _Proj:
    """Projection results (NumPy, float64 except radii/rect)."""

    __slots__ = ("means2d", "conics", "depths", "radii", "rect")

    def __init__(self, n):
        self.means2d = np.empty((n, 2))
        self.conics = np.empty((n, 3))
        self.depths = np.empty(n)
        self.radii = np.empty((n, 2), np.int32)
        self.rect = np.empty((n, 4), np.int32)


def _project_np(K, means, quats, scales, opac, cam: _CamParams) -> _Proj:
    p = _Proj(means.shape[0])
    with _RUN_LOCK:
        _apply_threads()
        K.project_fwd(means, quats, scales, opac, cam.viewmat, cam.fx, cam.fy, cam.cx, cam.cy,
                      cam.width, cam.height, cam.near, cam.far, EPS2D, ALPHA_MIN, EXTEND_MAX,
                      CLIP_MARGIN, cam.tiles_x, cam.tiles_y, p.means2d, p.conics, p.depths,
                      p.radii, p.rect)
    return p


def _project_bwd_np(K, means, quats, scales, cam: _CamParams, proj: _Proj, v_means2d, v_conics):
    n = means.shape[0]
    v_means = np.empty((n, 3))
    v_quats = np.empty((n, 4))
    v_scales = np.empty((n, 3))
    with _RUN_LOCK:
        _apply_threads()
        K.project_bwd(means, quats, scales, cam.viewmat, cam.fx, cam.fy, cam.cx, cam.cy,
                      cam.width, cam.height, CLIP_MARGIN, proj.radii, proj.conics,
                      np.ascontiguousarray(v_means2d, dtype=np.float64),
                      np.ascontiguousarray(v_conics, dtype=np.float64), v_means, v_quats,
                      v_scales)
    return v_means, v_quats, v_scales


class _RasterState:
    """What the forward keeps for the backward (NumPy arrays)."""

    __slots__ = ("means2d", "conics", "tile_start", "pair_gauss", "pair_slot", "gauss_start",
                 "pair_rows", "T", "last", "n_pairs")


def _sorted_visible(K, depths: np.ndarray, radii: np.ndarray, rect: np.ndarray) -> np.ndarray:
    """[M] int64 ids of binned Gaussians, front to back (stable: ties keep index order)."""
    vis = np.nonzero((radii.max(axis=1) > 0) & (rect[:, 2] > rect[:, 0])
                     & (rect[:, 3] > rect[:, 1]))[0]
    return K.depth_order(depths, np.ascontiguousarray(vis, dtype=np.int64))


def _raster_fwd_np(K, proj: _Proj, opac32, colors32, bg32, cam: _CamParams,
                   means2d32=None, conics32=None):
    st = _RasterState()
    st.means2d = proj.means2d.astype(np.float32) if means2d32 is None else means2d32
    st.conics = proj.conics.astype(np.float32) if conics32 is None else conics32
    order = _sorted_visible(K, proj.depths, proj.radii, proj.rect)
    n_tiles = cam.tiles_x * cam.tiles_y
    h, w, c = cam.height, cam.width, colors32.shape[1]
    image = np.empty((h, w, c), np.float32)
    st.T = np.empty((h, w), np.float32)
    st.last = np.empty((h, w), np.int64)
    import numba

    with _RUN_LOCK:
        n_threads = _apply_threads()
        n_chunks = max(1, min(4 * n_threads, order.shape[0]))
        st.tile_start, st.pair_gauss, st.pair_slot, st.gauss_start = K.bin_pairs(
            order, proj.rect, cam.tiles_x, n_tiles, n_chunks)
        st.n_pairs = int(st.pair_gauss.shape[0])
        if n_tiles and int(np.diff(st.tile_start).max()) >= 1 << 24:
            raise ValueError("more than 2^24 Gaussians overlap one 16x16 tile; the CPU "
                             "rasterizer stores tile-local indices as float32")
        st.pair_rows = np.zeros(st.n_pairs, np.int32)
        with numba.parallel_chunksize(_TILE_CHUNK):
            K.raster_fwd(st.means2d, st.conics, opac32, colors32, bg32, proj.radii,
                         st.tile_start, st.pair_gauss, w, h, cam.tiles_x, image, st.T, st.last,
                         st.pair_rows)
    return st, image


def _raster_bwd_np(K, proj: _Proj, opac32, colors32, bg32, cam: _CamParams, st, v_image,
                   v_alpha):
    if isinstance(st, tuple):  # (state, image) as returned by _raster_fwd_np
        st = st[0]
    n, c = colors32.shape
    pair = np.zeros((st.n_pairs, 6 + c), np.float32)
    v_means2d = np.empty((n, 2), np.float32)
    v_conics = np.empty((n, 3), np.float32)
    v_opac = np.empty(n, np.float32)
    v_colors = np.empty((n, c), np.float32)
    import numba

    with _RUN_LOCK:
        _apply_threads()
        with numba.parallel_chunksize(_TILE_CHUNK):
            K.raster_bwd(st.means2d, st.conics, opac32, colors32, bg32, proj.radii,
                         st.tile_start, st.pair_gauss, st.pair_slot, st.pair_rows, cam.width,
                         cam.height, cam.tiles_x, st.T, st.last, v_image, v_alpha, pair)
        K.reduce_pairs(pair, st.gauss_start, v_means2d, v_conics, v_opac, v_colors)
    return v_means2d, v_conics, v_opac, v_colors


_NP_DTYPES = {torch.float32: np.float32, torch.float64: np.float64}


def _np(t: Tensor, dtype) -> np.ndarray:
    """C-contiguous NumPy copy/view of ``t`` in ``dtype``.

    Conversions are done by NumPy (single-threaded) rather than torch: a torch op on ~1e5
    elements runs on torch's OpenMP pool, whose workers then spin for milliseconds and take
    the cores from the numba kernels that follow (measured: kernels ~40 % slower).
    """
    a = t.detach()
    if a.device.type != "cpu":
        a = a.cpu()
    if a.dtype not in _NP_DTYPES:  # e.g. float16 / bfloat16: let torch convert
        a = a.to(dtype)
    return np.ascontiguousarray(a.numpy(), dtype=_NP_DTYPES[dtype])


def _torch(a: np.ndarray, like_dtype, device) -> Tensor:
    """Tensor of dtype ``like_dtype`` on ``device`` from a NumPy array (converted by NumPy)."""
    np_dtype = _NP_DTYPES.get(like_dtype)
    if np_dtype is not None:
        out = torch.from_numpy(np.ascontiguousarray(a, dtype=np_dtype))
    else:
        out = torch.from_numpy(np.ascontiguousarray(a)).to(like_dtype)
    return out if device.type == "cpu" else out.to(device)


class _Project(torch.autograd.Function):
    """means [N,3], quats [N,4], scales [N,3] (+ opacities [N], non-diff) -> means2d [N,2],
    conics [N,3] (differentiable), depths [N], radii [N,2] int32, rect [N,4] int32."""

    @staticmethod
    def forward(ctx, means, quats, scales, opacities, cam: _CamParams, holder: dict):
        K = kernels()
        m = _np(means, torch.float64)
        q = _np(quats, torch.float64)
        s = _np(scales, torch.float64)
        proj = _project_np(K, m, q, s, _np(opacities, torch.float64), cam)
        holder["proj"] = proj  # float64 results for the rasterizer (depth sort, radii, rects)
        ctx.cam = cam
        ctx.proj = proj
        ctx.np_inputs = (m, q, s)
        ctx.meta = (means.dtype, means.device, quats.dtype, scales.dtype)
        dev = means.device
        means2d = _torch(proj.means2d, means.dtype, dev)
        conics = _torch(proj.conics, means.dtype, dev)
        depths = _torch(proj.depths, means.dtype, dev)
        radii = _torch(proj.radii, torch.int32, dev)
        rect = _torch(proj.rect, torch.int32, dev)
        ctx.mark_non_differentiable(depths, radii, rect)
        return means2d, conics, depths, radii, rect

    @staticmethod
    def backward(ctx, v_means2d, v_conics, _v_depths, _v_radii, _v_rect):
        m, q, s = ctx.np_inputs
        n = m.shape[0]
        vm2 = np.zeros((n, 2)) if v_means2d is None else _np(v_means2d, torch.float64)
        vc = np.zeros((n, 3)) if v_conics is None else _np(v_conics, torch.float64)
        v_means, v_quats, v_scales = _project_bwd_np(kernels(), m, q, s, ctx.cam, ctx.proj,
                                                     vm2, vc)
        dtype_m, dev, dtype_q, dtype_s = ctx.meta
        return (_torch(v_means, dtype_m, dev), _torch(v_quats, dtype_q, dev),
                _torch(v_scales, dtype_s, dev), None, None, None)


class _Rasterize(torch.autograd.Function):
    """means2d [N,2], conics [N,3], opacities [N], colors [N,C], background [C]
    (+ projection results) -> image [H,W,C], alpha [H,W]."""

    @staticmethod
    def forward(ctx, means2d, conics, opacities, colors, background, proj: _Proj,
                cam: _CamParams):
        K = kernels()
        opac32 = _np(opacities, torch.float32)
        colors32 = _np(colors, torch.float32)
        bg32 = _np(background, torch.float32)
        st, image = _raster_fwd_np(K, proj, opac32, colors32, bg32, cam,
                                   _np(means2d, torch.float32), _np(conics, torch.float32))
        ctx.state = (proj, opac32, colors32, bg32, cam, st)
        ctx.meta = (means2d.dtype, conics.dtype, opacities.dtype, colors.dtype,
                    background.dtype, colors.device)
        dev = colors.device
        image_t = _torch(image, colors.dtype, dev)
        alpha_t = _torch(1.0 - st.T, colors.dtype, dev)
        return image_t, alpha_t

    @staticmethod
    def backward(ctx, v_image, v_alpha):
        proj, opac32, colors32, bg32, cam, st = ctx.state
        h, w, c = cam.height, cam.width, colors32.shape[1]
        vi = np.zeros((h, w, c), np.float32) if v_image is None else _np(v_image, torch.float32)
        va = np.zeros((h, w), np.float32) if v_alpha is None else _np(v_alpha, torch.float32)
        v_m2d, v_con, v_op, v_col = _raster_bwd_np(kernels(), proj, opac32, colors32, bg32, cam,
                                                   st, vi, va)
        dt_m, dt_c, dt_o, dt_col, dt_bg, dev = ctx.meta
        v_bg = None
        if ctx.needs_input_grad[4]:
            v_bg = _torch((st.T[..., None] * vi).sum(axis=(0, 1)), dt_bg, dev)
        return (_torch(v_m2d, dt_m, dev), _torch(v_con, dt_c, dev), _torch(v_op, dt_o, dev),
                _torch(v_col, dt_col, dev), v_bg, None, None)


def rasterize_cpu(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor,
                  colors: Tensor, camera, background: Optional[Tensor] = None) -> RenderOutput:
    """Render with the compiled CPU backend (see :func:`baseline.render.rasterize`).

    Args:
        means [N, 3], quats [N, 4] (wxyz), scales [N, 3] (positive), opacities [N] in [0, 1],
        colors [N, C]; camera: :class:`baseline.camera.Camera`; background [C] or None.
    Returns:
        :class:`RenderOutput` with image [H, W, C], alpha [H, W], means2d [N, 2] (retains grad),
        radii [N] int32, visible [N] bool, depths [N]. Tensors on the inputs' device (computed
        on the CPU; CUDA inputs are copied).
    """
    background = check_inputs(means, quats, scales, opacities, colors, camera, background)
    cam = _CamParams.from_camera(camera)
    holder: dict = {}
    means2d, conics, depths, _radii_xy, _rect = _Project.apply(means, quats, scales,
                                                               opacities, cam, holder)
    if means2d.requires_grad:
        means2d.retain_grad()
    proj = holder["proj"]
    image, alpha = _Rasterize.apply(means2d, conics, opacities, colors, background, proj, cam)
    radii_np = proj.radii.max(axis=1, initial=0)
    radii = _torch(radii_np, torch.int32, means.device)
    visible = _torch(radii_np > 0, torch.bool, means.device)
    return RenderOutput(image=image, alpha=alpha, means2d=means2d, radii=radii,
                        visible=visible, depths=depths, backend="cpu")
