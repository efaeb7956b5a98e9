"""Units of the data layer: distortion mapping against COLMAP's formulas written out by hand,
the pinhole choice, the remap, the area resize and image I/O."""
from __future__ import annotations

import numpy as np
import OpenImageIO as oiio
import pytest

import baseline.data.images as images_mod
import baseline.fileio as fileio_mod
from baseline.data.errors import SceneError
from baseline.data.images import read_image, resize_area, write_png_atomic
from baseline.data.undistort import (SourceCamera, choose_pinhole, distort_pixels, remap,
                                     undistort_map, _border)


def colmap_distort(model, params, xy):
    """COLMAP's projection of normalized points xy [N, 2], from its camera model formulas."""
    u, v = xy[:, 0], xy[:, 1]
    r2 = u * u + v * v
    if model == "SIMPLE_RADIAL":
        f, cx, cy, k = params
        fx = fy = f
        du, dv = u * k * r2, v * k * r2
    elif model == "RADIAL":
        f, cx, cy, k1, k2 = params
        fx = fy = f
        rad = k1 * r2 + k2 * r2 * r2
        du, dv = u * rad, v * rad
    elif model == "OPENCV":
        fx, fy, cx, cy, k1, k2, p1, p2 = params
        rad = k1 * r2 + k2 * r2 * r2
        du = u * rad + 2 * p1 * u * v + p2 * (r2 + 2 * u * u)
        dv = v * rad + 2 * p2 * u * v + p1 * (r2 + 2 * v * v)
    else:
        raise ValueError(model)
    return np.stack([fx * (u + du) + cx, fy * (v + dv) + cy], 1)


CAMS = [
    SourceCamera("SIMPLE_RADIAL", 400, 300, (350.0, 201.0, 148.0, 0.06), 1),
    SourceCamera("RADIAL", 400, 300, (330.0, 198.0, 152.0, 0.05, -0.01), 2),
    SourceCamera("OPENCV", 400, 300, (340.0, 335.0, 203.0, 149.0, 0.07, -0.02, 0.003, -0.002), 3),
]


@pytest.mark.parametrize("cam", CAMS, ids=lambda c: c.model)
@pytest.mark.parametrize("file_size", [(400, 300), (200, 150)])
def test_distort_pixels_matches_colmap_formulas(cam, file_size):
    pin = choose_pinhole(cam, "crop")
    rng = np.random.default_rng(0)
    uv = rng.uniform([0, 0], file_size, size=(500, 2))
    got = distort_pixels(cam, pin, uv, file_size)
    s = np.array(file_size) / [cam.width, cam.height]
    fx, fy, cx, cy = pin
    xy = np.stack([(uv[:, 0] / s[0] - cx) / fx, (uv[:, 1] / s[1] - cy) / fy], 1)
    expect = colmap_distort(cam.model, cam.params, xy) * s
    assert np.abs(got - expect).max() < 1e-9


@pytest.mark.parametrize("cam", CAMS, ids=lambda c: c.model)
def test_crop_is_the_smallest_zoom_without_blank_pixels(cam):
    fx0, fy0, cx0, cy0 = cam.intrinsics()
    fx, fy, cx, cy = choose_pinhole(cam, "crop")
    s = fx / fx0
    assert fy / fy0 == pytest.approx(s) and (cx, cy) == (cx0, cy0) and s > 1.0
    size = (cam.width, cam.height)
    border = _border(*size)

    def inside(scale):
        src = distort_pixels(cam, (fx0 * scale, fy0 * scale, cx, cy), border, size)
        return bool(np.all((src >= -1e-6) & (src <= np.array(size) + 1e-6)))
    assert inside(s) and not inside(s * (1 - 1e-5))
    assert choose_pinhole(cam, "keep") == (fx0, fy0, cx0, cy0)


def test_barrel_distortion_keeps_focal():
    cam = SourceCamera("SIMPLE_RADIAL", 400, 300, (350.0, 200.0, 150.0, -0.05), 7)
    assert choose_pinhole(cam, "crop") == cam.intrinsics()
    pin = SourceCamera("PINHOLE", 400, 300, (350.0, 351.0, 200.0, 150.0))
    assert choose_pinhole(pin, "crop") == (350.0, 351.0, 200.0, 150.0)


def test_non_invertible_distortion_is_rejected():
    cam = SourceCamera("SIMPLE_RADIAL", 400, 300, (150.0, 200.0, 150.0, -0.9), 4)
    with pytest.raises(SceneError, match="camera 4"):
        choose_pinhole(cam, "crop", where="x")


