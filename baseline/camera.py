"""The camera shared by scene loaders, the rasterizer and the trainer.

A pinhole camera with world-to-camera extrinsics in the OpenCV convention (x right, y down,
z forward), like gsplat's ``viewmats``.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import torch


@dataclass(frozen=True)
class Camera:
    """One posed pinhole view.

    Attributes:
        viewmat: [4, 4] float32 world-to-camera matrix (OpenCV axes).
        fx, fy, cx, cy: intrinsics in pixels for an image of ``width`` x ``height``.
        width, height: image size in pixels.
        near: near plane; Gaussians (and, in the prefilter, anchors) with camera-space
            z <= near are culled. 0.2 as Scaffold-GS's and HAC's prefilter and rasterizer
            (scenes take it from ``data.near``).
        far: far plane.
        name: image name (for reports and caches).
        index: position of the view in the scene's sorted view list.
    """

    viewmat: torch.Tensor
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    near: float = 0.2
    far: float = 1e10
    name: str = ""
    index: int = 0

    @property
    def center(self) -> torch.Tensor:
        """[3] camera centre in world coordinates."""
        R = self.viewmat[:3, :3]
        t = self.viewmat[:3, 3]
        return -R.T @ t

    def scaled(self, factor: float) -> "Camera":
        """The same view rendered at ``factor`` times the resolution.

        The image size is rounded to whole pixels (at least 1) and the intrinsics are scaled by
        the *actual* size ratio per axis, so the pixel grid stays consistent with the image.
        """
        w = max(1, int(round(self.width * factor)))
        h = max(1, int(round(self.height * factor)))
        sx, sy = w / self.width, h / self.height
        return replace(self, fx=self.fx * sx, fy=self.fy * sy, cx=self.cx * sx, cy=self.cy * sy,
                       width=w, height=h)

    def K(self) -> torch.Tensor:
        """[3, 3] intrinsics matrix."""
        return torch.tensor([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]],
                            dtype=torch.float32)
