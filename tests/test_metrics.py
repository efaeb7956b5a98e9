"""Metrics against hand-computed values: uint8 PSNR, SSIM (3DGS's and scikit-image's), LPIPS
plumbing."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from baseline.eval.metrics import (LPIPS, LPIPS_UNAVAILABLE, load_lpips, psnr, ssim,
                                   ssim_skimage, to_uint8)

torch.set_num_threads(1)


def test_psnr_constant_offset():
    gt = np.full((8, 9, 3), 100, np.uint8)
    img = np.full((8, 9, 3), 110, np.uint8)
    assert psnr(img, gt) == pytest.approx(10 * math.log10(255 ** 2 / 100))     # 28.1308 dB
    assert psnr(img / 255.0, gt / 255.0) == pytest.approx(28.130803608679106)
    assert psnr(torch.from_numpy(img / 255.0).float(), gt) == pytest.approx(28.130803608679106)
    # one channel off by 3 on half the pixels: mse = 9 / 2 / 3
    img2 = gt.copy()
    img2[:4, :, 1] += 3
    assert psnr(img2, gt) == pytest.approx(10 * math.log10(255 ** 2 / (9 * 36 / 216)))
    assert psnr(gt, gt) == math.inf


def test_uint8_rounding():
    gt = np.full((4, 4, 3), 100 / 255)
    assert psnr(gt + 0.49 / 255, gt) == math.inf             # rounds to the same uint8
    assert psnr(gt + 0.51 / 255, gt) == pytest.approx(10 * math.log10(255 ** 2))   # off by 1
    over = np.full((4, 4, 3), 1.7)
    assert np.all(to_uint8(over) == 255) and np.all(to_uint8(-over) == 0)
    assert psnr(over, np.ones((4, 4, 3))) == math.inf        # clamped before rounding
    assert to_uint8(np.array([[[0.5 / 255, 1.5 / 255, 127.5 / 255]]])).tolist() == [[[0, 2, 128]]]
    with pytest.raises(ValueError):
        psnr(np.zeros((4, 4, 3)), np.zeros((4, 5, 3)))


def _window() -> np.ndarray:
    x = np.arange(-5, 6)
    g = np.exp(-x ** 2 / (2 * 1.5 ** 2))
    g /= g.sum()
    return np.outer(g, g)


def ssim_direct(a: np.ndarray, b: np.ndarray) -> float:
    """scikit-image's SSIM written out: 11x11 Gaussian window (sigma 1.5, normalized),
    population moments, averaged over every window that lies inside the image and over
    channels."""
    win = _window()
    C1, C2 = (0.01 * 255) ** 2, (0.03 * 255) ** 2
    H, W, C = a.shape
    vals = []
    for c in range(C):
        for i in range(5, H - 5):
            for j in range(5, W - 5):
                pa = a[i - 5:i + 6, j - 5:j + 6, c].astype(np.float64)
                pb = b[i - 5:i + 6, j - 5:j + 6, c].astype(np.float64)
                ma, mb = (win * pa).sum(), (win * pb).sum()
                va = (win * pa * pa).sum() - ma * ma
                vb = (win * pb * pb).sum() - mb * mb
                cov = (win * pa * pb).sum() - ma * mb
                vals.append(((2 * ma * mb + C1) * (2 * cov + C2))
                            / ((ma * ma + mb * mb + C1) * (va + vb + C2)))
    return float(np.mean(vals))


def ssim_3dgs_direct(a: np.ndarray, b: np.ndarray) -> float:
    """3DGS's SSIM written out, pixel by pixel: the images / 255, the 11x11 Gaussian window
    (sigma 1.5) over every pixel with the pixels outside the image read as 0 (conv2d's zero
    padding: the window is not renormalized), C1 = 0.01^2, C2 = 0.03^2, the map averaged over
    every pixel and channel."""
    win = _window()
    C1, C2 = 0.01 ** 2, 0.03 ** 2
    H, W, C = a.shape
    pa_all = np.zeros((H + 10, W + 10, C))
    pb_all = np.zeros((H + 10, W + 10, C))
    pa_all[5:-5, 5:-5] = a / 255.0
    pb_all[5:-5, 5:-5] = b / 255.0
    vals = []
    for c in range(C):
        for i in range(H):
            for j in range(W):
                pa = pa_all[i:i + 11, j:j + 11, c]
                pb = pb_all[i:i + 11, j:j + 11, c]
                ma, mb = (win * pa).sum(), (win * pb).sum()
                va = (win * pa * pa).sum() - ma * ma
                vb = (win * pb * pb).sum() - mb * mb
                cov = (win * pa * pb).sum() - ma * mb
                vals.append(((2 * ma * mb + C1) * (2 * cov + C2))
                            / ((ma * ma + mb * mb + C1) * (va + vb + C2)))
    return float(np.mean(vals))


def test_ssim_is_3dgs_ssim_over_the_whole_image():
    """The reported SSIM is 3DGS's: zero padding over the whole image, on random images of
    several sizes, against the formula written out; it differs from scikit-image's (which
    leaves the border out)."""
    rng = np.random.default_rng(7)
    for shape in ((11, 11, 3), (19, 23, 3), (16, 30, 1)):
        gt = rng.integers(0, 256, shape).astype(np.uint8)
        img = np.clip(gt + rng.normal(0, 25, gt.shape), 0, 255).round().astype(np.uint8)
        assert ssim(img, gt) == pytest.approx(ssim_3dgs_direct(img, gt), abs=1e-12)
        assert ssim(img, gt) == pytest.approx(ssim(gt, img), abs=1e-12)
    assert abs(ssim(img, gt) - ssim_skimage(img, gt)) > 1e-3
    flat = np.full((12, 14, 3), 200, np.uint8)
    assert ssim(flat, flat) == pytest.approx(1.0, abs=1e-12)
    # float input is rounded to uint8 first: +0.4/255 changes nothing
    assert ssim(gt / 255.0 + 0.4 / 255, gt) == ssim(gt, gt)
    with pytest.raises(ValueError):
        ssim(gt[:10, :10], gt[:10, :10])


def test_ssim_skimage_against_direct_computation():
    rng = np.random.default_rng(0)
    gt = rng.integers(0, 256, (19, 23, 3)).astype(np.uint8)
    img = np.clip(gt + rng.normal(0, 25, gt.shape), 0, 255).round().astype(np.uint8)
    assert ssim_skimage(img, gt) == pytest.approx(ssim_direct(img, gt), abs=1e-9)
    assert ssim_skimage(gt, gt) == 1.0
    assert ssim_skimage(img, gt) == pytest.approx(ssim_skimage(gt, img))
    assert 0.5 < ssim_skimage(img, gt) < 0.99
    assert ssim_skimage(gt / 255.0 + 0.4 / 255, gt) == 1.0
    with pytest.raises(ValueError):
        ssim_skimage(gt[:10, :10], gt[:10, :10])


def _random_lpips(seed=0) -> LPIPS:
    torch.manual_seed(seed)
    net = LPIPS()
    for m in net.modules():
        if isinstance(m, torch.nn.Conv2d):
            torch.nn.init.normal_(m.weight, std=0.05)
            if m.bias is not None:
                torch.nn.init.normal_(m.bias, std=0.01)
    for lin in net.lins:
        lin.weight.data.abs_()                                  # LPIPS heads are non-negative
    return net


def test_lpips_zero_for_identical_and_shapes():
    net = _random_lpips()
    rng = np.random.default_rng(1)
    x = rng.uniform(size=(2, 32, 40, 3)).astype(np.float32)
    y = np.clip(x + rng.normal(0, 0.2, x.shape), 0, 1).astype(np.float32)
    d0 = net(x[0], x[0])
    assert d0.shape == () and float(d0) == 0.0
    d = net(x, y)
    assert d.shape == (2,) and torch.all(d > 0)
    assert float(net(x[1], y[1])) == pytest.approx(float(d[1]), rel=1e-5)
    assert float(net(torch.from_numpy(x[1]), y[1])) == pytest.approx(float(d[1]), rel=1e-5)
    with pytest.raises(ValueError):
        net(x[0], x[0, :, :, :2])


def test_load_lpips(tmp_path):
    assert load_lpips(None) == (None, LPIPS_UNAVAILABLE)
    model, reason = load_lpips(tmp_path / "missing.pth")
    assert model is None and reason.startswith(LPIPS_UNAVAILABLE) and "missing.pth" in reason

    net = _random_lpips(3)
    sd = net.state_dict()
    # torchvision names for the backbone, lpips-package names for the heads
    tv = {k: v for k, v in sd.items() if k.startswith("features.")}
    tv.update({f"lin{k}.model.1.weight": sd[f"lins.{k}.weight"] for k in range(5)})
    torch.save(tv, tmp_path / "tv.pth")
    # the lpips package's own full-model names: net.slice{s}.{i}.*
    slices = {0: 1, 2: 1, 5: 2, 7: 2, 10: 3, 12: 3, 14: 3, 17: 4, 19: 4, 21: 4, 24: 5, 26: 5, 28: 5}
    lp = {f"net.slice{s}.{i}.{p}": sd[f"features.{i}.{p}"] for i, s in slices.items()
          for p in ("weight", "bias")}
    lp.update({f"lin{k}.model.1.weight": sd[f"lins.{k}.weight"] for k in range(5)})
    lp["scaling_layer.shift"] = torch.zeros(1, 3, 1, 1)
    torch.save(lp, tmp_path / "lp.pth")

    rng = np.random.default_rng(2)
    x = rng.uniform(size=(24, 24, 3)).astype(np.float32)
    y = rng.uniform(size=(24, 24, 3)).astype(np.float32)
    ref = float(net(x, y))
    for f in ("tv.pth", "lp.pth"):
        m, reason = load_lpips(tmp_path / f)
        assert reason is None and float(m(x, y)) == pytest.approx(ref, rel=1e-6)

    del tv["lin4.model.1.weight"]
    torch.save(tv, tmp_path / "bad.pth")
    with pytest.raises(ValueError, match="lins.4.weight"):
        load_lpips(tmp_path / "bad.pth")


def test_lpips_from_the_two_files_the_field_ships(tmp_path, monkeypatch):
    """The lpips package keeps only its linear layers (weights/v0.1/vgg.pth, keys
    lin{k}.model.1.weight) and torchvision the VGG16 backbone (vgg16-397923af.pth, features.* and
    classifier.*): given as LIN,VGG they are merged; both found on the machine (a package
    folder and the torch hub cache) they are used without being passed; nothing downloads."""
    import types

    import baseline.eval.metrics as metrics
    from baseline.cli import _lpips_weights
    from baseline.experiment import lpips_id

    net = _random_lpips(5)
    sd = net.state_dict()
    lin = {f"lin{k}.model.1.weight": sd[f"lins.{k}.weight"] for k in range(5)}
    vgg = {k: v for k, v in sd.items() if k.startswith("features.")}
    vgg["classifier.0.weight"] = torch.zeros(4, 4)          # torchvision's head: ignored
    pkg = tmp_path / "site" / "lpips"
    (pkg / "weights" / "v0.1").mkdir(parents=True)
    (pkg / "__init__.py").write_text("raise ImportError('needs torchvision')\n")
    torch.save(lin, pkg / "weights" / "v0.1" / "vgg.pth")
    hub = tmp_path / "hub"
    (hub / "checkpoints").mkdir(parents=True)
    torch.save(vgg, hub / "checkpoints" / "vgg16-397923af.pth")
    rng = np.random.default_rng(4)
    x = rng.uniform(size=(24, 24, 3)).astype(np.float32)
    y = rng.uniform(size=(24, 24, 3)).astype(np.float32)
    ref = float(net(x, y))
    pair = f"{pkg / 'weights/v0.1/vgg.pth'},{hub / 'checkpoints/vgg16-397923af.pth'}"
    m, reason = load_lpips(pair)
    assert reason is None and float(m(x, y)) == pytest.approx(ref, rel=1e-6)
    assert lpips_id(pair).count("bytes)") == 2
    with pytest.raises(ValueError, match="lack"):              # one half alone is not enough
        load_lpips(pkg / "weights/v0.1/vgg.pth")
    # found on the machine without being passed (the package is never imported)
    assert metrics.find_lpips_weights() is None or "vgg.pth" in metrics.find_lpips_weights()
    monkeypatch.syspath_prepend(str(tmp_path / "site"))
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(hub))
    import importlib
    importlib.invalidate_caches()
    assert metrics.find_lpips_weights() == pair
    assert _lpips_weights(types.SimpleNamespace(lpips_weights=None)) == pair
    assert _lpips_weights(types.SimpleNamespace(lpips_weights="mine.pth")) == "mine.pth"
