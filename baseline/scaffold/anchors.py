"""Anchor initialisation: voxelized SfM points (docs/method.md section 2)."""
from __future__ import annotations

import math

import numpy as np
import torch


def knn_mean_sq_dist(points: torch.Tensor, k: int = 3, chunk: int = 4096) -> torch.Tensor:
    """Mean squared distance from each point to its ``k`` nearest other points.

    Args:
        points: [P, 3].
    Returns:
        [P] mean of the k smallest squared distances (self excluded).

    scipy's cKDTree does the search: exact, O(P log P), and memory-bounded for large clouds.
    """
    from scipy.spatial import cKDTree

    p = points.detach().cpu().double().numpy()
    if len(p) < 2:
        return torch.zeros(len(p), dtype=torch.float32)
    kk = min(k + 1, len(p))
    d, _ = cKDTree(p).query(p, k=kk)
    d = np.asarray(d).reshape(len(p), kk)[:, 1:]
    return torch.from_numpy((d ** 2).mean(axis=1)).float()


def auto_voxel_size(points: torch.Tensor) -> float:
    """docs/method.md section 2: v <= 0 means the median over points of the mean squared distance to the 3-NN."""
    return float(torch.median(knn_mean_sq_dist(points)).item())


def voxelize(points: torch.Tensor, voxel_size: float) -> torch.Tensor:
    """Anchor positions ``unique(round(p / v)) * v``.

    Args:
        points: [P, 3] float.
        voxel_size: v > 0.
    Returns:
        [N, 3] float32 anchor positions, sorted lexicographically by voxel index (deterministic).
    """
    if voxel_size <= 0 or not math.isfinite(voxel_size):
        raise ValueError(f"voxel size must be positive and finite, got {voxel_size}")
    cells = torch.round(points.double() / voxel_size).long()
    uniq = torch.unique(cells, dim=0)  # torch.unique(dim=0) sorts lexicographically
    return (uniq.double() * voxel_size).float()


def init_log_scaling(anchors: torch.Tensor) -> torch.Tensor:
    """[N, 6] log-scaling: log(sqrt(mean sq. 3-NN distance)), clamped >= 1e-7 before the sqrt."""
    d2 = knn_mean_sq_dist(anchors).clamp_min(1e-7)
    return torch.log(torch.sqrt(d2))[:, None].repeat(1, 6)
