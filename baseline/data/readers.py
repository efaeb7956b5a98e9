"""Format readers: COLMAP (via pycolmap) and Blender / instant-ngp ``transforms*.json``.

Each reader turns a scene folder into a list of :class:`ViewRecord` (image file, capture camera,
OpenCV world-to-camera pose) plus an initial point cloud. Everything about image sizes,
undistortion, caching and the train/test split is done by :mod:`baseline.data.scene`.
"""
from __future__ import annotations

import json
import math
import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap

from .errors import SceneError
from .images import IMAGE_EXTENSIONS
from .undistort import SourceCamera, check_supported

LAYOUTS = ("COLMAP: sparse/0/ (or sparse/) holding cameras, images and points3D as .bin or .txt, "
           "with the images in images/ or images_N/",
           "Blender / instant-ngp: transforms_train.json + transforms_test.json, or transforms.json")


@dataclass(frozen=True)
class ViewRecord:
    """One view as read from disk, before any resizing.

    Attributes:
        name: image name (sort key, ``Camera.name``).
        path: the image file.
        source: the capture camera at its calibration size.
        w2c: [4, 4] float64 world-to-camera matrix, OpenCV axes.
        split: "train" / "test" when the format fixes it, else None.
    """

    name: str
    path: Path
    source: SourceCamera
    w2c: np.ndarray = field(repr=False)
    split: str | None = None


@dataclass
class ReaderResult:
    fmt: str
    views: list[ViewRecord]
    points: np.ndarray | None      # [P, 3] float64, None -> random init
    colors: np.ndarray | None      # [P, 3] float in [0, 1]
    info: dict


def unknown_layout(path: Path) -> SceneError:
    return SceneError(f"{path}: not a recognized scene folder. Accepted layouts:\n  - "
                      + "\n  - ".join(LAYOUTS))


def detect_format(path: Path) -> str:
    """'colmap' or 'blender' for a scene folder, else :class:`SceneError`."""
    if not path.exists():
        raise SceneError(f"{path}: scene folder does not exist")
    if not path.is_dir():
        raise SceneError(f"{path}: not a folder. Accepted layouts:\n  - " + "\n  - ".join(LAYOUTS))
    if colmap_model_dir(path) is not None:
        return "colmap"
    if any(path.glob("transforms*.json")):
        return "blender"
    raise unknown_layout(path)


# --------------------------------------------------------------------------------------- COLMAP
def colmap_model_dir(path: Path) -> Path | None:
    for d in (path / "sparse" / "0", path / "sparse"):
        if (d / "cameras.bin").is_file() or (d / "cameras.txt").is_file():
            return d
    return None


MAX_JSON_BYTES = 256 << 20


def read_bounded(path: Path, cap: int) -> str:
    """A text file's content, refused above ``cap`` bytes or when it is not a regular file
    (a device, pipe or /proc file is never read to its end: :mod:`baseline.fileio`)."""
    from baseline.fileio import UnreadableFile, read_text_bounded

    try:
        return read_text_bounded(path, "a scene file", cap=cap)
    except UnreadableFile as e:
        raise SceneError(str(e)) from None


# the smallest record of each COLMAP binary file (bytes): cameras (id, model, width, height, one
# parameter), images (id, qvec, tvec, camera id, empty name + NUL, point count), points3D (id,
# xyz, rgb, error, track length)
_COLMAP_MIN_RECORD = {"cameras": 32, "images": 73, "points3D": 51}


