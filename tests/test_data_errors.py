"""Bad inputs: each raises SceneError (a ValueError) whose message names the file or camera."""
from __future__ import annotations

import json
import shutil

import numpy as np
import pycolmap
import pytest
import torch

from baseline.data import SceneError, load_scene
from baseline.data.images import write_png_atomic
from baseline.data.synthetic import make_scene

torch.set_num_threads(1)

SMALL = dict(n_views=6, width=48, height=36, n_points=100)


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    return make_scene(tmp_path_factory.mktemp("err") / "scene", **SMALL)


@pytest.fixture
def scene(base, tmp_path):
    return shutil.copytree(base, tmp_path / "scene")


def load(path, tmp_path, **kw):
    return load_scene(path, cache_dir=tmp_path / "cache", **kw)


def test_scene_error_is_value_error():
    assert issubclass(SceneError, ValueError)


def test_missing_image(scene, tmp_path):
    (scene / "images" / "view_003.png").unlink()
    with pytest.raises(SceneError) as e:
        load(scene, tmp_path)
    msg = str(e.value)
    assert str(scene / "images" / "view_003.png") in msg and "images.bin" in msg


def test_unreadable_image(scene, tmp_path):
    (scene / "images" / "view_002.png").write_bytes(b"this is not a png" * 10)
    with pytest.raises(SceneError) as e:
        load(scene, tmp_path)
    assert str(scene / "images" / "view_002.png") in str(e.value)