def test_undistort_map_centres_and_remap():
    cam = CAMS[0]
    pin = choose_pinhole(cam, "crop")
    mx, my = undistort_map(cam, pin, (40, 30))
    assert mx.shape == (30, 40)
    q = distort_pixels(cam, pin, np.array([[7.5, 11.5]]), (40, 30))[0]
    assert (mx[11, 7], my[11, 7]) == pytest.approx(tuple(q))
    rng = np.random.default_rng(1)
    img = rng.uniform(size=(30, 40, 3)).astype(np.float32)
    # identity map at pixel centres reproduces the image; integer shifts move it exactly
    u, v = np.meshgrid(np.arange(40) + 0.5, np.arange(30) + 0.5)
    assert np.array_equal(remap(img, u, v), img)
    shifted = remap(img, u + 2, v + 1)
    assert np.allclose(shifted[:-1, :-2], img[1:, 2:])
    # half-way between two pixels: their mean; outside the image: blank
    half = remap(img, u[:, :-1] + 0.5, v[:, :-1])
    assert np.allclose(half, 0.5 * (img[:, :-1] + img[:, 1:]), atol=1e-6)
    out = remap(img, u - 5, v)
    assert np.all(out[:, :4] == 0) and np.allclose(out[:, 5:], img[:, :-5])


def test_resize_area():
    rng = np.random.default_rng(2)
    img = rng.uniform(size=(24, 40, 3)).astype(np.float32)
    # integer factor: block mean
    assert np.allclose(resize_area(img, 10, 6), img.reshape(6, 4, 10, 4, 3).mean(axis=(1, 3)))
    # non-integer factor 40 -> 25 (8/5) and 24 -> 15: nearest x5 upsampling then 8x8 block mean
    # is exact area averaging
    up = img.repeat(5, axis=0).repeat(5, axis=1)
    brute = up.reshape(15, 8, 25, 8, 3).mean(axis=(1, 3))
    assert np.allclose(resize_area(img, 25, 15), brute, atol=1e-6)
    odd = resize_area(img, 17, 11)                              # any size: mean is preserved
    assert odd.shape == (11, 17, 3) and odd.mean() == pytest.approx(img.mean(), rel=1e-5)
    assert np.allclose(resize_area(np.full((9, 13, 4), 0.25, np.float32), 5, 4), 0.25)


def _write(path, arr, fmt):
    out = oiio.ImageOutput.create(str(path))
    h, w, c = arr.shape
    spec = oiio.ImageSpec(w, h, c, fmt)
    spec.attribute("oiio:UnassociatedAlpha", 1)          # store exactly these values
    assert out.open(str(path), spec)
    out.write_image(arr)
    out.close()


def test_read_image_formats(tmp_path):
    v16 = np.array([[[0, 1000, 65535]]], np.uint16).repeat(2, 0).repeat(3, 1)
    _write(tmp_path / "a.png", v16, "uint16")
    a = read_image(tmp_path / "a.png")
    assert a.dtype == np.float32 and a.shape == (2, 3, 3)
    assert a[0, 0] == pytest.approx([0, 1000 / 65535, 1], abs=1e-6)
    _write(tmp_path / "g.png", np.full((2, 3, 1), 51, np.uint8), "uint8")
    g = read_image(tmp_path / "g.png")
    assert g.shape == (2, 3, 3) and np.allclose(g, 0.2)
    ga = np.concatenate([np.full((2, 3, 1), 51, np.uint8), np.full((2, 3, 1), 255, np.uint8)], 2)
    _write(tmp_path / "ga.png", ga, "uint8")
    assert read_image(tmp_path / "ga.png").shape == (2, 3, 4)
    rgba = np.zeros((2, 3, 4), np.uint8)
    rgba[..., 0], rgba[..., 3] = 200, 100
    _write(tmp_path / "c.png", rgba, "uint8")
    c = read_image(tmp_path / "c.png")                           # straight alpha, as stored
    assert c[0, 0] == pytest.approx([200 / 255, 0, 0, 100 / 255], abs=1e-6)
    with pytest.raises(SceneError, match="nothere.png"):
        read_image(tmp_path / "nothere.png")


def test_write_png_atomic(tmp_path, monkeypatch):
    img = np.arange(2 * 3 * 3, dtype=np.uint8).reshape(2, 3, 3)
    write_png_atomic(tmp_path / "sub" / "x.png", img)
    assert np.array_equal(images_mod.read_png_u8(tmp_path / "sub" / "x.png"), img)

    def boom(src, dst):
        raise OSError("disk full")
    monkeypatch.setattr(fileio_mod.os, "replace", boom)
    with pytest.raises(OSError, match="disk full"):
        write_png_atomic(tmp_path / "sub" / "y.png", img)
    assert sorted(p.name for p in (tmp_path / "sub").iterdir()) == ["x.png"]
