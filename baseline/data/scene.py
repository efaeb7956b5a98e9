"""Scene loading: cameras, split, initial points and lazily loaded, disk-cached images.

``load_scene(path)`` reads a COLMAP or Blender / instant-ngp folder (format detected from its
layout) and returns a :class:`Scene`. Images are decoded with OpenImageIO, undistorted to
pinhole when the capture camera has distortion (:mod:`baseline.data.undistort`), resized once
with an exact area filter (:func:`baseline.data.images.resize_area`) and cached on disk as
uint8 PNGs; :meth:`Scene.image` reads one image back from the cache, so memory stays bounded
whatever the number of views.

Protocol (docs/method.md section 1), all recorded in ``Scene.protocol``:

* Views are sorted by image name (plain string order, as 3DGS does for COLMAP; Blender frame
  names such as ``train/r_10`` sort in natural order, digits numerically, which is the file
  order of the NeRF-Synthetic json files). With ``eval`` on, view ``k`` of the sorted list is a
  test view when ``k % test_every == 0``; Blender scenes with ``transforms_train.json`` /
  ``transforms_test.json`` take the split from the files instead. With ``eval`` off every view
  is a training view.
* ``resolution``: -1 keeps the image size but caps the width at 1600 px; 1, 2, 4, 8 divide the
  size (rounded to whole pixels, COLMAP scenes read ``images_r/`` when it exists); any other
  positive value is a target width (3DGS convention). Intrinsics are scaled per axis by the
  actual size ratio, so they always match the image loaded.
* ``extent`` = 1.1 x the largest distance from a training camera centre to their mean.
* Points: COLMAP ``points3D`` (colours / 255); Blender: ``random_init_points`` uniform in
  ``[-random_init_extent, random_init_extent]^3`` with uniform random colours (seeded).
"""
from __future__ import annotations

import hashlib
import json
import os
import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from ..camera import Camera
from .errors import SceneError
from .images import (image_size, premultiply, read_image, read_png_u8, resize_area, to_uint8,
                     write_png_atomic)
from .readers import ReaderResult, ViewRecord, detect_format, read_blender, read_colmap
from .undistort import SourceCamera, choose_pinhole, remap, undistort_map

CACHE_VERSION = 1
MAX_DEFAULT_WIDTH = 1600


@dataclass(frozen=True)
class ViewSource:
    """Where a view's image comes from and how its cached image is made.

    Attributes:
        name: the view's image name.
        path: the source image file.
        source: the capture camera (model, calibration size, parameters).
        pinhole: (fx, fy, cx, cy) of the undistorted camera in calibration pixels.
        file_size: (w, h) of the source file.
        size: (w, h) of the loaded (cached) image.
        cache_file: the cached uint8 PNG.
    """

    name: str
    path: Path
    source: SourceCamera
    pinhole: tuple[float, float, float, float]   # undistorted intrinsics, calibration pixels
    file_size: tuple[int, int]                   # (w, h) of the source file
    size: tuple[int, int]                        # (w, h) after resizing
    cache_file: Path

    def build(self) -> np.ndarray:
        """Decode, undistort, resize and quantize: uint8 [h, w, 3 or 4] (RGBA premultiplied)."""
        img = read_image(self.path)
        if (img.shape[1], img.shape[0]) != self.file_size:
            raise SceneError(f"{self.path}: image is {img.shape[1]}x{img.shape[0]} but its header "
                             f"said {self.file_size[0]}x{self.file_size[1]}")
        img = premultiply(img)
        if not self.source.is_pinhole:
            img = remap(img, *undistort_map(self.source, self.pinhole, self.file_size))
        img = resize_area(img, *self.size)
        return to_uint8(img)


class _ImageStore:
    """The on-disk cache of a scene's images: one PNG per view, written atomically."""

    def __init__(self, recipes: dict[int, ViewSource]):
        self.recipes = recipes

    def ensure(self, idx: int) -> Path:
        r = self.recipes[idx]
        if not r.cache_file.is_file():
            write_png_atomic(r.cache_file, r.build())
        return r.cache_file

    def prefetch(self, desc: str, progress: bool = True) -> None:
        todo = [i for i, r in self.recipes.items() if not r.cache_file.is_file()]
        for i in tqdm(todo, desc=desc, unit="img", disable=not (todo and progress)):
            self.ensure(i)

    def load_u8(self, idx: int) -> np.ndarray:
        path = self.ensure(idx)
        try:
            return read_png_u8(path)
        except OSError:             # damaged cache entry (e.g. disk trouble): rebuild once
            path.unlink(missing_ok=True)
            return read_png_u8(self.ensure(idx))