def check_colmap_bin(path: Path, kind: str) -> None:
    """Walk a COLMAP ``.bin`` file's records checking every declared count (records, 2D points,
    track lengths) against the bytes left, so that a corrupt or hostile file is refused with its
    name before pycolmap sizes an allocation from it (a points3D.bin declaring 2^62 points made
    it allocate gigabytes). The walk reads counts only; pycolmap parses the values."""
    import struct

    from baseline.fileio import UnreadableFile, read_bytes_bounded

    try:
        data = read_bytes_bounded(path, f"a COLMAP {kind}.bin file")
    except UnreadableFile as e:
        raise SceneError(str(e)) from None
    size = len(data)

    def bad(what):
        return SceneError(f"{path}: corrupt COLMAP {kind}.bin: {what}")

    if size < 8:
        raise bad(f"{size} bytes, shorter than its record count")
    (n,) = struct.unpack_from("<Q", data, 0)
    if n * _COLMAP_MIN_RECORD[kind] > size - 8:
        raise bad(f"declares {n} records, more than its {size} bytes can hold")
    off = 8
    if kind == "cameras":
        for i in range(n):
            if off + 24 > size:
                raise bad(f"camera {i} cut off")
            (model,) = struct.unpack_from("<i", data, off + 4)
            n_par = _camera_params(int(model))
            if n_par is None:
                raise bad(f"camera {i} has an unknown model id {model}")
            off += 24 + 8 * n_par
    elif kind == "images":
        for i in range(n):
            end = off + 64
            if end > size:
                raise bad(f"image {i} cut off")
            nul = data.find(b"\0", end)
            if nul < 0:
                raise bad(f"image {i}: its name has no end")
            off = nul + 1
            if off + 8 > size:
                raise bad(f"image {i} cut off")
            (n2d,) = struct.unpack_from("<Q", data, off)
            off += 8
            if n2d > (size - off) // 24:
                raise bad(f"image {i} declares {n2d} 2D points, more than the bytes left")
            off += 24 * n2d
    else:
        for i in range(n):
            if off + 51 > size:
                raise bad(f"point {i} cut off")
            (tl,) = struct.unpack_from("<Q", data, off + 43)
            off += 51
            if tl > (size - off) // 8:
                raise bad(f"point {i} declares a track of {tl}, more than the bytes left")
            off += 8 * tl
    if off > size:
        raise bad("its records run past its end")


def _camera_params(model_id: int) -> int | None:
    """How many parameters a COLMAP camera model id has, as the installed pycolmap defines
    it; None for an id it does not know."""
    if not 0 <= model_id < 256:
        return None
    try:
        n = len(pycolmap.Camera.create_from_model_id(0, pycolmap.CameraModelId(model_id), 1.0,
                                                     10, 10).params)
    except Exception:  # noqa: BLE001 - any failure: not a model this pycolmap has
        return None
    return n or None


def _model_file(d: Path, stem: str) -> Path | None:
    for ext in (".bin", ".txt"):
        if (d / (stem + ext)).is_file():
            return d / (stem + ext)
    return None


def image_folders(path: Path) -> dict[int, Path]:
    """{downscale N: folder} for images/ (N = 1) and images_N/ folders of a COLMAP scene."""
    out = {}
    if (path / "images").is_dir():
        out[1] = path / "images"
    for d in path.iterdir():
        m = re.fullmatch(r"images_(\d+)", d.name)
        if m and d.is_dir() and int(m.group(1)) > 0:
            out[int(m.group(1))] = d
    return out


