"""Image I/O (OpenImageIO), area resampling and the atomic on-disk image cache.

Conventions used throughout the data layer:

* Arrays are ``[H, W, C]`` (channel last), ``C`` = 3 (RGB) or 4 (RGBA).
* Continuous pixel coordinates follow COLMAP and gsplat: the centre of pixel ``(row i, col j)``
  lies at ``(x, y) = (j + 0.5, i + 0.5)``; the image covers ``[0, W] x [0, H]``.
* The cache stores uint8 PNGs. RGBA images are stored with *premultiplied* colour, so that
  resampling is correct at alpha edges and compositing on any background is one linear step
  (``rgb + (1 - a) * background``) done when the image is read back.
* OpenImageIO by default converts alpha images to premultiplied ("associated") colour on read
  and back on write. We turn that off (``oiio:UnassociatedAlpha = 1``) on every read and write,
  so arrays hold exactly the file's values and the premultiplication is ours, done once.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import scipy.sparse

from baseline.fileio import atomic_path

from .errors import SceneError

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".exr", ".bmp")


def _raw_alpha_spec() -> "oiio.ImageSpec":
    """An open/write configuration that keeps alpha and colour as stored (no premultiplying)."""
    spec = oiio.ImageSpec()
    spec.attribute("oiio:UnassociatedAlpha", 1)
    return spec


def _open(path: Path) -> "oiio.ImageInput":
    from baseline.fileio import UnreadableFile, check_readable

    if not Path(path).exists():
        raise SceneError(f"image file not found: {path}")
    try:                         # a FIFO or a device would block or never end
        check_readable(path, "an image")
    except UnreadableFile as e:
        raise SceneError(str(e)) from None
    inp = oiio.ImageInput.open(str(path), _raw_alpha_spec())
    if inp is None:
        raise SceneError(f"cannot read image {path}: {oiio.geterror() or 'unknown format'} "
                         "(the file is corrupt or not an image; replace or remove it)")
    return inp


def image_size(path: str | Path) -> tuple[int, int]:
    """(width, height) of an image file, read from its header only."""
    inp = _open(Path(path))
    try:
        spec = inp.spec()
        return int(spec.width), int(spec.height)
    finally:
        inp.close()


def read_image(path: str | Path) -> np.ndarray:
    """Read an 8/16-bit (or float) JPEG/PNG/... as float32 ``[H, W, 3 or 4]`` in [0, 1].

    Grey images are replicated to RGB; grey+alpha becomes RGBA; an image with four or more
    channels keeps RGBA when its fourth channel is named ``A`` (else RGB). Alpha is *straight*
    (not premultiplied), as stored in PNG. Any decode error (including a truncated file, which
    some decoders would otherwise return half-filled) raises :class:`SceneError` naming the file.
    """
    path = Path(path)
    inp = _open(path)
    try:
        spec = inp.spec()
        nch = int(spec.nchannels)
        data = inp.read_image(0, 0, 0, nch, "float")
        err = inp.geterror() if inp.has_error else ""
    finally:
        inp.close()
    if data is None or err:
        raise SceneError(f"cannot read image {path}: {err or oiio.geterror() or 'decode failed'} "
                         "(the file is corrupt or truncated; replace or remove it)")
    data = np.asarray(data, dtype=np.float32)
    if data.ndim == 2:
        data = data[:, :, None]
    names = [str(n).upper() for n in spec.channelnames]
    if nch == 1:
        data = np.repeat(data, 3, axis=2)
    elif nch == 2:
        data = np.concatenate([np.repeat(data[:, :, :1], 3, axis=2), data[:, :, 1:2]], axis=2)
    elif nch == 3:
        pass
    elif len(names) >= 4 and names[3] == "A":
        data = data[:, :, :4]
    else:
        data = data[:, :, :3]
    return np.clip(data, 0.0, 1.0)


def premultiply(img: np.ndarray) -> np.ndarray:
    """RGBA with straight alpha -> RGBA with premultiplied colour (RGB images pass through)."""
    if img.shape[2] != 4:
        return img
    out = img.copy()
    out[:, :, :3] *= out[:, :, 3:4]
    return out


def _area_matrix(n_in: int, n_out: int) -> scipy.sparse.csr_matrix:
    """[n_out, n_in] weights of exact area (box) resampling along one axis.

    Output pixel ``o`` covers the input interval ``[o*s, (o+1)*s]`` with ``s = n_in / n_out``;
    its weight on input pixel ``i`` is the length of the overlap with ``[i, i+1]``, divided by
    ``s``. Rows sum to 1. For integer factors this is the plain block mean.
    """
    s = n_in / n_out
    rows, cols, vals = [], [], []
    span = int(np.ceil(s)) + 2
    o = np.arange(n_out)
    start = o * s
    first = np.floor(start).astype(np.int64)
    for k in range(span):
        i = first + k
        ok = i < n_in
        lo = np.maximum(start, i)
        hi = np.minimum(start + s, i + 1)
        w = np.clip(hi - lo, 0.0, None) / s
        keep = ok & (w > 0)
        rows.append(o[keep])
        cols.append(i[keep])
        vals.append(w[keep])
    return scipy.sparse.csr_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n_out, n_in))


def resize_area(img: np.ndarray, width: int, height: int) -> np.ndarray:
    """Resample ``[H, W, C]`` to ``[height, width, C]`` with an exact area (box) filter.

    Chosen over OpenImageIO's filtered resize because it is exact, deterministic and keeps the
    continuous pixel grid: output pixel edges sit at ``k * W / width`` of the input, so the
    intrinsics scale by the per-axis size ratio (as :meth:`Camera.scaled` assumes). Applied to
    premultiplied RGBA it is correct at alpha edges.
    """
    h, w, c = img.shape
    if (w, h) == (width, height):
        return img
    if w % width == 0 and h % height == 0:
        fx, fy = w // width, h // height
        return img.reshape(height, fy, width, fx, c).mean(axis=(1, 3), dtype=np.float64).astype(
            np.float32)
    ay = _area_matrix(h, height)
    ax = _area_matrix(w, width)
    tmp = ay @ img.reshape(h, w * c).astype(np.float64)          # [height, w*c]
    tmp = tmp.reshape(height, w, c).transpose(1, 0, 2).reshape(w, height * c)
    out = (ax @ tmp).reshape(width, height, c).transpose(1, 0, 2)
    return np.ascontiguousarray(out, dtype=np.float32)


def to_uint8(img: np.ndarray) -> np.ndarray:
    """round(clamp(x, 0, 1) * 255) as uint8."""
    return np.round(np.clip(img, 0.0, 1.0) * 255.0).astype(np.uint8)


def write_png_atomic(path: str | Path, img_u8: np.ndarray) -> None:
    """Write a uint8 ``[H, W, C]`` PNG atomically (:func:`baseline.fileio.atomic_path`).

    A reader never sees a half-written file; a failed write leaves ``path`` as it was and no
    temporary file. Not fsynced: these are renders and a rebuildable image cache.
    """
    h, w, c = img_u8.shape
    with atomic_path(path, fsync=False) as tmp:      # cache and renders: rename suffices
        out = oiio.ImageOutput.create(str(tmp))
        spec = oiio.ImageSpec(w, h, c, "uint8")
        spec.attribute("oiio:UnassociatedAlpha", 1)          # write the values as given
        if out is None or not out.open(str(tmp), spec):
            raise OSError(f"cannot write {path}: {oiio.geterror()}")
        ok = out.write_image(np.ascontiguousarray(img_u8))
        out.close()
        if not ok:
            raise OSError(f"cannot write {path}: {oiio.geterror()}")


def read_png_u8(path: str | Path) -> np.ndarray:
    """Read a cached uint8 PNG as ``[H, W, C]`` uint8 (values as stored)."""
    inp = oiio.ImageInput.open(str(path), _raw_alpha_spec())
    if inp is None:
        raise OSError(f"cannot read cached image {path}: {oiio.geterror()}")
    try:
        spec = inp.spec()
        data = inp.read_image(0, 0, 0, spec.nchannels, "uint8")
    finally:
        inp.close()
    if data is None:
        raise OSError(f"cannot read cached image {path}: {oiio.geterror()}")
    data = np.asarray(data)
    return data[:, :, None] if data.ndim == 2 else data
