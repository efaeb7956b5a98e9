"""CUDA backend: gsplat's ``rasterization()`` wrapped to return a :class:`RenderOutput`.

gsplat is imported lazily (it is the optional ``cuda`` extra). The call uses
``packed=False, rasterize_mode="classic", eps2d=0.3, tile_size=16, sh_degree=None`` (colors
are post-activation values, any channel count) and the camera's near/far planes.

Known differences from the CPU/reference backends (all outside the normal operating range):
    * near/far: gsplat culls ``z < near`` and ``z > far``; the CPU backend culls ``z <= near``
      and ``z >= far`` (only a Gaussian exactly on a plane differs).
    * gradients: gsplat's projection backward ignores the clamp of x/z, y/z in the Jacobian
      (as the original 3DGS code); the CPU/reference backends give the exact gradient of the
      clamped function. Only Gaussians centred outside 1.3x the field of view differ.
    * gsplat < 1.5 sizes boxes by 3 sigma of the largest eigenvalue (not opacity-aware) and
      returns radii [N]; gsplat >= 1.5 matches the CPU backend's opacity-aware boxes and
      returns radii [N, 2], reduced here to ``max`` over x and y.
    * zero quaternions: gsplat normalizes to NaN; the CPU backend uses the identity rotation.
    * ``means2d``: gsplat's screen-space means are a [1, N, 2] tensor; the returned
      ``means2d`` [N, 2] is a leaf holding the same values whose ``.grad`` is filled by a hook
      on gsplat's tensor during backward (accumulating like a normal ``.grad``).
"""
from __future__ import annotations

from typing import Optional

import torch
from torch import Tensor

from .conventions import EPS2D, TILE_SIZE, RenderOutput, check_inputs

INSTALL_HINT = ("the 'gsplat' rasterizer backend needs the gsplat package: "
                "pip install gsplat (the toolkit's 'cuda' extra), or use backend='cpu'")


def gsplat_available() -> bool:
    """True when gsplat can be imported (does not check for a GPU)."""
    try:
        import gsplat  # noqa: F401
    except Exception:
        return False
    return True


def _import_gsplat():
    try:
        import gsplat
    except ImportError as e:
        raise ImportError(INSTALL_HINT) from e
    return gsplat


def rasterize_gsplat(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor,
                     colors: Tensor, camera, background: Optional[Tensor] = None) -> RenderOutput:
    """Render with gsplat on CUDA (see :func:`baseline.render.rasterize` for the arguments).

    Raises:
        ImportError: gsplat is not installed (with the install command).
        ValueError: the inputs are not CUDA tensors.
    """
    gs = _import_gsplat()
    if not means.is_cuda:
        raise ValueError("the 'gsplat' rasterizer backend needs CUDA tensors; "
                         "move the inputs to the GPU or use backend='cpu'")
    return rasterize_with_module(gs, means, quats, scales, opacities, colors, camera, background)


def rasterize_with_module(gs, means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor,
                          colors: Tensor, camera, background: Optional[Tensor] = None
                          ) -> RenderOutput:
    """The wrapper proper, with the gsplat module passed in (lets tests substitute a fake).

    Shapes: means [N, 3], quats [N, 4], scales [N, 3], opacities [N], colors [N, C],
    background [C] or None. Returns a :class:`RenderOutput`.
    """
    background = check_inputs(means, quats, scales, opacities, colors, camera, background)
    dev, dt = means.device, means.dtype
    viewmats = camera.viewmat.to(dev, dt)[None]  # [1, 4, 4]
    Ks = camera.K().to(dev, dt)[None]  # [1, 3, 3]
    render_colors, render_alphas, meta = gs.rasterization(
        means, quats, scales, opacities, colors, viewmats, Ks, int(camera.width),
        int(camera.height), near_plane=float(camera.near), far_plane=float(camera.far),
        eps2d=EPS2D, sh_degree=None, packed=False, tile_size=TILE_SIZE,
        backgrounds=background[None], render_mode="RGB", rasterize_mode="classic")
    image = render_colors[0]  # [H, W, C]
    alpha = render_alphas[0, ..., 0]  # [H, W]
    radii = meta["radii"][0]
    if radii.dim() == 2:  # gsplat >= 1.5: [N, 2]
        radii = radii.max(dim=-1).values
    radii = radii.to(torch.int32)
    m2d_full = meta["means2d"]  # [1, N, 2]
    means2d = m2d_full.detach()[0].clone()
    if m2d_full.requires_grad:
        means2d.requires_grad_(True)

        def _hook(grad: Tensor) -> None:
            g = grad[0].detach()
            means2d.grad = g.clone() if means2d.grad is None else means2d.grad + g

        m2d_full.register_hook(_hook)
    depths = meta.get("depths")
    if depths is not None:
        depths = depths[0].detach()
    return RenderOutput(image=image, alpha=alpha, means2d=means2d, radii=radii,
                        visible=radii > 0, depths=depths, backend="gsplat")