def test_truncated_image(scene, tmp_path):
    """Header intact, pixel data cut: fails when decoded (at prefetch, or at image())."""
    f = scene / "images" / "view_004.png"
    data = f.read_bytes()
    f.write_bytes(data[: len(data) // 2])
    with pytest.raises(SceneError, match="view_004.png"):
        load(scene, tmp_path)
    s = load(scene, tmp_path, prefetch=False)
    s.image(s.cameras[3])                                    # other images are fine
    with pytest.raises(SceneError, match="view_004.png"):
        s.image(s.cameras[4])


@pytest.mark.parametrize("model,dist", [("OPENCV_FISHEYE", (0.05, 0.0, 0.0, 0.0)),
                                        ("SIMPLE_RADIAL_FISHEYE", (0.05,))])
def test_unsupported_camera_model(tmp_path, model, dist):
    out = make_scene(tmp_path / "fish", camera_model=model, distortion=dist, **SMALL)
    with pytest.raises(SceneError) as e:
        load(out, tmp_path)
    msg = str(e.value)
    assert "camera id 1" in msg and model in msg and "cameras.bin" in msg
    for ok in ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV"):
        assert ok in msg


def test_empty_point_cloud(scene, tmp_path):
    model = scene / "sparse" / "0"
    rec = pycolmap.Reconstruction(str(model))
    for pid in list(rec.point3D_ids()):
        rec.delete_point3D(pid)
    rec.write(str(model))
    with pytest.raises(SceneError) as e:
        load(scene, tmp_path)
    msg = str(e.value)
    assert str(model / "points3D.bin") in msg and "empty" in msg and "triangulat" in msg


def test_incomplete_model(scene, tmp_path):
    (scene / "sparse" / "0" / "points3D.bin").unlink()
    with pytest.raises(SceneError, match="points3D"):
        load(scene, tmp_path)


@pytest.mark.parametrize("content", ["empty", "junk"])
def test_unknown_layout(tmp_path, content):
    d = tmp_path / "notascene"
    d.mkdir()
    if content == "junk":
        (d / "readme.txt").write_text("hello")
        (d / "images").mkdir()
    with pytest.raises(SceneError) as e:
        load(d, tmp_path)
    msg = str(e.value)
    assert str(d) in msg and "COLMAP" in msg and "sparse/0" in msg and "transforms" in msg


def test_missing_folder(tmp_path):
    with pytest.raises(SceneError, match="does not exist"):
        load(tmp_path / "nope", tmp_path)


def test_image_with_wrong_aspect(scene, tmp_path):
    write_png_atomic(scene / "images" / "view_001.png", np.zeros((48, 36, 3), np.uint8))
    with pytest.raises(SceneError) as e:
        load(scene, tmp_path)
    assert "view_001.png" in str(e.value) and "48x36" in str(e.value)


def test_downscaled_sizes_fit_their_calibration():
    from baseline.data.scene import fits_calibration

    assert fits_calibration(245, 136, 979, 546)      # truck at 1/4, 136.5 rounded down
    assert fits_calibration(245, 137, 979, 546)      # ... rounded up (ImageMagick)
    assert fits_calibration(489, 273, 979, 546) and fits_calibration(979, 546, 979, 546)
    assert fits_calibration(504, 378, 4032, 3024)    # fern images_8
    assert not fits_calibration(136, 245, 979, 546)  # rotated
    assert not fits_calibration(245, 130, 979, 546)  # cropped by 6 px
    assert not fits_calibration(36, 48, 48, 36)


def test_missing_image_folder(scene, tmp_path):
    with pytest.raises(SceneError, match="images_4"):
        load(scene, tmp_path, images="images_4")
    shutil.rmtree(scene / "images")
    with pytest.raises(SceneError, match="no images/"):
        load(scene, tmp_path)


def _blender(tmp_path, meta_extra=None, frame_file="./train/r_0"):
    d = tmp_path / "bl"
    (d / "train").mkdir(parents=True)
    write_png_atomic(d / "train" / "r_0.png", np.zeros((8, 8, 4), np.uint8))
    meta = {"camera_angle_x": 0.7, "frames": [{"file_path": frame_file,
                                                "transform_matrix": np.eye(4).tolist()}]}
    meta.update(meta_extra or {})
    (d / "transforms_train.json").write_text(json.dumps(meta))
    return d


@pytest.mark.filterwarnings("ignore:all training cameras share one centre")
def test_blender_errors(tmp_path):
    d = _blender(tmp_path / "a", frame_file="./train/r_9")
    with pytest.raises(SceneError) as e:
        load(d, tmp_path)
    assert "r_9" in str(e.value) and "transforms_train.json" in str(e.value)

    d = _blender(tmp_path / "b")
    meta = json.loads((d / "transforms_train.json").read_text())
    del meta["camera_angle_x"]
    (d / "transforms_train.json").write_text(json.dumps(meta))
    with pytest.raises(SceneError, match="transforms_train.json.*intrinsics"):
        load(d, tmp_path)

    d = _blender(tmp_path / "c", {"is_fisheye": True})
    with pytest.raises(SceneError, match="not supported"):
        load(d, tmp_path)

    d = _blender(tmp_path / "d")
    with pytest.raises(SceneError, match="COLMAP scenes only"):
        load(d, tmp_path, images="images_8")
    assert len(load(d, tmp_path).train_cameras) == 1         # the valid one loads


MALFORMED = [
    ("top-level list", lambda m: [m], "top level must be an object"),
    ("camera_angle_x null", lambda m: {**m, "camera_angle_x": None}, "'camera_angle_x' must be"),
    ("camera_angle_x 0", lambda m: {**m, "camera_angle_x": 0}, "'camera_angle_x' = 0.0 is out"),
    ("camera_angle_x string", lambda m: {**m, "camera_angle_x": "wide"}, "'camera_angle_x'"),
    ("camera_model null", lambda m: {**m, "camera_model": None}, None),      # = absent: loads
    ("camera_model int", lambda m: {**m, "camera_model": 3}, "'camera_model' must be a string"),
    ("fl_x negative", lambda m: {**m, "fl_x": -5.0}, "'fl_x'"),
    ("w zero", lambda m: {**m, "fl_x": 5.0, "w": 0}, "'w'"),
    ("k1 NaN", lambda m: {**m, "k1": float("nan")}, "'k1'"),
    ("frame not an object", lambda m: {**m, "frames": [3]}, "frame 0"),
    ("file_path null", lambda m: {**m, "frames": [{**m["frames"][0], "file_path": None}]},
     "frame 0: 'file_path'"),
    ("matrix NaN", lambda m: {**m, "frames": [{**m["frames"][0], "transform_matrix":
                                              [[float("nan")] * 4] * 4}]}, "frame 0: .*NaN"),
    ("matrix Inf", lambda m: {**m, "frames": [{**m["frames"][0], "transform_matrix":
                                              [[1, 0, 0, float("inf")], [0, 1, 0, 0],
                                               [0, 0, 1, 0], [0, 0, 0, 1]]}]}, "NaN or Inf"),
    ("matrix ragged", lambda m: {**m, "frames": [{**m["frames"][0], "transform_matrix":
                                                 [[1, 0], [0, 1, 0, 0]]}]}, "transform_matrix"),
    ("matrix singular", lambda m: {**m, "frames": [{**m["frames"][0], "transform_matrix":
                                                    np.zeros((4, 4)).tolist()}]}, "singular"),
    ("matrix 2x4", lambda m: {**m, "frames": [{**m["frames"][0], "transform_matrix":
                                               np.eye(4)[:2].tolist()}]}, "3x4 or 4x4"),
]


@pytest.mark.filterwarnings("ignore:all training cameras share one centre")
@pytest.mark.parametrize("name,edit,error", MALFORMED, ids=[m[0] for m in MALFORMED])
def test_malformed_transforms_give_a_named_error(tmp_path, name, edit, error):
    """Every malformed transforms.json is one SceneError naming the file (and the frame and key
    where there is one), never another exception; NaN allowed into JSON by Python's encoder."""
    d = _blender(tmp_path / "m")
    js = d / "transforms_train.json"
    js.write_text(json.dumps(edit(json.loads(js.read_text()))))
    if error is None:
        assert len(load(d, tmp_path).train_cameras) == 1
        return
    with pytest.raises(SceneError, match=error) as e:
        load(d, tmp_path)
    assert "transforms_train.json" in str(e.value)


def test_colmap_counts_are_checked_before_pycolmap_allocates(scene, tmp_path):
    """A points3D.bin declaring 2^62 points (or a track, or 2D points, past its bytes) is
    refused by name at once, before pycolmap sizes an allocation from it."""
    import struct
    import time

    pts = scene / "sparse" / "0" / "points3D.bin"
    raw = bytearray(pts.read_bytes())
    good = bytes(raw)
    raw[0:8] = struct.pack("<Q", 1 << 62)
    pts.write_bytes(bytes(raw))
    t0 = time.perf_counter()
    with pytest.raises(SceneError, match="points3D.bin.*declares 4611686018427387904 records"):
        load(scene, tmp_path)
    assert time.perf_counter() - t0 < 30
    raw = bytearray(good)
    raw[8 + 43:8 + 51] = struct.pack("<Q", 1 << 40)             # the first point's track
    pts.write_bytes(bytes(raw))
    with pytest.raises(SceneError, match="point 0 declares a track of"):
        load(scene, tmp_path)
    pts.write_bytes(good)
    ims = scene / "sparse" / "0" / "images.bin"
    raw = bytearray(ims.read_bytes())
    nul = raw.index(b"\0", 8 + 64)
    raw[nul + 1:nul + 9] = struct.pack("<Q", 1 << 50)          # the first image's 2D points
    ims.write_bytes(bytes(raw))
    with pytest.raises(SceneError, match="image 0 declares .* 2D points"):
        load(scene, tmp_path)


def test_a_deeply_nested_transforms_file_is_a_named_error(tmp_path):
    d = _blender(tmp_path)
    (d / "transforms_train.json").write_text("[" * 100000 + "]" * 100000)
    with pytest.raises(SceneError, match="nested too deeply|cannot parse"):
        load(d, tmp_path)


def test_a_scene_without_a_training_view_is_a_named_error(tmp_path):
    one = make_scene(tmp_path / "one", n_views=1, width=48, height=36, n_points=50)
    with pytest.raises(SceneError, match="no training view"):
        load(one, tmp_path)
    sc = load(one, tmp_path, eval=False)
    assert len(sc.train_cameras) == 1 and not sc.test_cameras


def test_voxel_size_out_of_range_is_refused():
    from baseline.config import ConfigError, build_config

    for bad in ("-0.1", "1e-12", "1e9"):
        with pytest.raises(ConfigError, match="model.voxel_size"):
            build_config([], [f"model.voxel_size={bad}"])
    assert build_config([], ["model.voxel_size=0"]).model.voxel_size == 0
