"""The reference forms of the training code's fast paths, swapped in together.

Each fast path that claims the numbers of a simpler form keeps that form here (or names it),
and :func:`reference_paths` puts all of them in place for the duration of a block, so that a
test can train once with the product code and once with the references and compare the
checkpoints bit for bit.

* hash-grid float kernels: the point-by-point loop of ``reference_grid_kernels``, on the
  binarized table of :class:`~baseline.hac.hashgrid.STEBinary`'s forward, and its backward
  as a ``torch.where``; the hash bits' count of ones and straight-through gradient as the
  ``torch`` ops they replace;
* the visible-anchor prefilter's numba pass: the torch form that other devices run.
"""
from __future__ import annotations

import contextlib

import numpy as np
import reference_grid_kernels as R
import torch

from baseline.hac import _grid_kernels as K
from baseline.hac._grid_kernels import DENSE
from baseline.render import prefilter as P


def _hashed(kinds):
    return (kinds != DENSE).astype("uint8")


def _grid_fwd(u, table, res, rows, offsets, kinds, strides, out, signs):
    if signs:        # STEBinary's forward: +1 where >= 0, else -1 (NaN: -1)
        table = np.where(table >= 0, 1.0, -1.0).astype(np.float32)
    R.grid_fwd(u, table, res, rows, offsets, _hashed(kinds), strides, out)


def _ste_mask(params, grad):
    """STEBinary's backward: ``torch.where(x.abs() <= 1.0, grad, 0.0)``."""
    grad[...] = torch.where(torch.from_numpy(params).abs() <= 1.0, torch.from_numpy(grad),
                            0.0).numpy()


def _grid_bwd(u, gout, res, rows, offsets, kinds, strides, gtable, nparts):
    R.grid_bwd(u, gout, res, rows, offsets, _hashed(kinds), strides, gtable, nparts)


def _count_nonneg(params):
    return int((torch.from_numpy(params) >= 0).sum())


def _ste_fill(params, g, out):
    out[...] = torch.where(torch.from_numpy(params).abs() <= 1.0, torch.tensor(g), 0.0).numpy()


def _visible(p, cov, *rest):
    """The prefilter's test as torch ops, written into the kernel's ``out`` (its last argument)."""
    *terms, out = rest
    out[...] = P._visible_torch(torch.from_numpy(p), torch.from_numpy(cov), *terms).numpy()


@contextlib.contextmanager
def reference_paths():
    """Every fast path replaced by its reference form inside the block."""
    with contextlib.ExitStack() as stack:
        for mod, name, ref in ((K, "grid_fwd", _grid_fwd), (K, "grid_bwd", _grid_bwd),
                               (K, "ste_mask", _ste_mask), (K, "count_nonneg", _count_nonneg),
                               (K, "ste_fill", _ste_fill), (P, "_visible_kernel", _visible)):
            old = getattr(mod, name)
            setattr(mod, name, ref)
            stack.callback(setattr, mod, name, old)
        yield