@dataclass
class Scene:
    """A loaded scene.

    Attributes:
        name: scene folder name.
        source_path: the scene folder.
        train_cameras / test_cameras: views sorted by name; ``Camera.index`` is the position in
            the full sorted list (train and test together), unique per view.
        points: [P, 3] float32 initial points (SfM or random).
        colors: [P, 3] float32 in [0, 1].
        extent: cameras_extent (1.1 x max distance of a training centre to their mean).
        background: [3] float32 colour RGBA images are composited on.
        protocol: how the data was prepared (format, image folder, downscale, split, background,
            counts, undistortion, cache folder): copy it into every report.
    """

    name: str
    source_path: Path
    train_cameras: list[Camera]
    test_cameras: list[Camera]
    points: torch.Tensor
    colors: torch.Tensor
    extent: float
    background: torch.Tensor
    protocol: dict
    _store: _ImageStore = field(repr=False)

    def view_source(self, camera: Camera) -> ViewSource:
        """The source file, capture camera and undistortion of one of this scene's views."""
        r = self._store.recipes.get(camera.index)
        if r is None or r.name != camera.name:
            raise KeyError(f"camera {camera.name!r} (index {camera.index}) is not a view of "
                           f"scene {self.name}")
        return r

    @property
    def cameras(self) -> list[Camera]:
        """All views, train and test, in index order."""
        return sorted(self.train_cameras + self.test_cameras, key=lambda c: c.index)

    def image(self, camera: Camera) -> torch.Tensor:
        """The ground-truth image of ``camera``: float32 [H, W, 3] in [0, 1].

        Loaded from the disk cache (built first if missing); only this image is read. RGBA
        sources are composited on ``background``. ``camera`` must be one of this scene's views
        at its loaded size (use the trainer's own resampling for other sizes).
        """
        r = self.view_source(camera)
        if (camera.width, camera.height) != r.size:
            raise ValueError(f"camera {camera.name!r} is {camera.width}x{camera.height} but the "
                             f"scene's image is {r.size[0]}x{r.size[1]}; resample the image "
                             "yourself for other sizes")
        u8 = self._store.load_u8(camera.index)
        img = u8.astype(np.float32) / 255.0
        if img.shape[2] == 4:
            bg = self.background.numpy().astype(np.float32)
            img = img[:, :, :3] + (1.0 - img[:, :, 3:4]) * bg
            img = np.clip(img, 0.0, 1.0)
        return torch.from_numpy(np.ascontiguousarray(img[:, :, :3]))


# ----------------------------------------------------------------------------------- helpers
def _natural_key(s: str):
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", s)]


def _target_size(w: int, h: int, resolution: int, extra: float | None) -> tuple[int, int]:
    """Image size after the resolution rule (see module docstring)."""
    if extra is not None:
        f = extra
    elif resolution in (1, 2, 4, 8):
        f = float(resolution)
    elif resolution == -1:
        f = w / MAX_DEFAULT_WIDTH if w > MAX_DEFAULT_WIDTH else 1.0
    else:
        f = w / resolution
    return max(1, int(round(w / f))), max(1, int(round(h / f)))


def fits_calibration(w: int, h: int, W: int, H: int, slack: float = 1.0) -> bool:
    """Whether a ``w`` x ``h`` image can be the ``W`` x ``H`` calibration image resized by one
    factor s, each side rounded to whole pixels (off by at most ``slack`` px: resizers round,
    floor or ceil). True when some s has |w - s W| <= slack and |h - s H| <= slack, i.e. the two
    intervals of s overlap. (Predicting one side from the other's ratio, as before, wrongly
    refused wide images: truck's 979x546 at a quarter is 245x136, and 136/546 * 979 = 243.9.)"""
    lo = max((w - slack) / W, (h - slack) / H)
    hi = min((w + slack) / W, (h + slack) / H)
    return lo <= hi + 1e-12


def _check_aspect(rec: ViewRecord, size: tuple[int, int]) -> None:
    """The file must be the calibration image at some scale (within rounding of a resize)."""
    w, h = size
    W, H = rec.source.width, rec.source.height
    if not fits_calibration(w, h, W, H):
        cid = f" (camera id {rec.source.camera_id})" if rec.source.camera_id is not None else ""
        raise SceneError(f"{rec.path}: image is {w}x{h} but its camera{cid} is calibrated for "
                         f"{W}x{H}, a different aspect ratio (rotated or cropped image?); "
                         "restore the original image or recalibrate")


def _default_cache_root(path: Path) -> Path:
    """The user's cache folder (``$XDG_CACHE_HOME/pgs`` or ``~/.cache/pgs``).

    Never beside the scene: datasets are often shared or read-only and must stay as the user
    has them. Entries are keyed by the source path and the view's parameters (``_cache_key``).
    """
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "pgs"


