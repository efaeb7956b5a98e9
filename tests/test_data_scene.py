"""load_scene on synthetic scenes built in tmp_path: split, intrinsics, resolution rules, cache,
the Blender / instant-ngp readers and undistortion of rendered distorted captures."""
from __future__ import annotations

import json
import os
import shutil

import numpy as np
import pycolmap
import pytest
import torch

import baseline.data.scene as scene_mod
from baseline.data import load_scene
from baseline.data.images import read_png_u8, write_png_atomic
from baseline.data.synthetic import World, make_scene
from baseline.eval.metrics import psnr

torch.set_num_threads(1)

W, H = 64, 48


@pytest.fixture(scope="module")
def syn(tmp_path_factory):
    return make_scene(tmp_path_factory.mktemp("syn") / "scene", n_views=20, width=W, height=H,
                      n_points=400, seed=5)


def copy_scene(src, dst):
    shutil.copytree(src, dst)
    return dst


def u8(img: torch.Tensor) -> np.ndarray:
    return np.round(img.numpy() * 255).astype(np.uint8)


def test_cameras_split_points(syn, tmp_path):
    s = load_scene(syn, cache_dir=tmp_path)
    rec = pycolmap.Reconstruction(str(syn / "sparse" / "0"))
    cams = s.cameras
    assert [c.index for c in cams] == list(range(20))
    assert [c.name for c in cams] == sorted(im.name for im in rec.images.values())
    assert [c.index for c in s.test_cameras] == [0, 8, 16]
    pc = rec.cameras[1]
    by_name = {im.name: im for im in rec.images.values()}
    for c in cams:
        assert (c.width, c.height) == (W, H)
        assert (c.fx, c.fy, c.cx, c.cy) == pytest.approx(tuple(pc.params))
        ref = np.asarray(by_name[c.name].cam_from_world().matrix())
        assert np.allclose(c.viewmat[:3].numpy(), ref, atol=1e-6)
        assert c.viewmat.dtype == torch.float32 and torch.equal(c.viewmat[3], torch.tensor([0., 0, 0, 1]))
    xyz = np.array([p.xyz for p in rec.points3D.values()])
    assert np.allclose(s.points.numpy(), xyz, atol=1e-5)
    centers = np.array([by_name[c.name].projection_center() for c in s.train_cameras])
    assert s.extent == pytest.approx(1.1 * np.linalg.norm(centers - centers.mean(0), axis=1).max(),
                                     rel=1e-5)
    p = s.protocol
    assert (p["n_train"], p["n_test"], p["image_folder"], p["image_size"]) == (17, 3, "images", [W, H])
    assert p["background"] == [0.0, 0.0, 0.0] and p["downscale"] == 1.0

    s2 = load_scene(syn, cache_dir=tmp_path, eval=False)
    assert len(s2.train_cameras) == 20 and not s2.test_cameras
    s3 = load_scene(syn, cache_dir=tmp_path, test_every=4)
    assert [c.index for c in s3.test_cameras] == [0, 4, 8, 12, 16]


def test_resolution_rules(syn, tmp_path):
    full = load_scene(syn, cache_dir=tmp_path)
    half = load_scene(syn, cache_dir=tmp_path, resolution=2)
    c1, c2 = full.train_cameras[3], half.train_cameras[3]
    assert (c2.width, c2.height) == (32, 24)
    assert (c2.fx, c2.fy, c2.cx, c2.cy) == pytest.approx((c1.fx / 2, c1.fy / 2, c1.cx / 2, c1.cy / 2))
    # area filter: the 2x2 block mean of the original, rounded (either way at .5 ties)
    orig = read_png_u8(syn / "images" / c1.name).astype(np.float64)
    block = orig.reshape(24, 2, 32, 2, 3).mean(axis=(1, 3))
    assert np.abs(u8(half.image(c2)) - block).max() <= 0.5 + 1e-9
    # a positive resolution outside 1/2/4/8 is a target width (3DGS convention)
    w40 = load_scene(syn, cache_dir=tmp_path, resolution=40)
    c40 = w40.train_cameras[3]
    assert (c40.width, c40.height) == (40, 30)
    assert c40.fx == pytest.approx(c1.fx * 40 / 64) and c40.fy == pytest.approx(c1.fy * 30 / 48)
    with pytest.raises(ValueError):
        load_scene(syn, cache_dir=tmp_path, resolution=0)


