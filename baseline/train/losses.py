"""Training losses: L1, SSIM (11x11 Gaussian window, sigma 1.5) as in 3DGS / Scaffold-GS."""
from __future__ import annotations

import functools

import torch
import torch.nn.functional as F


@functools.lru_cache(maxsize=4)
def _window(size: int = 11, sigma: float = 1.5, channels: int = 3) -> torch.Tensor:
    x = torch.arange(size, dtype=torch.float32) - (size - 1) / 2
    g = torch.exp(-(x ** 2) / (2 * sigma ** 2))
    g = g / g.sum()
    w2 = (g[:, None] * g[None, :])[None, None]
    return w2.expand(channels, 1, size, size).contiguous()


def ssim(img: torch.Tensor, gt: torch.Tensor, size: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """Differentiable mean SSIM of two images [H,W,C] in [0,1] (zero padding, as 3DGS's loss).

    Used for the training loss only; reported metrics use scikit-image on uint8 images.
    """
    C = img.shape[-1]
    x = img.permute(2, 0, 1)[None]
    y = gt.permute(2, 0, 1)[None]
    w = _window(size, sigma, C).to(img)
    pad = size // 2
    mu_x = F.conv2d(x, w, padding=pad, groups=C)
    mu_y = F.conv2d(y, w, padding=pad, groups=C)
    sxx = F.conv2d(x * x, w, padding=pad, groups=C) - mu_x ** 2
    syy = F.conv2d(y * y, w, padding=pad, groups=C) - mu_y ** 2
    sxy = F.conv2d(x * y, w, padding=pad, groups=C) - mu_x * mu_y
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    num = (2 * mu_x * mu_y + c1) * (2 * sxy + c2)
    den = (mu_x ** 2 + mu_y ** 2 + c1) * (sxx + syy + c2)
    return (num / den).mean()


def reconstruction_loss(img: torch.Tensor, gt: torch.Tensor, lambda_dssim: float = 0.2):
    """(1 - lambda) L1 + lambda (1 - SSIM); returns (loss, l1)."""
    l1 = (img - gt).abs().mean()
    return (1.0 - lambda_dssim) * l1 + lambda_dssim * (1.0 - ssim(img, gt)), l1


def lr_exp(step: int, total: int, lr0: float, lr1: float) -> float:
    """``exp((1-t) ln lr0 + t ln lr1)``, t = step / total clamped to [0,1] (Scaffold-GS schedule)."""
    if lr0 == lr1:
        return lr0
    if lr0 <= 0 or lr1 <= 0:
        return 0.0
    import math

    t = min(max(step / max(total, 1), 0.0), 1.0)
    return math.exp((1 - t) * math.log(lr0) + t * math.log(lr1))