def _cache_key(rec: ViewRecord, pinhole, file_size, size, undistort: str) -> str:
    st = rec.path.stat()
    blob = json.dumps({"v": CACHE_VERSION, "src": str(rec.path.resolve()), "bytes": st.st_size,
                       "mtime": st.st_mtime_ns, "model": rec.source.model,
                       "calib": [rec.source.width, rec.source.height],
                       "params": list(rec.source.params), "pinhole": list(pinhole),
                       "undistort": undistort if not rec.source.is_pinhole else None,
                       "file": list(file_size), "size": list(size)}, sort_keys=True)
    return hashlib.sha1(blob.encode()).hexdigest()[:16]


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", name.replace("/", "__"))


def cameras_extent(cameras: list[Camera]) -> float:
    """1.1 x the largest distance from a camera centre to the mean centre (3DGS scene scale)."""
    if not cameras:
        return 1.0
    c = torch.stack([cam.center.double() for cam in cameras])
    ext = 1.1 * float((c - c.mean(0)).norm(dim=1).max())
    if ext <= 0.0:
        warnings.warn("all training cameras share one centre; using extent 1.0", stacklevel=2)
        return 1.0
    return ext


def scene_bounds(scene) -> tuple[torch.Tensor, float]:
    """``(centre [3], extent)`` of a scene: the mean training camera centre and
    :func:`cameras_extent` (what :func:`baseline.scaffold.model.check_bounds` measures against)."""
    cams = scene.train_cameras or scene.test_cameras
    if not cams:
        return torch.zeros(3), float(scene.extent)
    return torch.stack([c.center.double() for c in cams]).mean(0).float(), float(scene.extent)