def test_images_n_folder_preferred(syn, tmp_path):
    sc = copy_scene(syn, tmp_path / "scene")
    (sc / "images_2").mkdir()
    for f in (sc / "images").iterdir():          # a recognizable images_2: constant grey
        write_png_atomic(sc / "images_2" / f.name, np.full((24, 32, 3), 77, np.uint8))
    s = load_scene(sc, cache_dir=tmp_path / "c", resolution=2)
    assert s.protocol["image_folder"] == "images_2"
    assert np.all(u8(s.image(s.train_cameras[0])) == 77)
    s4 = load_scene(sc, cache_dir=tmp_path / "c", resolution=4)      # images_2 downscaled by 2
    assert s4.protocol["image_folder"] == "images_2" and s4.protocol["image_size"] == [16, 12]
    s1 = load_scene(sc, cache_dir=tmp_path / "c", images="images_2", resolution=2)
    assert s1.protocol["image_size"] == [16, 12]            # explicit folder: r divides it
    assert s1.train_cameras[0].fx == pytest.approx(s4.train_cameras[0].fx)
    assert load_scene(sc, cache_dir=tmp_path / "c").protocol["image_folder"] == "images"


def test_text_model_and_sparse_without_0(syn, tmp_path):
    a = copy_scene(syn, tmp_path / "a")
    rec = pycolmap.Reconstruction(str(a / "sparse" / "0"))
    for f in (a / "sparse" / "0").iterdir():
        f.unlink()
    rec.write_text(str(a / "sparse" / "0"))
    b = copy_scene(syn, tmp_path / "b")
    for f in (b / "sparse" / "0").iterdir():
        f.rename(b / "sparse" / f.name)
    (b / "sparse" / "0").rmdir()
    ref = load_scene(syn, cache_dir=tmp_path / "c", prefetch=False)
    for path in (a, b):
        s = load_scene(path, cache_dir=tmp_path / "c", prefetch=False)
        assert [c.name for c in s.cameras] == [c.name for c in ref.cameras]
        assert torch.allclose(s.cameras[7].viewmat, ref.cameras[7].viewmat, atol=1e-6)
        assert torch.allclose(s.points, ref.points, atol=1e-5)


def test_cache_lazy_bounded_atomic(syn, tmp_path, monkeypatch):
    s = load_scene(syn, cache_dir=tmp_path, prefetch=False)
    cache = s.protocol["cache_dir"]
    assert not any(p.suffix == ".png" for p in tmp_path.rglob("*"))      # nothing built yet
    reads = []
    real = scene_mod.read_png_u8
    monkeypatch.setattr(scene_mod, "read_png_u8", lambda p: reads.append(p) or real(p))
    img = s.image(s.test_cameras[1])
    assert img.shape == (H, W, 3) and len(reads) == 1
    assert len(list(tmp_path.rglob("*.png"))) == 1                        # only that image
    assert str(s.view_source(s.test_cameras[1]).cache_file).startswith(cache)
    # prefetch builds the rest; a second load reuses every file without decoding a source
    load_scene(syn, cache_dir=tmp_path)
    assert len(list(tmp_path.rglob("*.png"))) == 20
    monkeypatch.setattr(scene_mod.ViewSource, "build",
                        lambda self: pytest.fail("cache entry rebuilt"))
    s2 = load_scene(syn, cache_dir=tmp_path)
    s2.image(s2.train_cameras[0])
    assert not [p for p in tmp_path.rglob("*") if ".tmp" in p.name]      # no temp leftovers
    # a camera of another scene / size is refused
    with pytest.raises(ValueError):
        s2.image(s2.train_cameras[0].scaled(0.5))


def test_cache_invalidated_by_source_change(syn, tmp_path):
    sc = copy_scene(syn, tmp_path / "scene")
    s = load_scene(sc, cache_dir=tmp_path / "c")
    cam = s.train_cameras[0]
    before = s.view_source(cam).cache_file
    write_png_atomic(sc / "images" / cam.name, np.full((H, W, 3), 200, np.uint8))
    os.utime(sc / "images" / cam.name, ns=(1, 1))
    s2 = load_scene(sc, cache_dir=tmp_path / "c")
    assert s2.view_source(cam).cache_file != before
    assert np.all(u8(s2.image(s2.train_cameras[0])) == 200)


def test_default_cache_dir(syn, tmp_path, monkeypatch):
    sc = copy_scene(syn, tmp_path / "scene")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    s = load_scene(sc, prefetch=False)
    s.image(s.train_cameras[0])
    assert s.protocol["cache_dir"].startswith(str(tmp_path / "xdg" / "pgs"))
    assert not (sc / ".pgs_cache").exists(), "the scene folder must stay untouched"


