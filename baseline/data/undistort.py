"""Undistortion of COLMAP / OpenCV-style captures to the pinhole model the rasterizer needs.

The remap is built from pycolmap's own camera model: for every pixel of the undistorted
(pinhole) image we compute its normalized camera ray, push it through the capture camera's
distortion with ``pycolmap.Camera.img_from_cam`` and sample the source image there bilinearly.
So the distortion formulas are COLMAP's, not a re-derivation.

Choice of the pinhole intrinsics (``mode``):

* ``"crop"`` (default): keep the image size and the principal point ``(cx, cy)``, and scale
  both focal lengths by the smallest common factor ``s >= 1`` for which every pixel of the
  undistorted image samples inside the source image (no blank border, like COLMAP's
  ``image_undistorter`` with ``blank_pixels=0``, but without changing the image size). For
  barrel-only distortion ``s = 1`` (we never zoom out).
* ``"keep"``: keep ``fx, fy, cx, cy`` of the capture camera exactly; pixels whose source falls
  outside the image are blank (black, or transparent for RGBA).

Coordinates are continuous pixel coordinates with pixel centres at ``+0.5`` (see images.py).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pycolmap
from scipy import ndimage

from .errors import SceneError

PINHOLE_MODELS = ("SIMPLE_PINHOLE", "PINHOLE")
DISTORTED_MODELS = ("SIMPLE_RADIAL", "RADIAL", "OPENCV")
SUPPORTED_MODELS = PINHOLE_MODELS + DISTORTED_MODELS
UNDISTORT_MODES = ("crop", "keep")


@dataclass(frozen=True)
class SourceCamera:
    """A capture camera as calibrated: COLMAP model name, calibration size and parameters.

    The image file may have another size (an ``images_N`` folder); the model is then applied in
    calibration pixels and scaled per axis by ``file size / calibration size``.
    """

    model: str
    width: int
    height: int
    params: tuple[float, ...]
    camera_id: int | None = None

    @classmethod
    def from_pycolmap(cls, cam: "pycolmap.Camera", camera_id: int | None = None) -> "SourceCamera":
        return cls(model=cam.model.name, width=int(cam.width), height=int(cam.height),
                   params=tuple(float(p) for p in cam.params),
                   camera_id=camera_id if camera_id is not None else int(cam.camera_id))

    def to_pycolmap(self) -> "pycolmap.Camera":
        return pycolmap.Camera(model=self.model, width=self.width, height=self.height,
                               params=list(self.params))

    @property
    def is_pinhole(self) -> bool:
        return self.model in PINHOLE_MODELS

    def intrinsics(self) -> tuple[float, float, float, float]:
        """(fx, fy, cx, cy) of the model's linear part, in calibration pixels."""
        c = self.to_pycolmap()
        return (float(c.focal_length_x), float(c.focal_length_y),
                float(c.principal_point_x), float(c.principal_point_y))

    def describe(self) -> str:
        cid = f"camera {self.camera_id}" if self.camera_id is not None else "camera"
        return f"{cid} ({self.model} {self.width}x{self.height}, params {list(self.params)})"


def check_supported(cam: SourceCamera, where: str) -> None:
    """Raise :class:`SceneError` unless ``cam.model`` is one we can use or undistort."""
    if cam.model not in SUPPORTED_MODELS:
        cid = cam.camera_id if cam.camera_id is not None else "?"
        raise SceneError(
            f"{where}: camera id {cid} uses the camera model {cam.model}, which is not supported. "
            f"Supported models: {', '.join(SUPPORTED_MODELS)} (distorted ones are undistorted to "
            "pinhole on load). Undistort the images first (e.g. `colmap image_undistorter`) and "
            "load the undistorted folder.")


