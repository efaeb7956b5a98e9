"""Real scenes from ../shared/data (skipped when absent): counts, sizes, intrinsics, undistortion.

Facts checked against /work/shared/data/README.md. Images are loaded at small scale and only a
few per scene, so the module runs in seconds.
"""
from __future__ import annotations

import math
import os
import warnings
from pathlib import Path

import numpy as np
import pycolmap
import pytest
import torch
from scipy import ndimage

from baseline.data import load_scene
from baseline.data.images import read_image
from baseline.data.undistort import undistort_map

torch.set_num_threads(1)


def _shared_data() -> Path:
    env = os.environ.get("PGS_SHARED_DATA")
    return Path(env) if env else Path(__file__).resolve().parents[1].parent / "shared" / "data"


DATA = _shared_data()


def scene_dir(name: str) -> Path:
    p = DATA / name
    if not p.is_dir():
        pytest.skip(f"real scene {name} not found under {DATA}")
    return p


def load(name, tmp_path, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")          # fern's LLFF name pairing warns by design
        return load_scene(scene_dir(name), cache_dir=tmp_path, prefetch=False, **kw)


def bilinear(arr: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Sample arr [h, w] or [h, w, c] at continuous pixel coords q [N, 2] (centres at +0.5)."""
    coords = np.stack([q[:, 1] - 0.5, q[:, 0] - 0.5])
    if arr.ndim == 2:
        return ndimage.map_coordinates(arr, coords, order=1, mode="nearest")
    return np.stack([ndimage.map_coordinates(arr[..., k], coords, order=1, mode="nearest")
                     for k in range(arr.shape[2])], 1)


def project(cam, X):
    """Pinhole projection with the loader's Camera: [N, 3] world -> ([M, 2] px, mask [N])."""
    V = cam.viewmat.double().numpy()
    Xc = X @ V[:3, :3].T + V[:3, 3]
    ok = Xc[:, 2] > 0.1
    z = np.where(ok, Xc[:, 2], 1.0)
    p = np.stack([cam.fx * Xc[:, 0] / z + cam.cx, cam.fy * Xc[:, 1] / z + cam.cy], 1)
    ok &= (p[:, 0] > 1) & (p[:, 0] < cam.width - 1) & (p[:, 1] > 1) & (p[:, 1] < cam.height - 1)
    return p[ok], ok


# ----------------------------------------------------------------------------- counts and sizes
def test_truck(tmp_path):
    s = load("tandt_truck", tmp_path)                     # -1: 979 < 1600, original size
    assert len(s.train_cameras) + len(s.test_cameras) == 251
    assert len(s.test_cameras) == math.ceil(251 / 8) == 32
    assert [c.index for c in s.test_cameras] == list(range(0, 251, 8))
    names = [c.name for c in s.cameras]
    assert names == sorted(names)
    c = s.train_cameras[0]
    assert (c.width, c.height) == (979, 546)
    assert (c.fx, c.fy, c.cx, c.cy) == pytest.approx((581.92456757, 578.43562416, 489.5, 273.0))
    assert s.protocol["camera_models"] == {"PINHOLE": 251} and s.protocol["undistort"] is None
    assert s.points.shape == (56399, 3) and s.colors.shape == (56399, 3)
    assert 0 <= float(s.colors.min()) and float(s.colors.max()) <= 1
    centers = torch.stack([c.center for c in s.train_cameras]).double()
    assert s.extent == pytest.approx(1.1 * float((centers - centers.mean(0)).norm(dim=1).max()),
                                     rel=1e-6)

    s8 = load("tandt_truck", tmp_path, resolution=8)
    c8 = s8.train_cameras[0]
    assert (c8.width, c8.height) == (round(979 / 8), round(546 / 8)) == (122, 68)
    assert c8.fx == pytest.approx(581.92456757 * 122 / 979)
    assert c8.fy == pytest.approx(578.43562416 * 68 / 546)
    assert c8.cx == pytest.approx(489.5 * 122 / 979) and c8.cy == pytest.approx(273.0 * 68 / 546)
    img = s8.image(s8.test_cameras[1])
    assert img.shape == (68, 122, 3) and img.dtype == torch.float32
    assert 0.05 < float(img.mean()) < 0.95
    assert s8.protocol["image_folder"] == "images" and s8.protocol["image_size"] == [122, 68]


def test_fern_folders(tmp_path):
    s8 = load("llff_fern", tmp_path, images="images_8", undistort="keep")
    assert len(s8.cameras) == 20 and len(s8.test_cameras) == 3
    c = s8.cameras[0]
    assert (c.width, c.height) == (504, 378)
    # SIMPLE_RADIAL f = 3260.526, given at 4032x3024: scaled by 504/4032 = 378/3024 = 1/8
    assert (c.fx, c.fy, c.cx, c.cy) == pytest.approx((3260.5263 / 8, 3260.5263 / 8, 252, 189),
                                                     rel=1e-6)
    assert s8.protocol["camera_models"] == {"SIMPLE_RADIAL": 20}
    assert s8.image(c).shape == (378, 504, 3)

    crop = load("llff_fern", tmp_path, images="images_8")          # default: crop, no blank
    cc = crop.cameras[0]
    assert (cc.width, cc.height, cc.cx, cc.cy) == (504, 378, 252, 189)
    assert 1.0 < cc.fx / c.fx < 1.03                  # k1 = 0.0198 is pincushion: zoom in a bit
    img = crop.image(cc).numpy()
    assert img[0].min(axis=-1).max() > 0 and img[:, 0].min(axis=-1).max() > 0   # no blank edges

    s16 = load("llff_fern", tmp_path, images="images_16")
    c16 = s16.cameras[0]
    assert (c16.width, c16.height) == (252, 189)
    assert c16.fx == pytest.approx(cc.fx / 2, rel=1e-9)
    # images_16 names (IMG_4026.png...) differ from the model's (image000.png...): sorted pairing
    assert "sorted order" in s16.protocol["name_mapping"]
    assert s16.view_source(c16).path.name == "IMG_4026.png"
    assert s16.image(c16).shape == (189, 252, 3)

    dflt = load("llff_fern", tmp_path)              # no images/: highest-resolution images_N
    assert dflt.protocol["image_folder"] == "images_8"
    assert load("llff_fern", tmp_path, resolution=8).protocol["image_folder"] == "images_8"


def test_lego(tmp_path):
    s = load("nerf_synthetic_lego", tmp_path)
    assert len(s.train_cameras) == 100 and len(s.test_cameras) == 25
    assert s.test_cameras[1].name == "test/r_8"        # every 8th of the 200 renders
    c = s.train_cameras[0]
    assert (c.width, c.height) == (800, 800)
    assert c.fx == pytest.approx(400 / math.tan(0.6911112070083618 / 2)) and c.cx == 400
    assert s.points.shape == (10000, 3) and float(s.points.abs().max()) <= 1.3
    # Blender camera 0 sits at +z looking down -z in OpenGL; in OpenCV it looks along +z_cam
    # towards the origin: the world origin projects near the image centre
    o = (c.viewmat @ torch.tensor([0.0, 0.0, 0.0, 1.0]))[:3]
    assert o[2] > 0
    assert abs(c.fx * o[0] / o[2] + c.cx - 400) < 80 and abs(c.fy * o[1] / o[2] + c.cy - 400) < 80
    # RGBA composited on the chosen background: transparent corners show it exactly
    black = load("nerf_synthetic_lego", tmp_path, resolution=8)
    white = load("nerf_synthetic_lego", tmp_path, resolution=8, background=(1.0, 1.0, 1.0))
    cb, cw = black.test_cameras[0], white.test_cameras[0]
    ib, iw = black.image(cb), white.image(cw)
    assert ib.shape == (100, 100, 3)
    assert torch.all(ib[0, 0] == 0) and torch.all(iw[0, 0] == 1)
    assert float((iw - ib).min()) >= -1e-6          # white bg only adds (1 - alpha)
    assert black.protocol["split"].startswith("from transforms_train")
    # full size, semi-transparent edges: straight colour from the file over the background
    wf = load("nerf_synthetic_lego", tmp_path, background=(1.0, 1.0, 1.0))
    cf = wf.test_cameras[0]
    raw = read_image(wf.view_source(cf).path)
    a = raw[..., 3:]
    assert ((a > 0) & (a < 1)).sum() > 1000
    expect = raw[..., :3] * a + (1 - a)
    assert np.abs(wf.image(cf).numpy() - expect).max() <= 0.5 / 255 + 1e-6
    noeval = load("nerf_synthetic_lego", tmp_path, resolution=8, eval=False)
    assert len(noeval.train_cameras) == 125 and not noeval.test_cameras


def test_beer(tmp_path):
    s = load("beer", tmp_path, resolution=4)
    assert len(s.cameras) == 71
    assert len({s.view_source(c).source.camera_id for c in s.cameras}) == 71
    assert s.protocol["camera_models"] == {"SIMPLE_RADIAL": 71}
    full = load("beer", tmp_path)
    assert all((c.width, c.height) == (720, 1280) for c in full.cameras)      # portrait
    c4 = s.cameras[5]
    assert (c4.width, c4.height) == (180, 320)
    assert c4.fx == pytest.approx(full.cameras[5].fx / 4) and c4.cy == pytest.approx(160)
    assert s.image(c4).shape == (320, 180, 3)


# ------------------------------------------------------------------------------ undistortion
def _reprojection(scene, name, n_views):
    """Per 3D point: pinhole projection -> loader's remap -> compare with pycolmap's projection
    of the same point through the distorted model (scaled to the source file)."""
    rec = pycolmap.Reconstruction(str(scene_dir(name) / "sparse" / "0"))
    by_name = {im.name: im for im in rec.images.values()}
    X = np.array([p.xyz for p in rec.points3D.values()])
    errs = []
    for cam in scene.cameras[:n_views]:
        vs = scene.view_source(cam)
        im = by_name[cam.name]
        w, h = vs.file_size
        p, ok = project(cam, X)
        q = p * [w / cam.width, h / cam.height]            # pinhole pixel at the file's scale
        mx, my = undistort_map(vs.source, vs.pinhole, (w, h))
        src = np.stack([bilinear(mx, q), bilinear(my, q)], 1)
        pc = rec.cameras[im.camera_id]
        T = np.asarray(im.cam_from_world().matrix())
        ref = pc.img_from_cam(X[ok] @ T[:3, :3].T + T[:3, 3]) * [w / pc.width, h / pc.height]
        errs.append(np.linalg.norm(src - ref, axis=1) * cam.width / w)   # in loaded-image px
    return np.concatenate(errs)


@pytest.mark.parametrize("name,kw", [
    ("llff_fern", dict(images="images_8")),
    ("llff_fern", dict(images="images_8", undistort="keep")),
    ("llff_fern", dict(images="images_16")),
    ("beer", dict(resolution=4)),
    ("beer", dict(resolution=1)),
])
def test_undistortion_matches_pycolmap_projection(tmp_path, name, kw):
    s = load(name, tmp_path, **kw)
    err = _reprojection(s, name, n_views=4)
    assert len(err) > 1000
    print(f"{name} {kw}: mean reprojection error {err.mean():.2e} px, max {err.max():.2e} px")
    assert err.mean() < 0.1 and err.max() < 0.1


@pytest.mark.parametrize("name,kw", [("llff_fern", dict(images="images_8")),
                                     ("beer", dict(resolution=1))])
def test_undistorted_pixels_come_from_the_remap(tmp_path, name, kw):
    """The cached image is the source sampled through the map (to uint8 rounding), and differs
    clearly from the unwarped source (the control shows the test can fail)."""
    s = load(name, tmp_path, **kw)
    for cam in s.cameras[:2]:
        vs = s.view_source(cam)
        und = s.image(cam).numpy()
        src = read_image(vs.path)[..., :3]
        mx, my = undistort_map(vs.source, vs.pinhole, vs.file_size)
        rng = np.random.default_rng(0)
        i = rng.integers(0, cam.height, 3000)
        j = rng.integers(0, cam.width, 3000)
        q = np.stack([mx[i, j], my[i, j]], 1)
        expect = bilinear(src, q)
        assert np.abs(und[i, j] - expect).max() <= 0.5 / 255 + 1e-6
        control = np.abs(und[i, j] - src[i, j]).mean()
        assert control > 10 * np.abs(und[i, j] - expect).mean()


def test_beer_keypoints_agree_after_undistortion(tmp_path):
    """beer's 2D observations, undistorted with pycolmap and mapped into the loader's pinhole
    camera, sit where the loader's camera projects their 3D points: the mean error matches the
    model's own reprojection error (measured by pycolmap in the distorted image) up to the zoom."""
    s = load("beer", tmp_path)
    rec = pycolmap.Reconstruction(str(scene_dir("beer") / "sparse" / "0"))
    by_name = {im.name: im for im in rec.images.values()}
    ours, theirs = [], []
    for cam in s.cameras[::7]:
        im = by_name[cam.name]
        pc = rec.cameras[im.camera_id]
        obs = [(p.xy, rec.points3D[p.point3D_id].xyz) for p in im.points2D if p.has_point3D()]
        kp = np.array([o[0] for o in obs])
        X = np.array([o[1] for o in obs])
        V = cam.viewmat.double().numpy()
        Xc = X @ V[:3, :3].T + V[:3, 3]
        p = np.stack([cam.fx * Xc[:, 0] / Xc[:, 2] + cam.cx, cam.fy * Xc[:, 1] / Xc[:, 2] + cam.cy], 1)
        n = pc.cam_from_img(kp)
        kpu = np.stack([cam.fx * n[:, 0] + cam.cx, cam.fy * n[:, 1] + cam.cy], 1)
        ours.append(np.linalg.norm(p - kpu, axis=1))
        T = np.asarray(im.cam_from_world().matrix())
        theirs.append(np.linalg.norm(pc.img_from_cam(X @ T[:3, :3].T + T[:3, 3]) - kp, axis=1))
    ours, theirs = np.concatenate(ours), np.concatenate(theirs)
    print(f"beer keypoints: ours {ours.mean():.3f} px (undistorted), pycolmap "
          f"{theirs.mean():.3f} px (distorted), {len(ours)} observations")
    assert len(ours) > 1000
    assert theirs.mean() * 0.97 < ours.mean() < theirs.mean() * 1.1