# ---------------------------------------------------------------------------------- load_scene
def load_scene(path: str | os.PathLike, resolution: int = -1, images: str | None = None,
               eval: bool = True, test_every: int = 8, background=(0.0, 0.0, 0.0),
               cache_dir: str | os.PathLike | None = None, random_init_points: int = 10000,
               random_init_extent: float = 1.3, seed: int = 0, undistort: str = "crop",
               prefetch: bool = True, progress: bool = True, near: float = 0.2) -> Scene:
    """Load a COLMAP or Blender / instant-ngp scene.

    Args:
        path: scene folder.
        resolution: -1 (original, width capped at 1600 px), 1/2/4/8 (divide the size), or a
            target width in pixels.
        images: COLMAP image folder name (e.g. ``"images_8"``); default: chosen from
            ``resolution`` (``images_r/`` if present, else ``images/`` downscaled).
        eval: hold out test views (every ``test_every``-th, or the Blender test file).
        test_every: test-view period for the every-Nth split.
        background: RGB in [0, 1] that RGBA images are composited on.
        cache_dir: where resized images are cached; default ``$XDG_CACHE_HOME/pgs``
            (``~/.cache/pgs``); the scene folder is never written to.
        random_init_points, random_init_extent, seed: random initial points for scenes without
            SfM points.
        undistort: ``"crop"`` or ``"keep"`` pinhole intrinsics for distorted cameras (see
            :mod:`baseline.data.undistort`).
        prefetch: build the whole image cache now (with a progress bar); if False each image is
            built on its first :meth:`Scene.image` call.
        near: every camera's near plane (anchors and Gaussians at view-space z <= near are
            culled; 0.2 as Scaffold-GS and HAC).

    Raises:
        SceneError: unknown layout, missing/unreadable files, unsupported camera model, empty
            point cloud; the message names the file or camera.
    """
    path = Path(path).expanduser().absolute()
    if not (resolution == -1 or (isinstance(resolution, int) and resolution > 0)):
        raise ValueError(f"resolution must be -1 or a positive integer, got {resolution!r}")
    if test_every < 1:
        raise ValueError(f"test_every must be >= 1, got {test_every}")
    fmt = detect_format(path)
    res: ReaderResult = (read_colmap(path, images, resolution) if fmt == "colmap"
                         else read_blender(path, images))

    # ---- order and split
    if fmt == "colmap":
        views = sorted(res.views, key=lambda v: v.name)
    elif res.info.get("split_source") == "files":
        views = sorted([v for v in res.views if v.split == "train"], key=lambda v: _natural_key(v.name))
        views += sorted([v for v in res.views if v.split == "test"], key=lambda v: _natural_key(v.name))
    else:
        views = sorted(res.views, key=lambda v: _natural_key(v.name))
    if len({v.name for v in views}) != len(views):
        raise SceneError(f"{path}: duplicate image names in the model")
    if not eval:
        is_test = [False] * len(views)
        split_desc = "none (eval off: every view is a training view)"
    elif fmt == "blender" and res.info.get("split_source") == "files":
        is_test = [v.split == "test" for v in views]
        split_desc = "from transforms_train.json / transforms_test.json"
    else:
        is_test = [k % test_every == 0 for k in range(len(views))]
        split_desc = f"every {test_every}th view in name order is a test view (index % " \
                     f"{test_every} == 0)"
    if all(is_test):
        raise SceneError(f"{path}: no training view: {len(views)} view(s), and the split ("
                         f"{split_desc}) makes every one a test view; a scene needs at least "
                         f"{2 if fmt != 'blender' else 1} views (or data.eval = false to train "
                         f"on all of them)")

    # ---- sizes, intrinsics, cache recipes
    cache_root = Path(cache_dir).expanduser() if cache_dir is not None else _default_cache_root(path)
    scene_dir = cache_root / f"{_safe(path.name)}-{hashlib.sha1(str(path).encode()).hexdigest()[:8]}"
    extra = res.info.get("folder_downscale")
    pinholes: dict[SourceCamera, tuple] = {}
    recipes: dict[int, ViewSource] = {}
    train, test = [], []
    models: dict[str, int] = {}
    for idx, (v, t) in enumerate(zip(views, is_test)):
        fsize = image_size(v.path)
        _check_aspect(v, fsize)
        size = _target_size(*fsize, resolution, extra)
        if v.source not in pinholes:
            pinholes[v.source] = choose_pinhole(v.source, undistort, where=str(v.path))
        fx, fy, cx, cy = pinholes[v.source]
        sx, sy = size[0] / v.source.width, size[1] / v.source.height
        models[v.source.model] = models.get(v.source.model, 0) + 1
        key = _cache_key(v, pinholes[v.source], fsize, size, undistort)
        sub = scene_dir / f"{size[0]}x{size[1]}"
        recipes[idx] = ViewSource(v.name, v.path, v.source, pinholes[v.source], fsize, size,
                               sub / f"{_safe(v.name)}-{key}.png")
        cam = Camera(viewmat=torch.from_numpy(v.w2c).float(), fx=fx * sx, fy=fy * sy,
                     cx=cx * sx, cy=cy * sy, width=size[0], height=size[1], near=float(near),
                     name=v.name, index=idx)
        (test if t else train).append(cam)

    # ---- points
    if res.points is not None:
        points = torch.from_numpy(res.points).float()
        colors = torch.from_numpy(res.colors).float()
        points_desc = f"SfM points3D ({len(points)})"
    else:
        rng = np.random.default_rng(seed)
        points = torch.from_numpy(rng.uniform(-random_init_extent, random_init_extent,
                                              (random_init_points, 3))).float()
        colors = torch.from_numpy(rng.uniform(0.0, 1.0, (random_init_points, 3))).float()
        points_desc = (f"random: {random_init_points} uniform in [-{random_init_extent}, "
                       f"{random_init_extent}]^3, seed {seed}")

    bg = torch.as_tensor(background, dtype=torch.float32).reshape(3)
    sizes = sorted({r.size for r in recipes.values()})
    fsizes = sorted({r.file_size for r in recipes.values()})
    protocol = {
        "format": fmt,
        "source": str(path),
        "image_folder": res.info.get("image_folder"),
        "resolution": resolution,
        "downscale": round(fsizes[0][0] / sizes[0][0], 6) if len(fsizes) == 1 and len(sizes) == 1
        else "per view",
        "image_size": list(sizes[0]) if len(sizes) == 1 else [list(s) for s in sizes],
        "resize_filter": "area (exact box average)",
        "split": split_desc,
        "eval": bool(eval),
        "test_every": test_every,
        "background": [float(x) for x in bg],
        "near": float(near),
        "n_train": len(train),
        "n_test": len(test),
        "points": points_desc,
        "n_points": len(points),
        "camera_models": models,
        "undistort": undistort if any(m not in ("PINHOLE", "SIMPLE_PINHOLE") for m in models)
        else None,
        "cache_dir": str(scene_dir),
    }
    if res.info.get("name_mapping") not in (None, "by name"):
        protocol["name_mapping"] = res.info["name_mapping"]
    scene = Scene(name=path.name, source_path=path, train_cameras=train, test_cameras=test,
                  points=points, colors=colors, extent=cameras_extent(train), background=bg,
                  protocol=protocol, _store=_ImageStore(recipes))
    if prefetch:
        scene._store.prefetch(f"caching {path.name} images {sizes[0][0]}x{sizes[0][1]}",
                              progress=progress)
    return scene
