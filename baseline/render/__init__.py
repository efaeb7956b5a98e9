"""The one rasterizer of the toolkit: a pure function with interchangeable backends.

    out = rasterize(means, quats, scales, opacities, colors, camera, background=None,
                    backend="auto")

Inputs (N Gaussians, C channels):
    means [N, 3] world positions; quats [N, 4] wxyz rotations (need not be normalized; a zero
    quaternion means identity); scales [N, 3] activated (positive) scales; opacities [N] in
    [0, 1]; colors [N, C] post-activation colours (any C >= 1; 3 is the usual case);
    camera: :class:`baseline.camera.Camera`; background [C] or None (zeros).

Output: :class:`RenderOutput` with image [H, W, C], alpha [H, W], means2d [N, 2] (pixel-space
projected centres; ``means2d.grad`` is populated by ``loss.backward()`` with the gradient in
*pixel* units, multiply by (W/2, H/2) for gsplat/3DGS "NDC" units), radii [N] int32 (0 = not
rendered), visible [N] bool, depths [N]. The image is differentiable w.r.t. means, quats,
scales, opacities and colors (and the background).

Backends (registry kind ``"rasterizer"``):
    ``cpu``        numba kernels (forward and backward), :mod:`baseline.render.cpu`
    ``gsplat``     gsplat's CUDA ``rasterization()``, :mod:`baseline.render.gsplat_backend`
    ``reference``  plain PyTorch + autograd, the ground truth, :mod:`baseline.render.reference`
``"auto"`` picks ``gsplat`` when the inputs are CUDA tensors and gsplat imports, else ``cpu``.
All follow the conventions in :mod:`baseline.render.conventions` (gsplat's "classic" mode).

Also here: :func:`prefilter_anchors` (Scaffold-GS visible-anchor prefilter).
"""
from __future__ import annotations

from typing import Optional

import torch
from torch import Tensor

from baseline import registry

from .conventions import TILE_SIZE, RenderOutput
from .cpu import rasterize_cpu, set_num_threads
from .gsplat_backend import gsplat_available, rasterize_gsplat
from .prefilter import prefilter_anchors
from .reference import rasterize_reference

__all__ = ["rasterize", "RenderOutput", "prefilter_anchors", "resolve_backend",
           "rasterize_cpu", "rasterize_gsplat", "rasterize_reference", "set_num_threads",
           "BACKENDS", "TILE_SIZE"]

BACKENDS = {
    "cpu": rasterize_cpu,
    "gsplat": rasterize_gsplat,
    "reference": rasterize_reference,
}
for _name, _fn in BACKENDS.items():
    registry.register("rasterizer", _name, _fn)


def resolve_backend(backend: str, means: Tensor) -> str:
    """The backend name ``backend`` stands for (``"auto"`` -> ``"gsplat"`` or ``"cpu"``)."""
    if backend != "auto":
        return backend
    if means.is_cuda and torch.cuda.is_available() and gsplat_available():
        return "gsplat"
    return "cpu"


def rasterize(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, colors: Tensor,
              camera, background: Optional[Tensor] = None, backend: str = "auto"
              ) -> RenderOutput:
    """Render N 3D Gaussians into one image (see the module docstring).

    Args:
        means: [N, 3] centres (world).
        quats: [N, 4] wxyz rotations, any norm.
        scales: [N, 3] activated scales (> 0).
        opacities: [N] opacities in [0, 1].
        colors: [N, C] colours / features, C >= 1.
        camera: :class:`baseline.camera.Camera` (viewmat world-to-camera, OpenCV axes).
        background: [C] colour behind the Gaussians, or None for zeros.
        backend: ``"auto"``, ``"cpu"``, ``"gsplat"``, ``"reference"`` or a name a plugin
            registered under kind ``"rasterizer"``.
    Returns:
        :class:`RenderOutput`: image [H, W, C], alpha [H, W], means2d [N, 2] (``.grad`` after
        backward, pixel units), radii [N] int32, visible [N] bool, depths [N].
    """
    name = resolve_backend(backend, means)
    fn = BACKENDS.get(name)
    if fn is None:
        fn = registry.get("rasterizer", name)  # plugin backends; unknown names list the known
    return fn(means, quats, scales, opacities, colors, camera, background)