# ------------------------------------------------------------------------ Blender / instant-ngp
def _c2w_opengl(cam) -> list:
    c2w = np.linalg.inv(cam.viewmat.double().numpy())
    c2w[:3, 1:3] *= -1
    return c2w.tolist()


def _rgba(src, dst):
    """Copy a PNG adding an alpha channel: top-left quarter transparent, top-right 100/255."""
    img = read_png_u8(src)
    a = np.full(img.shape[:2] + (1,), 255, np.uint8)
    a[: img.shape[0] // 2, : img.shape[1] // 2] = 0
    a[: img.shape[0] // 2, img.shape[1] // 2:] = 100
    write_png_atomic(dst, np.concatenate([img, a], axis=2))


def test_blender_split_files_and_rgba(syn, tmp_path):
    ref = load_scene(syn, cache_dir=tmp_path / "c")
    bl = tmp_path / "blender"
    (bl / "train").mkdir(parents=True)
    (bl / "test").mkdir()
    angle = 2 * np.arctan(0.5 * W / ref.cameras[0].fx)
    for split, cams in (("train", ref.train_cameras), ("test", ref.test_cameras)):
        frames = []
        for c in cams:
            stem = c.name[:-4]
            _rgba(syn / "images" / c.name, bl / split / f"{stem}.png")
            frames.append({"file_path": f"./{split}/{stem}", "transform_matrix": _c2w_opengl(c)})
        (bl / f"transforms_{split}.json").write_text(
            json.dumps({"camera_angle_x": angle, "frames": frames}))
    s = load_scene(bl, cache_dir=tmp_path / "c", background=(1.0, 0.0, 0.0))
    assert len(s.train_cameras) == 17 and len(s.test_cameras) == 3
    assert s.protocol["format"] == "blender" and s.points.shape == (10000, 3)
    assert float(s.points.abs().max()) <= 1.3
    c, r = s.train_cameras[2], ref.train_cameras[2]
    assert c.name == "train/" + r.name[:-4]
    assert (c.fx, c.fy, c.cx, c.cy) == pytest.approx((r.fx, r.fy, r.cx, r.cy))
    assert torch.allclose(c.viewmat, r.viewmat, atol=1e-5)         # OpenGL c2w -> OpenCV w2c
    img, rimg = s.image(c), ref.image(r)
    assert torch.all(img[: H // 2, : W // 2] == torch.tensor([1.0, 0.0, 0.0]))
    assert torch.equal(img[H // 2:], rimg[H // 2:])
    # semi-transparent: straight colour c (as in the file) over the background, a = 100/255
    a, bg = 100 / 255, torch.tensor([1.0, 0.0, 0.0])
    expect = rimg[: H // 2, W // 2:] * a + (1 - a) * bg
    assert float((img[: H // 2, W // 2:] - expect).abs().max()) <= 0.5 / 255 + 1e-6
    half = load_scene(bl, cache_dir=tmp_path / "c", resolution=2, background=(1.0, 0.0, 0.0))
    # resized (premultiplied area average): the 2x2 block mean of the full-size composite
    full = s.image(s.train_cameras[2]).numpy().reshape(H // 2, 2, W // 2, 2, 3).mean(axis=(1, 3))
    assert np.abs(half.image(half.train_cameras[2]).numpy() - full).max() <= 1.01 / 255
    # seeded random init
    s_b = load_scene(bl, cache_dir=tmp_path / "c", seed=1, random_init_points=50, prefetch=False)
    s_a = load_scene(bl, cache_dir=tmp_path / "c", seed=1, random_init_points=50, prefetch=False)
    assert s_b.points.shape == (50, 3) and torch.equal(s_a.points, s_b.points)
    assert not torch.equal(s_a.points, s.points[:50])


def _check_undistorted(s, world):
    for cam in s.cameras:
        pin = pycolmap.Camera(model="PINHOLE", width=cam.width, height=cam.height,
                              params=[cam.fx, cam.fy, cam.cx, cam.cy])
        ref = world.render(pin, cam.viewmat.double().numpy())
        got = s.image(cam).numpy()
        raw = read_png_u8(s.view_source(cam).path) / 255.0
        assert psnr(got, ref) > 33 and psnr(got, ref) > psnr(raw, ref) + 4


@pytest.mark.parametrize("model,dist", [("SIMPLE_RADIAL", (0.1,)), ("RADIAL", (0.06, 0.02))])
def test_radial_captures_are_undistorted(tmp_path, model, dist):
    """Images rendered *through* a distorted model, then undistorted by the loader, match a
    pinhole rendering with the loader's intrinsics far better than the raw images do."""
    out = make_scene(tmp_path / "d", n_views=2, width=160, height=120, seed=4, n_points=50,
                     texture_detail=0.5, camera_model=model, distortion=dist)
    s = load_scene(out, cache_dir=tmp_path / "c", eval=False)
    assert s.protocol["camera_models"] == {model: 2}
    _check_undistorted(s, World(4, 0.5))


@pytest.mark.parametrize("model", ["SIMPLE_PINHOLE", "PINHOLE"])
def test_pinhole_models_are_not_resampled(tmp_path, model):
    out = make_scene(tmp_path / "p", n_views=2, width=40, height=30, n_points=50,
                     camera_model=model)
    s = load_scene(out, cache_dir=tmp_path / "c", eval=False)
    assert s.protocol["undistort"] is None
    c = s.cameras[1]
    f = 0.5 * 40 / np.tan(np.radians(55) / 2)
    assert (c.fx, c.fy, c.cx, c.cy) == pytest.approx((f, f, 20, 15))
    assert np.array_equal(u8(s.image(c)), read_png_u8(out / "images" / c.name))


def test_width_capped_at_1600(tmp_path):
    out = make_scene(tmp_path / "w", n_views=2, width=1700, height=40, n_points=20,
                     texture_detail=0.0)
    s = load_scene(out, cache_dir=tmp_path / "c", eval=False)
    c = s.cameras[0]
    assert (c.width, c.height) == (1600, 38)                 # round(40 * 1600 / 1700)
    f = 0.5 * 1700 / np.tan(np.radians(55) / 2)
    assert (c.fx, c.fy, c.cx, c.cy) == pytest.approx((f * 1600 / 1700, f * 38 / 40, 800, 19))
    assert s.image(c).shape == (38, 1600, 3)
    r1 = load_scene(out, cache_dir=tmp_path / "c", eval=False, resolution=1, prefetch=False)
    assert r1.cameras[0].width == 1700


def test_distorted_capture_is_undistorted(tmp_path):
    """An OPENCV capture with one camera per view, undistorted by the loader, matches a pinhole
    rendering (see above). Also read as an instant-ngp transforms.json with k1, k2, p1, p2:
    the same cameras and images."""
    dist = (0.08, -0.02, 0.002, -0.001)
    out = make_scene(tmp_path / "d", n_views=3, width=160, height=120, seed=2, n_points=100,
                     texture_detail=0.5, camera_model="OPENCV", distortion=dist,
                     shared_camera=False)
    s = load_scene(out, cache_dir=tmp_path / "c", eval=False)
    assert s.protocol["camera_models"] == {"OPENCV": 3} and s.protocol["undistort"] == "crop"
    _check_undistorted(s, World(2, 0.5))

    # the same capture as an instant-ngp transforms.json (single file: every-8th split)
    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    pc = rec.cameras[1]
    fx, fy, cx, cy = pc.params[:4]
    frames = [{"file_path": f"images/{c.name}", "transform_matrix": _c2w_opengl(c)}
              for c in s.cameras]
    meta = {"fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy, "w": 160, "h": 120,
            "k1": dist[0], "k2": dist[1], "p1": dist[2], "p2": dist[3], "frames": frames}
    (out / "transforms.json").write_text(json.dumps(meta))
    shutil.rmtree(out / "sparse")
    t = load_scene(out, cache_dir=tmp_path / "c")
    assert t.protocol["format"] == "blender" and [c.index for c in t.test_cameras] == [0]
    for a, b in zip(t.cameras, s.cameras):
        assert (a.fx, a.fy, a.cx, a.cy) == pytest.approx((b.fx, b.fy, b.cx, b.cy))
        assert torch.equal(t.image(a), s.image(b))


def test_keep_mode_leaves_blank_border(tmp_path):
    out = make_scene(tmp_path / "d", n_views=2, width=80, height=60, n_points=50,
                     camera_model="SIMPLE_RADIAL", distortion=(0.15,))
    keep = load_scene(out, cache_dir=tmp_path / "c", undistort="keep", eval=False)
    crop = load_scene(out, cache_dir=tmp_path / "c", eval=False)
    src_f = pycolmap.Reconstruction(str(out / "sparse" / "0")).cameras[1].params[0]
    ck, cc = keep.cameras[0], crop.cameras[0]
    assert ck.fx == pytest.approx(src_f) and cc.fx > ck.fx
    k_img, c_img = keep.image(ck).numpy(), crop.image(cc).numpy()
    assert np.all(k_img[0, 0] == 0)                          # pincushion corner: blank
    assert c_img.sum(-1).min() > 0                           # cropped: no blank pixel