def choose_image_folder(path: Path, images: str | None, resolution: int) -> tuple[Path, float | None]:
    """The folder to read and the extra downscale factor still to apply (None: use the rule).

    Rules (COLMAP): an explicit ``images`` folder is used as is and ``resolution`` applies to its
    images. Otherwise, for ``resolution`` r in (1, 2, 4, 8): ``images_r/`` when it exists, else
    the folder with the largest N dividing r (``images/`` is N = 1), downscaled by r / N; for -1
    or a target width: ``images/``, or the highest-resolution ``images_N/`` when there is none.
    """
    if images is not None:
        folder = Path(images) if Path(images).is_absolute() else path / images
        if not folder.is_dir():
            avail = sorted(p.name for p in image_folders(path).values())
            raise SceneError(f"{folder}: image folder not found (available: {avail or 'none'})")
        return folder, None
    folders = image_folders(path)
    if not folders:
        raise SceneError(f"{path}: no images/ or images_N/ folder next to the COLMAP model")
    if resolution in (1, 2, 4, 8):
        divisors = [n for n in folders if resolution % n == 0]
        if not divisors:
            raise SceneError(
                f"{path}: resolution {resolution} needs images/ or images_N/ with N dividing "
                f"{resolution}; found only {sorted(f.name for f in folders.values())}. Pass "
                "images=<folder> (and a resolution relative to it) instead.")
        n = max(divisors)
        return folders[n], float(resolution // n)
    return folders[min(folders)], None


def _resolve_image_files(folder: Path, names: list[str], model_file: Path) -> tuple[list[Path], str]:
    """File path of each model image name; fall back to a sorted-order mapping (LLFF style)."""
    def find(name: str) -> Path | None:
        p = folder / name
        if p.is_file():
            return p
        stem = folder / Path(name).with_suffix("")
        for ext in IMAGE_EXTENSIONS:
            for e in (ext, ext.upper()):
                q = stem.with_suffix(e)
                if q.is_file():
                    return q
        return None

    found = [find(n) for n in names]
    if all(f is not None for f in found):
        return found, "by name"
    files = sorted(p for p in folder.iterdir()
                   if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS)
    if all(f is None for f in found) and len(files) == len(names):
        # LLFF-style folders rename the images (image000.png in the model, IMG_4026.png on disk):
        # with none matching and the counts equal, pair them in sorted order.
        order = sorted(range(len(names)), key=lambda i: names[i])
        out: list[Path] = [None] * len(names)  # type: ignore[list-item]
        for f, i in zip(files, order):
            out[i] = f
        warnings.warn(f"{folder}: no file matches the image names of {model_file}; pairing the "
                      f"{len(files)} files with the model's images in sorted order", stacklevel=3)
        return out, "by sorted order (model names not found in the folder)"
    missing = names[[f is None for f in found].index(True)]
    raise SceneError(f"{folder / missing}: image file referenced by {model_file} not found "
                     f"({sum(f is None for f in found)} of {len(names)} missing). Restore the file, "
                     "or remove the image from the model.")


def read_colmap(path: Path, images: str | None, resolution: int) -> ReaderResult:
    model_dir = colmap_model_dir(path)
    assert model_dir is not None
    files = {s: _model_file(model_dir, s) for s in ("cameras", "images", "points3D")}
    missing = [s for s, f in files.items() if f is None]
    if missing:
        raise SceneError(f"{model_dir}: incomplete COLMAP model, missing "
                         + ", ".join(f"{s}.bin/.txt" for s in missing))
    for stem, f in files.items():
        if f.suffix == ".bin":
            check_colmap_bin(f, stem)      # declared counts against the bytes, before pycolmap
    try:
        rec = pycolmap.Reconstruction(str(model_dir))
    except Exception as e:  # pycolmap raises assorted errors for broken files
        raise SceneError(f"{model_dir}: cannot read the COLMAP model: {e}") from e

    folder, extra = choose_image_folder(path, images, resolution)
    imgs = [im for im in rec.images.values() if im.has_pose]
    if len(imgs) < len(rec.images):
        warnings.warn(f"{files['images']}: {len(rec.images) - len(imgs)} unregistered images "
                      "skipped", stacklevel=2)
    if not imgs:
        raise SceneError(f"{files['images']}: the model has no registered images")
    sources: dict[int, SourceCamera] = {}
    for im in imgs:
        if im.camera_id not in sources:
            src = SourceCamera.from_pycolmap(rec.cameras[im.camera_id], camera_id=im.camera_id)
            check_supported(src, str(files["cameras"]))
            if (not all(math.isfinite(x) for x in src.params) or src.width <= 0
                    or src.height <= 0 or src.params[0] <= 0):
                raise SceneError(f"{files['cameras']}: camera {im.camera_id}: invalid "
                                 f"intrinsics {src.width}x{src.height} {list(src.params)}")
            sources[im.camera_id] = src
    names = [im.name for im in imgs]
    paths, mapping = _resolve_image_files(folder, names, files["images"])

    views = []
    for im, p in zip(imgs, paths):
        w2c = np.eye(4)
        w2c[:3, :4] = np.asarray(im.cam_from_world().matrix(), dtype=np.float64)
        if not np.isfinite(w2c).all():
            raise SceneError(f"{files['images']}: image {im.name}: its pose holds NaN or Inf")
        views.append(ViewRecord(name=im.name, path=p, source=sources[im.camera_id], w2c=w2c))

    pts = rec.points3D
    if len(pts) == 0:
        raise SceneError(f"{files['points3D']}: the point cloud is empty (0 points). Anchors are "
                         "initialised from SfM points: triangulate the model first (e.g. "
                         "`colmap point_triangulator`), or convert the scene to a "
                         "transforms.json layout to start from random points.")
    xyz = np.empty((len(pts), 3), dtype=np.float64)
    rgb = np.empty((len(pts), 3), dtype=np.float64)
    for k, p in enumerate(pts.values()):
        xyz[k] = p.xyz
        rgb[k] = p.color
    finite = np.isfinite(xyz).all(axis=1)
    if not finite.all():
        warnings.warn(f"{files['points3D']}: {int((~finite).sum())} points with NaN or Inf "
                      f"coordinates skipped", stacklevel=2)
        xyz, rgb = xyz[finite], rgb[finite]
        if not len(xyz):
            raise SceneError(f"{files['points3D']}: no point has finite coordinates")
    info = {"image_folder": folder.name, "folder_downscale": extra, "name_mapping": mapping,
            "model": str(model_dir)}
    return ReaderResult("colmap", views, xyz, rgb / 255.0, info)


# -------------------------------------------------------------------------------------- Blender
_DIST_KEYS = ("k1", "k2", "p1", "p2")
_UNSUPPORTED_DIST_KEYS = ("k3", "k4", "k5", "k6")


def _frame_image(json_path: Path, file_path: str) -> Path:
    p = (json_path.parent / file_path)
    if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS:
        return p
    for ext in IMAGE_EXTENSIONS:
        for e in (ext, ext.upper()):
            q = Path(str(p) + e)
            if q.is_file():
                return q
    raise SceneError(f"{p}: image file referenced by {json_path} not found (tried the name as "
                     f"given and with extensions {', '.join(IMAGE_EXTENSIONS)})")


def _number(meta: dict, key: str, where: str, lo: float = -math.inf, hi: float = math.inf,
            default=None, open_lo: bool = False) -> float:
    """``meta[key]`` as a finite float in [lo, hi] (``(lo, hi]`` with ``open_lo``), else a
    :class:`SceneError` naming the key and where it is."""
    v = meta.get(key, default)
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise SceneError(f"{where}: '{key}' must be a number, got {v!r:.60}")
    v = float(v)
    if not math.isfinite(v) or v < lo or v > hi or (open_lo and v == lo):
        raise SceneError(f"{where}: '{key}' = {v} is out of range "
                         f"{'(' if open_lo else '['}{lo}, {hi}]")
    return v


def _blender_camera(json_path: Path, meta: dict, size: tuple[int, int],
                    where: str | None = None) -> SourceCamera:
    w, h = size
    where = where or str(json_path)
    model = meta.get("camera_model", "")
    if model is None:
        model = ""
    if not isinstance(model, str):
        raise SceneError(f"{where}: 'camera_model' must be a string, got {model!r:.60}")
    if meta.get("is_fisheye") or model.upper() not in ("", "OPENCV", "PINHOLE"):
        raise SceneError(f"{where}: camera model {model or 'fisheye'} is not supported "
                         "(supported: pinhole with optional k1, k2, p1, p2 distortion)")
    if "fl_x" in meta:
        W0 = int(_number(meta, "w", where, 1, 1 << 20, default=w))
        H0 = int(_number(meta, "h", where, 1, 1 << 20, default=h))
        fx = _number(meta, "fl_x", where, 0, 1e9, open_lo=True)
        fy = _number(meta, "fl_y", where, 0, 1e9, default=fx, open_lo=True)
        cx = _number(meta, "cx", where, -1e9, 1e9, default=W0 / 2)
        cy = _number(meta, "cy", where, -1e9, 1e9, default=H0 / 2)
    elif "camera_angle_x" in meta:
        W0, H0 = w, h
        ax = _number(meta, "camera_angle_x", where, 0, math.pi - 1e-6, open_lo=True)
        fx = 0.5 * W0 / math.tan(0.5 * ax)
        fy = (0.5 * H0 / math.tan(0.5 * _number(meta, "camera_angle_y", where, 0,
                                                math.pi - 1e-6, open_lo=True))
              if "camera_angle_y" in meta else fx)
        cx, cy = W0 / 2, H0 / 2
    else:
        raise SceneError(f"{where}: no intrinsics: expected camera_angle_x or fl_x (+ fl_y, "
                         "cx, cy, w, h)")
    bad = [k for k in _UNSUPPORTED_DIST_KEYS if _number(meta, k, where, default=0.0) != 0.0]
    if bad:
        raise SceneError(f"{where}: distortion terms {bad} are not supported (supported: "
                         "k1, k2, p1, p2); undistort the images first")
    dist = [_number(meta, k, where, -1e3, 1e3, default=0.0) for k in _DIST_KEYS]
    if any(dist):
        return SourceCamera("OPENCV", W0, H0, (fx, fy, cx, cy, *dist))
    return SourceCamera("PINHOLE", W0, H0, (fx, fy, cx, cy))


def _read_transforms(json_path: Path, split: str | None) -> list[ViewRecord]:
    from .images import image_size
    try:
        meta = json.loads(read_bounded(json_path, MAX_JSON_BYTES))
    except (OSError, ValueError) as e:
        raise SceneError(f"{json_path}: cannot parse: {e}") from e
    except RecursionError:
        raise SceneError(f"{json_path}: cannot parse: nested too deeply") from None
    if not isinstance(meta, dict):
        raise SceneError(f"{json_path}: the top level must be an object with a 'frames' list, "
                         f"got a {type(meta).__name__}")
    frames = meta.get("frames")
    if not isinstance(frames, list):
        raise SceneError(f"{json_path}: no 'frames' list")
    top = {k: v for k, v in meta.items() if k != "frames"}
    views = []
    for i, fr in enumerate(frames):
        where = f"{json_path}, frame {i}"
        if not isinstance(fr, dict) or "file_path" not in fr or "transform_matrix" not in fr:
            raise SceneError(f"{where}: a frame must be an object with file_path and "
                             f"transform_matrix")
        if not isinstance(fr["file_path"], str) or not fr["file_path"]:
            raise SceneError(f"{where}: 'file_path' must be a non-empty string")
        p = _frame_image(json_path, fr["file_path"])
        src = _blender_camera(json_path, {**top, **fr}, image_size(p), where)
        try:
            m = np.asarray(fr["transform_matrix"], dtype=np.float64)
        except (TypeError, ValueError):
            raise SceneError(f"{where}: 'transform_matrix' is not a numeric matrix") from None
        if m.ndim != 2 or m.shape[0] not in (3, 4) or m.shape[1] != 4:
            raise SceneError(f"{where}: 'transform_matrix' must be 3x4 or 4x4, got shape "
                             f"{tuple(m.shape)}")
        if not np.isfinite(m).all():
            raise SceneError(f"{where}: 'transform_matrix' holds NaN or Inf")
        c2w = np.eye(4)
        c2w[: m.shape[0], :4] = m[:, :4]
        if abs(np.linalg.det(c2w[:3, :3])) < 1e-12:
            raise SceneError(f"{where}: 'transform_matrix' has a singular rotation part")
        c2w[:3, 1:3] *= -1.0            # OpenGL/Blender (y up, z back) -> OpenCV (y down, z fwd)
        name = re.sub(r"^\./", "", str(fr["file_path"]))
        name = str(Path(name).with_suffix("")) if Path(name).suffix.lower() in IMAGE_EXTENSIONS \
            else name
        views.append(ViewRecord(name=name, path=p, source=src, w2c=np.linalg.inv(c2w),
                                split=split))
    return views


def read_blender(path: Path, images: str | None) -> ReaderResult:
    if images is not None:
        raise SceneError(f"{path}: images={images!r} applies to COLMAP scenes only; Blender scenes "
                         "take their image paths from transforms*.json")
    train, test = path / "transforms_train.json", path / "transforms_test.json"
    if train.is_file():
        views = _read_transforms(train, "train")
        if test.is_file():
            views += _read_transforms(test, "test")
        split = "files"
        jsons = [train.name] + ([test.name] if test.is_file() else [])
    elif (path / "transforms.json").is_file():
        views = _read_transforms(path / "transforms.json", None)
        split = "every_n"
        jsons = ["transforms.json"]
    else:
        found = sorted(p.name for p in path.glob("transforms*.json"))
        raise SceneError(f"{path}: found {found} but need transforms_train.json (+ "
                         "transforms_test.json) or transforms.json")
    if not views:
        raise SceneError(f"{path / jsons[0]}: no frames")
    return ReaderResult("blender", views, None, None,
                        {"image_folder": ", ".join(jsons), "folder_downscale": None,
                         "split_source": split})