def distort_pixels(cam: SourceCamera, pinhole: tuple[float, float, float, float],
                   uv: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Map pixels of the undistorted image to pixels of the source (distorted) image.

    Args:
        cam: the capture camera.
        pinhole: (fx, fy, cx, cy) of the undistorted camera in *calibration* pixels.
        uv: [N, 2] continuous pixel coordinates in the undistorted image of size ``size``.
        size: (width, height) of both the source file and the undistorted image.

    Returns:
        [N, 2] continuous pixel coordinates in the source image.
    """
    w, h = size
    sx, sy = w / cam.width, h / cam.height
    fx, fy, cx, cy = pinhole
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    rays = np.stack([(uv[:, 0] / sx - cx) / fx, (uv[:, 1] / sy - cy) / fy,
                     np.ones(len(uv))], axis=1)
    src = np.asarray(cam.to_pycolmap().img_from_cam(rays, check_cheirality=False),
                     dtype=np.float64).reshape(-1, 2)
    return src * np.array([sx, sy])


def _border(width: float, height: float, n: int = 1024) -> np.ndarray:
    t = np.linspace(0.0, 1.0, n)
    xs, ys = t * width, t * height
    return np.concatenate([
        np.stack([xs, np.zeros(n)], 1), np.stack([xs, np.full(n, height)], 1),
        np.stack([np.zeros(n), ys], 1), np.stack([np.full(n, width), ys], 1)])


def _inside(src: np.ndarray, width: float, height: float, tol: float = 1e-6) -> bool:
    return bool(np.all(np.isfinite(src)) and np.all(src[:, 0] >= -tol)
                and np.all(src[:, 0] <= width + tol) and np.all(src[:, 1] >= -tol)
                and np.all(src[:, 1] <= height + tol))


def choose_pinhole(cam: SourceCamera, mode: str = "crop",
                   where: str = "") -> tuple[float, float, float, float]:
    """The pinhole intrinsics (fx, fy, cx, cy), in calibration pixels, images are undistorted to.

    See the module docstring for the two modes. Raises :class:`SceneError` if the distortion is
    not invertible over the image (pycolmap cannot map the pixels back to the same rays).
    """
    if mode not in UNDISTORT_MODES:
        raise ValueError(f"undistort mode must be one of {UNDISTORT_MODES}, got {mode!r}")
    fx, fy, cx, cy = cam.intrinsics()
    if cam.is_pinhole:
        return fx, fy, cx, cy
    W, H = cam.width, cam.height
    border = _border(W, H)
    size = (W, H)

    def ok(s: float) -> bool:
        return _inside(distort_pixels(cam, (fx * s, fy * s, cx, cy), border, size), W, H)

    scale = 1.0
    if mode == "crop" and not ok(1.0):
        lo, hi = 1.0, 2.0
        while not ok(hi):
            lo, hi = hi, hi * 2.0
            if hi > 64:
                raise SceneError(f"{where}: {cam.describe()}: no zoom keeps the undistorted image "
                                 "inside the source; the distortion is too strong to undistort")
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            lo, hi = (lo, mid) if ok(mid) else (mid, hi)
        scale = hi
    pin = (fx * scale, fy * scale, cx, cy)
    _check_invertible(cam, pin, where)
    return pin


def _check_invertible(cam: SourceCamera, pinhole, where: str) -> None:
    """The distortion must be one-to-one over the undistorted image: rays -> pixels -> rays."""
    W, H = cam.width, cam.height
    g = np.linspace(0.0, 1.0, 33)
    uv = np.stack(np.meshgrid(g * W, g * H), -1).reshape(-1, 2)
    src = distort_pixels(cam, pinhole, uv, (W, H))
    fx, fy, cx, cy = pinhole
    rays = np.stack([(uv[:, 0] - cx) / fx, (uv[:, 1] - cy) / fy], 1)
    back = np.asarray(cam.to_pycolmap().cam_from_img(src), dtype=np.float64).reshape(-1, 2)
    err = np.abs(back - rays).max() * max(fx, fy) if np.all(np.isfinite(back)) else np.inf
    if not err < 1e-3:
        raise SceneError(f"{where}: {cam.describe()}: the distortion is not invertible over the "
                         f"image (round-trip error {err:.3g} px); undistort the images with COLMAP "
                         "and load the undistorted folder")


def undistort_map(cam: SourceCamera, pinhole: tuple[float, float, float, float],
                  size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Source coordinates of every undistorted pixel centre.

    Returns:
        (map_x, map_y): two [h, w] float64 arrays of continuous source pixel coordinates.
    """
    w, h = size
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    src = distort_pixels(cam, pinhole, np.stack([u.ravel(), v.ravel()], 1), size)
    return src[:, 0].reshape(h, w), src[:, 1].reshape(h, w)


def remap(img: np.ndarray, map_x: np.ndarray, map_y: np.ndarray) -> np.ndarray:
    """Bilinearly sample ``img`` [h, w, C] at continuous coordinates (map_x, map_y).

    Samples inside the image's continuous extent ``[0, w] x [0, h]`` are valid (the outer half
    pixel clamps to the edge pixel); samples outside are 0 (blank).
    """
    h, w, c = img.shape
    coords = np.stack([map_y.ravel() - 0.5, map_x.ravel() - 0.5])
    out = np.empty((map_x.size, c), dtype=np.float32)
    for k in range(c):
        out[:, k] = ndimage.map_coordinates(img[:, :, k], coords, order=1, mode="nearest")
    tol = 1e-6
    outside = ((map_x.ravel() < -tol) | (map_x.ravel() > w + tol)
               | (map_y.ravel() < -tol) | (map_y.ravel() > h + tol))
    out[outside] = 0.0
    return out.reshape(map_x.shape + (c,))
