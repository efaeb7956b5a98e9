"""The procedural COLMAP scene: readable, deterministic, seed- and texture-dependent, loadable."""
from __future__ import annotations

import warnings

import numpy as np
import pycolmap
import pytest
import torch

from baseline.data import load_scene
from baseline.data.images import read_image, read_png_u8
from baseline.data.synthetic import World, make_scene

torch.set_num_threads(1)

SMALL = dict(n_views=12, width=64, height=48, n_points=500)


def _files(root):
    return sorted(p.relative_to(root) for p in root.rglob("*") if p.is_file())


def test_readable_by_pycolmap(tmp_path):
    out = make_scene(tmp_path / "s", **SMALL)
    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    assert rec.num_images() == 12 and rec.num_cameras() == 1 and rec.num_points3D() == 500
    cam = rec.cameras[1]
    assert cam.model.name == "PINHOLE" and (cam.width, cam.height) == (64, 48)
    assert cam.principal_point_x == 32 and cam.principal_point_y == 24
    names = sorted(im.name for im in rec.images.values())
    assert names == [f"view_{k:03d}.png" for k in range(12)]
    for name in names:
        img = read_image(out / "images" / name)
        assert img.shape == (48, 64, 3)
    # points lie in the scene's bounds and are seen by the cameras that sampled them
    xyz = np.array([p.xyz for p in rec.points3D.values()])
    assert np.all(np.abs(xyz[:, :2]) < 3.1) and xyz[:, 2].min() > -0.05 and xyz[:, 2].max() < 1.2
    # every camera looks at the scene centre: it projects near the principal point
    for im in rec.images.values():
        p = cam.img_from_cam(im.cam_from_world() * np.array([0.0, 0.0, 0.35]))
        assert abs(p[0] - 32) < 6 and abs(p[1] - 24) < 6


def test_deterministic_for_a_seed(tmp_path):
    a = make_scene(tmp_path / "a", seed=3, **SMALL)
    b = make_scene(tmp_path / "b", seed=3, **SMALL)
    files = _files(a)
    assert files == _files(b) and len(files) >= 12 + 3
    for f in files:
        assert (a / f).read_bytes() == (b / f).read_bytes(), f


def test_different_seed_differs(tmp_path):
    a = make_scene(tmp_path / "a", seed=0, **SMALL)
    b = make_scene(tmp_path / "b", seed=1, **SMALL)
    for k in (0, 5):
        ia = read_image(a / "images" / f"view_{k:03d}.png")
        ib = read_image(b / "images" / f"view_{k:03d}.png")
        assert np.abs(ia - ib).mean() > 0.01
    assert (a / "sparse/0/points3D.bin").read_bytes() != (b / "sparse/0/points3D.bin").read_bytes()


def _ground_colours(world: World) -> np.ndarray:
    """Shaded colours of the ground's far corners seen straight from above (no shadows)."""
    g = np.linspace(2.5, 2.95, 12)
    x, y = np.meshgrid(np.concatenate([-g, g]), np.concatenate([-g, g]))
    o = np.stack([x.ravel(), y.ravel(), np.full(x.size, 5.0)], 1)
    d = np.tile([0.0, 0.0, -1.0], (len(o), 1))
    rgb, t, _ = world.trace(o, d)
    assert np.all(np.isfinite(t))
    return rgb


def test_texture_detail(tmp_path):
    flat = _ground_colours(World(seed=0, texture_detail=0.0))
    assert np.ptp(flat, axis=0).max() == 0.0              # flat colour: shading only
    textured = _ground_colours(World(seed=0, texture_detail=1.0))
    assert textured.std(axis=0).max() > 0.03
    # the images: flat texture has far less fine detail than the default
    a = make_scene(tmp_path / "flat", texture_detail=0.0, **SMALL)
    b = make_scene(tmp_path / "tex", texture_detail=1.0, **SMALL)

    def detail(root):
        img = read_image(root / "images" / "view_004.png")
        return np.abs(np.diff(img, axis=1)).mean() + np.abs(np.diff(img, axis=0)).mean()
    assert detail(a) < 0.6 * detail(b)


def test_loads_with_every_8th_split(tmp_path):
    out = make_scene(tmp_path / "s", n_views=20, width=64, height=48, n_points=400)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        s = load_scene(out, cache_dir=tmp_path / "cache")
    assert [c.index for c in s.test_cameras] == [0, 8, 16]
    assert [c.name for c in s.test_cameras] == ["view_000.png", "view_008.png", "view_016.png"]
    assert len(s.train_cameras) == 17 and s.points.shape == (400, 3)
    img = s.image(s.train_cameras[0])
    assert img.shape == (48, 64, 3)
    ref = read_png_u8(out / "images" / "view_001.png")      # PINHOLE at -1: same uint8 values
    assert np.array_equal(np.round(img.numpy() * 255).astype(np.uint8), ref)


@pytest.mark.parametrize("model,dist", [("SIMPLE_RADIAL", (0.05,)),
                                        ("OPENCV", (0.05, -0.01, 0.001, 0.0))])
def test_distorted_models_render(tmp_path, model, dist):
    out = make_scene(tmp_path / "s", camera_model=model, distortion=dist, **SMALL)
    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    cam = rec.cameras[1]
    assert cam.model.name == model and list(cam.params[-len(dist):]) == pytest.approx(list(dist))
